#!/usr/bin/env bash
# Set up if needed, then run the daemon: `bash scripts/serve.sh [--host H] [--port P] [--config FILE]`.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

bash scripts/setup.sh
exec .venv/bin/eyeserver serve "$@"
