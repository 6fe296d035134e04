"""Subcommand groups of the command line (``eyeserver sim``, ``eyeserver bench``)."""

from __future__ import annotations

import argparse
from typing import TypeAlias

#: The object ``ArgumentParser.add_subparsers()`` returns.
Subparsers: TypeAlias = "argparse._SubParsersAction[argparse.ArgumentParser]"
