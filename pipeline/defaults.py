"""The shipped defaults and reading a user's TOML file.

A leaf module (it imports nothing else of aeromag but the error type), so the reader
(``pipeline.io.mapping``) and the stages (``pipeline.maps.level``) can use it without importing
:mod:`pipeline.config`, which itself imports the stages' settings: no ``config`` <-> ``io``
import cycle. :mod:`pipeline.config` re-exports everything here.
"""

from __future__ import annotations

import copy
import functools
import tomllib
from collections.abc import Callable
from dataclasses import field
from importlib import resources
from pathlib import Path
from typing import Any

from pipeline.errors import AeromagError


def default_text() -> str:
    """The shipped configuration file (``pipeline/default_config.toml``) as text."""
    return resources.files("pipeline").joinpath("default_config.toml").read_text()


@functools.cache
def _defaults() -> dict[str, Any]:
    return tomllib.loads(default_text())


def default_value(section: str, key: str) -> Any:
    """A value of the shipped defaults: the one source of a code default that has a key."""
    return copy.deepcopy(_defaults()[section][key])


@functools.cache
def _comments() -> dict[str, str]:
    out, section = {}, ""
    for line in default_text().splitlines():
        text = line.strip()
        if text.startswith("["):
            section = text.strip("[]")
        elif "=" in text and "  # " in text and not text.startswith("#"):
            out[f"{section}.{text.split('=', 1)[0].strip()}"] = text.split("  # ", 1)[1].strip()
    return out


def default_comment(key: str) -> str:
    """The comment beside ``section.name`` in the shipped defaults: the one description of a
    setting, which the command line's option help also shows (the file is read once).

    Raises
    ------
    KeyError
        The shipped file has no such key, or no comment beside it.
    """
    try:
        return _comments()[key]
    except KeyError:
        raise KeyError(f"no commented key {key} in the shipped defaults") from None


def default_field(section: str, key: str, convert: Callable[[Any], Any] | None = None) -> Any:
    """A dataclass field defaulting to a shipped value (``convert`` maps the TOML value to the
    field's type, e.g. ``tuple`` for a band): settings classes never re-type a literal."""

    def make() -> Any:
        v = default_value(section, key)
        return convert(v) if convert else v

    return field(default_factory=make)


def ridge_problem(value: Any) -> str | None:
    """The one rule for ``compensation.ridge``: ``"auto"`` or a number >= 0 (None: fine)."""
    if value == "auto" or (
        isinstance(value, int | float) and not isinstance(value, bool) and value >= 0
    ):
        return None
    return f"ridge must be 'auto' or a number >= 0, not {value!r}"


def read_toml(path: str | Path, what: str) -> dict[str, Any]:
    """A user's TOML file (``what``: "configuration", "mapping"), or a one-line error naming
    the file when it is missing or not valid TOML."""
    p = Path(path)
    if not p.is_file():
        raise AeromagError(f"{what} file not found", file=p)
    try:
        return tomllib.loads(p.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise AeromagError(f"not valid TOML ({exc})", file=p) from None
