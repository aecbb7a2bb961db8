"""``aeromag ARGS`` in this interpreter: the console script's entry point (flows.cli.main),
its exit code and what it wrote to stdout and stderr, as ``subprocess.run`` returns them.

For commands that run no Prefect flow: each call spares a ~2 s interpreter start and import
(numpy, scipy, matplotlib). What a separate process would show on stderr shows here too:
warnings (under Python's default filters, not pytest's capture) and log records of WARNING
and above that reach the root logger. The console script as a process of its own
(``python -m flows.cli``) stays covered where flows run: tests/test_flow.py (``process``
without a server), tests/test_bad_input_flows.py (``process``, ``reprocess``),
tests/test_operations.py (``config``, ``reprocess``, ``serve``), tests/test_campaign.py."""

from __future__ import annotations

import contextlib
import io
import logging
import subprocess
import sys
import warnings

# Python's own default warning filters (the order of warnings.filters at start-up)
DEFAULT_FILTERS = [
    ("default", DeprecationWarning, "__main__"),
    ("ignore", DeprecationWarning, ""),
    ("ignore", PendingDeprecationWarning, ""),
    ("ignore", ImportWarning, ""),
    ("ignore", ResourceWarning, ""),
]


def run(*args: str) -> subprocess.CompletedProcess:
    from flows.cli import main

    out, err = io.StringIO(), io.StringIO()
    argv, sys.argv = sys.argv, ["aeromag", *args]
    root = logging.getLogger()
    handler = logging.StreamHandler(err)
    handler.setLevel(logging.WARNING)
    code: int | str | None = 0
    try:
        with (
            contextlib.redirect_stdout(out),
            contextlib.redirect_stderr(err),
            warnings.catch_warnings(),
        ):
            warnings.resetwarnings()
            for action, category, module in reversed(DEFAULT_FILTERS):
                warnings.filterwarnings(action, category=category, module=module)
            warnings.showwarning = _to_stderr
            root.addHandler(handler)
            main()
    except SystemExit as exc:
        code = exc.code
    finally:
        root.removeHandler(handler)
        sys.argv = argv
    if not isinstance(code, int):  # sys.exit(None) / sys.exit("message"), as Python maps them
        code = 0 if code is None else 1
    return subprocess.CompletedProcess(["aeromag", *args], code, out.getvalue(), err.getvalue())


def _to_stderr(message, category, filename, lineno, file=None, line=None) -> None:
    sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))
