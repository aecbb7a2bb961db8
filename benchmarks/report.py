"""Shared ending of every benchmark: a Markdown table and a non-zero exit on wrong values."""

from __future__ import annotations

import sys


def finish(rows: list[tuple[str, str]], errors: list[str]) -> int:
    """Print ``rows`` as a two-column Markdown table, each error on stderr; exit status."""
    print("| benchmark | result |\n|---|---|")
    for key, value in rows:
        print(f"| {key} | {value} |")
    for e in errors:
        print(f"WRONG: {e}", file=sys.stderr)
    return 1 if errors else 0
