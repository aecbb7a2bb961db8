"""The one user-facing error type.

Every problem a user can cause (bad file, missing channel, wrong units ...) is raised as
:class:`AeromagError`, whose text is a single line naming the file, the channel and the
problem. The CLI prints that line and exits non-zero; it never shows a traceback.
"""

from __future__ import annotations

import errno
import logging
from collections import OrderedDict
from pathlib import Path


class AeromagError(Exception):
    """A problem with user input, reported as ``FILE: CHANNEL: problem``."""

    def __init__(self, problem: str, *, file: str | Path | None = None, channel: str | None = None):
        self.problem = " ".join(str(problem).split())  # always one line
        self.file = str(file) if file is not None else None
        self.channel = channel
        super().__init__(str(self))

    def __str__(self) -> str:
        parts = [p for p in (self.file, self.channel) if p]
        return ": ".join([*parts, self.problem])


def missing_file(path: str | Path) -> AeromagError:
    """The one line for an input ``path`` that is not a readable file: a folder given where
    a file is wanted, or nothing there."""
    if Path(path).is_dir():
        return AeromagError("a folder, not a file", file=path)
    return AeromagError("file not found", file=path)


# what a user's output path can do to a write: a file where a folder should be, a folder
# where the file should be, no permission, a read-only or full disk
_OUTPUT_ERRNOS = frozenset(
    {
        errno.ENOTDIR,
        errno.EEXIST,
        errno.EISDIR,
        errno.EACCES,
        errno.EPERM,
        errno.EROFS,
        errno.ENOSPC,
    }
)


def user_error(exc: BaseException) -> BaseException:
    """``exc`` as the user's problem when it is one: an :class:`OSError` writing to a path
    the user chose (a file where a folder should be, no permission, a full disk) becomes
    an :class:`AeromagError` naming that path; anything else is returned unchanged."""
    if isinstance(exc, OSError) and exc.errno in _OUTPUT_ERRNOS and exc.filename:
        return AeromagError(f"cannot write here: {exc.strerror}", file=exc.filename)
    return exc


class OneLineErrors(logging.Filter):
    """Logging filter: each record carrying an :class:`AeromagError` becomes its one line,
    ``aeromag: error: FILE: CHANNEL: problem``, once, without a traceback; repetitions of it
    (a flow re-logs its task's exception, both log "Finished in state Failed") are dropped.
    Other exceptions (bugs) keep their tracebacks."""

    def __init__(self, remember: int = 64) -> None:
        super().__init__("aeromag-one-line-errors")
        self._seen: OrderedDict[str, None] = OrderedDict()
        self._remember = remember

    def _first_time(self, text: str) -> bool:
        if text in self._seen:
            return False
        self._seen[text] = None
        while len(self._seen) > self._remember:
            self._seen.popitem(last=False)
        return True

    def filter(self, record: logging.LogRecord) -> bool:
        """Turn a record carrying an AeromagError into its one line, once.

        Returns
        -------
        bool
            False for a repeat of a line already logged and for Prefect's "Finished in state
            Failed(...AeromagError...)" record; True otherwise.
        """
        exc = record.exc_info[1] if record.exc_info else None
        if isinstance(exc, AeromagError):
            if not self._first_time(str(exc)):
                return False
            record.msg, record.args = f"aeromag: error: {exc}", ()
            record.exc_info, record.exc_text = None, None
            return True
        if record.levelno >= logging.ERROR and "AeromagError" in str(record.msg):
            return False  # "Finished in state Failed('... AeromagError: ...')": said already
        return True
