"""Write the blocking client from the asyncio one (or check that it is current).

Usage, from the repository root::

    python clients/python/scripts/unasync.py           # writes _client_sync.py, _streams_sync.py
    python clients/python/scripts/unasync.py --check   # exit 1 when they are out of date

The asyncio code (``_client_async.py``, ``_streams_async.py``) is the one written by hand; the
blocking twin is the same code with the asyncio words taken out (``async def`` → ``def``,
``await x`` → ``x``, ``AsyncFoo`` → ``Foo``, ``__aenter__`` → ``__enter__``, ``_io_async`` →
``_io_sync``, …), as httpcore does. So the two clients cannot drift apart: :func:`render` is
what the tests call to check it.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "src" / "eyeserver_client"

#: (asyncio source, blocking output, the output's module docstring)
FILES = (
    ("_client_async.py", "_client_sync.py",
     '"""The blocking client of the eyeserver API (:class:`Client`).\n\n'
     "Generated from ``_client_async.py`` by ``scripts/unasync.py``: do not edit (edit that\n"
     'file and run the script).\n"""'),
    ("_streams_async.py", "_streams_sync.py",
     '"""Reading the daemon\'s WebSocket streams, reconnecting and keeping the place by '
     "``seq``.\n\n"
     "Generated from ``_streams_async.py`` by ``scripts/unasync.py``: do not edit (edit that\n"
     'file and run the script).\n"""'),
)

#: Applied in order, each a regular expression and its replacement.
RULES: tuple[tuple[str, str], ...] = (
    (r"\b_io_async\b", "_io_sync"),
    (r"\b_streams_async\b", "_streams_sync"),
    (r"\b_client_async\b", "_client_sync"),
    (r"\basync def\b", "def"),
    (r"\basync with\b", "with"),
    (r"\basync for\b", "for"),
    (r"\bawait ", ""),
    (r"\b__aenter__\b", "__enter__"),
    (r"\b__aexit__\b", "__exit__"),
    (r"\b__aiter__\b", "__iter__"),
    (r"\b__anext__\b", "__next__"),
    (r"\bStopAsyncIteration\b", "StopIteration"),
    (r"\baclose\b", "close"),
    (r"\baread\b", "read"),
    (r"\bAsync([A-Z]\w*)", r"\1"),
    (r"\(asyncio\)", "(blocking)"),
)


def render(source: str, docstring: str) -> str:
    """The blocking twin of the asyncio module ``source``, with ``docstring`` as its own."""
    if not source.startswith('"""'):
        raise ValueError("the asyncio module must start with its docstring")
    end = source.index('"""', 3) + 3
    lines = source[end:].split("\n")
    for n, line in enumerate(lines):
        changed = line
        for pattern, replacement in RULES:
            changed = re.sub(pattern, replacement, changed)
        lines[n] = changed
        shorter = len(line) - len(changed)
        if shorter > 0 and _balance(changed) > 0:
            # The lines continuing this one were aligned under its brackets: move them too.
            column = _same_start(line, changed) + shorter
            depth = _balance(changed)
            for following in range(n + 1, len(lines)):
                text = lines[following]
                if len(text) - len(text.lstrip(" ")) >= column:
                    lines[following] = text[shorter:]
                depth += _balance(text)
                if depth <= 0:
                    break
    return docstring + "\n".join(lines)


def _same_start(a: str, b: str) -> int:
    """How many leading characters ``a`` and ``b`` share."""
    return next((n for n, (x, y) in enumerate(zip(a, b, strict=False)) if x != y),
                min(len(a), len(b)))


def _balance(line: str) -> int:
    """Brackets opened minus closed on a line of code (string literals left out)."""
    code = re.sub(r'"[^"]*"|\'[^\']*\'', "", line.split("#", 1)[0])
    return sum(code.count(c) for c in "([{") - sum(code.count(c) for c in ")]}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true",
                        help="do not write; exit 1 when a blocking module is out of date")
    args = parser.parse_args(argv)
    stale = []
    for source, output, docstring in FILES:
        text = render((PACKAGE / source).read_text(encoding="utf-8"), docstring)
        target = PACKAGE / output
        current = target.read_text(encoding="utf-8") if target.exists() else ""
        if current == text:
            continue
        if args.check:
            stale.append(output)
        else:
            target.write_text(text, encoding="utf-8")
            print(f"wrote {target}", file=sys.stderr)
    if stale:
        print(f"out of date: {', '.join(stale)}; run {Path(__file__).name} without --check",
              file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
