"""Access to the JSON Schemas in ``schemas/``: the single source of channel definitions."""

from __future__ import annotations

from functools import cache
from pathlib import Path
from typing import Any

import fastjsonschema
import orjson


def schema_dir() -> Path:
    """Folder holding the schema files (packaged copy first, then the source tree)."""
    here = Path(__file__).resolve().parent.parent
    for candidate in (here / "_schemas", here.parent / "schemas"):
        if candidate.is_dir():
            return candidate
    raise FileNotFoundError("aeromag schema folder not found (expected schemas/ beside pipeline/)")


def schema_path(name: str) -> Path:
    """File of schema ``name``: ``aeromag.X`` -> ``schemas/aeromag.X.json``,
    ``foxglove.X`` -> ``schemas/foxglove/X.json`` (Foxglove's official schemas)."""
    if name.startswith("foxglove."):
        return schema_dir() / "foxglove" / f"{name.split('.', 1)[1]}.json"
    return schema_dir() / f"{name}.json"


@cache
def schema_bytes(name: str) -> bytes:
    """Schema text as stored in an MCAP Schema record."""
    path = schema_path(name)
    if not path.is_file():
        raise KeyError(f"no JSON Schema named {name!r} in {schema_dir()}")
    return path.read_bytes()


@cache
def schema(name: str) -> dict[str, Any]:
    """The JSON Schema named ``name``, parsed (cached).

    Parameters
    ----------
    name : str
        ``aeromag.<Name>`` for ours, ``foxglove.<Name>`` for Foxglove's.

    Returns
    -------
    dict

    Raises
    ------
    KeyError
        No schema of that name.
    """
    return orjson.loads(schema_bytes(name))


@cache
def validator(name: str):
    """Compiled validator (fastjsonschema: ~10x faster than jsonschema for per-message checks)."""
    return fastjsonschema.compile(schema(name))


def validate(name: str, payload: dict[str, Any]) -> str | None:
    """Validate one decoded message; return the problem as text, or None when valid."""
    try:
        validator(name)(payload)
    except fastjsonschema.JsonSchemaValueException as exc:
        return exc.message
    return None
