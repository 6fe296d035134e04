#!/usr/bin/env bash
# Install eyeserver as a systemd service on the room PC. Run as root from a checkout:
#
#     sudo deploy/install.sh            # install or upgrade, then (re)start the service
#
# Creates the system user "eyeserver", a virtual environment in /opt/eyeserver/venv with this
# checkout installed into it, /etc/eyeserver/{eyeserver.toml,eyeserver.env} (kept if present),
# the unit /etc/systemd/system/eyeserver.service, the Debian packages of the device drivers
# (scripts/system-packages.sh) and the udev rules of the devices (99-eyeserver.rules).
# Idempotent. See deploy/README.md.
set -euo pipefail

PREFIX=/opt/eyeserver
CONFIG_DIR=/etc/eyeserver
UNIT=/etc/systemd/system/eyeserver.service
SERVICE_USER=eyeserver
PYTHON=${PYTHON:-python3}

here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
source_dir=$(dirname "$here")

say() { printf 'install.sh: %s\n' "$*"; }
die() { say "error: $*" >&2; exit 1; }

[[ $(id -u) -eq 0 ]] || die "run as root (sudo $0)"
command -v systemctl >/dev/null || die "systemd is needed"
"$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 11))' \
    || die "$PYTHON is older than 3.11"

if ! id -u "$SERVICE_USER" >/dev/null 2>&1; then
    say "creating the system user $SERVICE_USER"
    useradd --system --user-group --home-dir /var/lib/eyeserver --no-create-home \
        --shell /usr/sbin/nologin "$SERVICE_USER"
fi
for group in video dialout; do  # cameras and serial ports
    if getent group "$group" >/dev/null; then
        usermod --append --groups "$group" "$SERVICE_USER"
    fi
done

# Debian packages of the real devices' drivers (Aravis for the GenICam cameras, PyGObject's
# build headers).
bash "$source_dir/scripts/system-packages.sh"
install -m 0644 "$here/99-eyeserver.rules" /etc/udev/rules.d/99-eyeserver.rules
udevadm control --reload 2>/dev/null && udevadm trigger 2>/dev/null || true

say "installing into $PREFIX/venv"
install -d -m 0755 "$PREFIX"
if [[ ! -x $PREFIX/venv/bin/python ]]; then
    "$PYTHON" -m venv "$PREFIX/venv"
fi
"$PREFIX/venv/bin/python" -m pip install --quiet --upgrade pip
# Exactly the versions the release was tested with (docs/soup.md, scripts/soup.py).
"$PREFIX/venv/bin/python" -m pip install --quiet --constraint "$here/constraints.txt" \
    "$source_dir[basler,genicam]"
install -m 0644 "$source_dir/README.md" "$PREFIX/README.md"

install -d -m 0750 -g "$SERVICE_USER" "$CONFIG_DIR"
if [[ ! -e $CONFIG_DIR/eyeserver.toml ]]; then
    install -m 0640 -g "$SERVICE_USER" "$here/eyeserver.toml" "$CONFIG_DIR/eyeserver.toml"
    say "wrote $CONFIG_DIR/eyeserver.toml (edit it: host, TLS, retention)"
else
    say "kept $CONFIG_DIR/eyeserver.toml; the current example is $here/eyeserver.toml"
fi
if [[ ! -e $CONFIG_DIR/eyeserver.env ]]; then
    umask 077
    operator=$("$PYTHON" -c 'import secrets; print(secrets.token_urlsafe(24))')
    physicist=$("$PYTHON" -c 'import secrets; print(secrets.token_urlsafe(24))')
    printf '# Secrets of the eyeserver service (mode 0600).\nEYESERVER_TOKENS=operator:%s,physicist:%s\n' \
        "$operator" "$physicist" >"$CONFIG_DIR/eyeserver.env"
    chmod 0600 "$CONFIG_DIR/eyeserver.env"
    say "wrote $CONFIG_DIR/eyeserver.env with a new token per role (root only)"
fi

install -m 0644 "$here/eyeserver.service" "$UNIT"
systemctl daemon-reload
systemctl enable eyeserver.service
systemctl restart eyeserver.service
say "started; check it with: systemctl status eyeserver; journalctl -u eyeserver -f"
