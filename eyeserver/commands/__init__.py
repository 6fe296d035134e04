"""Subcommand groups of the command line (``eyeserver sim``, ``eyeserver bench``)."""

from __future__ import annotations

import argparse
import sys
import time
from typing import TypeAlias

#: The object ``ArgumentParser.add_subparsers()`` returns.
Subparsers: TypeAlias = "argparse._SubParsersAction[argparse.ArgumentParser]"


def progress(message: str) -> None:
    """Report progress of a long command on stderr, time-stamped (stdout stays for results)."""
    print(f"[{time.strftime('%H:%M:%S')}] {message}", file=sys.stderr, flush=True)
