"""The one user-facing error type.

Every problem a user can cause (bad file, missing channel, wrong units ...) is raised as
:class:`AeromagError`, whose text is a single line naming the file, the channel and the
problem. The CLI prints that line and exits non-zero; it never shows a traceback.
"""

from __future__ import annotations

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
