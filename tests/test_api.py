"""The curated public API in ``pipeline/__init__.py`` and the compatibility re-exports."""

from __future__ import annotations

import ast
import importlib
import subprocess
import sys
from pathlib import Path

import pipeline


def test_all_lists_the_lazy_names():
    assert pipeline.__all__ == ["__version__", *pipeline._LAZY]
    assert len(set(pipeline.__all__)) == len(pipeline.__all__)


def test_every_public_name_resolves_to_its_module_object():
    for name, module in pipeline._LAZY.items():
        assert getattr(pipeline, name) is getattr(importlib.import_module(module), name), name
    assert set(pipeline.__all__) <= set(dir(pipeline))


def test_type_checking_imports_match_the_lazy_table():
    tree = ast.parse(Path(pipeline.__file__).read_text())
    block = next(
        n
        for n in tree.body
        if isinstance(n, ast.If) and getattr(n.test, "id", "") == "TYPE_CHECKING"
    )
    imported = {a.name: n.module for n in block.body for a in n.names}
    assert imported == pipeline._LAZY


def test_import_pipeline_is_cheap():
    """``import pipeline`` loads none of the heavy dependencies (they load on first use)."""
    code = (
        "import sys, pipeline; "
        "print(sorted(m for m in ('numpy', 'pandas', 'scipy', 'prefect', 'typing', "
        "'pipeline.io', 'pipeline.config') if m in sys.modules))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        cwd=Path(pipeline.__file__).parent.parent,
    )
    assert out.stdout.strip() == "[]"


def test_moved_names_are_re_exported():
    import pipeline.config
    import pipeline.defaults
    import pipeline.flight
    import pipeline.io
    import pipeline.io.reader

    assert pipeline.io.reader.Flight is pipeline.io.Flight is pipeline.flight.Flight
    for name in ("default_text", "default_value", "read_toml"):
        assert getattr(pipeline.config, name) is getattr(pipeline.defaults, name)
