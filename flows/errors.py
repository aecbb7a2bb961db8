"""Our errors stay one line inside Prefect's logs too.

Prefect logs a failing task and its flow with the exception's full traceback (about 40 lines
each). For an :class:`~pipeline.errors.AeromagError` — bad input, named by file, channel and
problem — the traceback tells a user nothing: this filter turns the first record of each such
error into ``aeromag: error: FILE: CHANNEL: problem`` and drops Prefect's repetitions of it
(the flow re-logs the task's exception, and both log a "Finished in state Failed" line).
Other exceptions (our bugs) keep their tracebacks.
"""

from __future__ import annotations

import logging
from collections import OrderedDict

from pipeline.errors import AeromagError

PREFECT_RUN_LOGGERS = ("prefect.task_runs", "prefect.flow_runs")


class OneLineErrors(logging.Filter):
    """Logging filter: one line per AeromagError, no traceback, no repetitions."""

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


_FILTER = OneLineErrors()


def install_one_line_errors() -> None:
    """Attach the filter to Prefect's flow- and task-run loggers (idempotent)."""
    for name in PREFECT_RUN_LOGGERS:
        logger = logging.getLogger(name)
        if _FILTER not in logger.filters:
            logger.addFilter(_FILTER)
