"""Our errors stay one line inside Prefect's logs too: :class:`pipeline.errors.OneLineErrors`
on Prefect's flow- and task-run loggers (Prefect logs a failing task and its flow with the
exception's full traceback, about 40 lines each, which tells a user nothing about bad input).
"""

from __future__ import annotations

import logging

from pipeline.errors import OneLineErrors

__all__ = ["OneLineErrors", "install_one_line_errors"]
PREFECT_RUN_LOGGERS = ("prefect.task_runs", "prefect.flow_runs")
_FILTER = OneLineErrors()


def install_one_line_errors() -> None:
    """Attach the filter to Prefect's flow- and task-run loggers (idempotent)."""
    for name in PREFECT_RUN_LOGGERS:
        logger = logging.getLogger(name)
        if _FILTER not in logger.filters:
            logger.addFilter(_FILTER)
