"""Every single-stage command honours ``--config`` for its own section (issue 37, item 2).

Each test gives a configuration file whose values differ from the shipped ones and catches
the arguments the stage itself receives (the stage function is replaced by one that records
its arguments and stops the command), so the test fails when the command re-types a default
or leaves the file's section out.
"""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from tests.conftest import FIXTURES

BOX = FIXTURES / "box_uav.mcap"


class Reached(Exception):
    """Raised by a replaced stage function: the command got as far as the stage."""

    def __init__(self, *args, **kwargs):
        super().__init__("stage reached")
        self.args_, self.kwargs = args, kwargs


def stop(*args, **kwargs):
    raise Reached(*args, **kwargs)


def invoke(tmp_path, toml: str, *args) -> Reached:
    """Run ``aeromag ARGS --config FILE`` in-process; the stage's arguments."""
    from flows.cli import app

    cfg = tmp_path / "c.toml"
    cfg.write_text("config_version = 1\n" + toml)
    res = CliRunner().invoke(app, [*(str(a) for a in args), "--config", str(cfg)])
    assert isinstance(res.exception, Reached), res.output
    return res.exception


def test_compensate_takes_compensation(tmp_path, monkeypatch):
    monkeypatch.setattr("pipeline.run.commands.run_compensation", stop)
    got = invoke(
        tmp_path,
        "[compensation]\nmodels = ['tl16']\nridge = 0.003\ntrim_s = 0.7\n",
        "compensate",
        BOX,
        "--out",
        tmp_path / "o.mcap",
        "--json",
        tmp_path / "o.json",
    )
    settings = got.args_[2]
    assert (settings.model, settings.ridge, settings.trim_s) == ("tl16", 0.003, 0.7)


def test_map_takes_map(tmp_path, monkeypatch):
    monkeypatch.setattr("pipeline.run.commands.build_map", stop)
    got = invoke(
        tmp_path,
        "[compensation]\nmodels = ['tl18']\n[map]\ncell_m = 7.5\narima = '1,1,1'\n",
        "map",
        BOX,
        "--out",
        tmp_path / "o.mcap",
        "--json",
        tmp_path / "o.json",
        "--lag",
        0.2,
    )
    settings = got.args_[3]
    assert (settings.cell_m, settings.arima, settings.lag_s) == (7.5, (1, 1, 1), 0.2)


def test_quality_takes_quality(tmp_path, monkeypatch):
    monkeypatch.setattr("pipeline.run.fields.run_quality", stop)
    got = invoke(
        tmp_path,
        "[compensation]\nmodels = ['tl18']\n[quality]\noverlap_m = 33.0\n",
        "quality",
        BOX,
        "--json",
        tmp_path / "q.json",
    )
    fields, settings = got.args_[2], got.args_[5]
    assert settings.overlap_m == 33.0 and "tl18" in fields


def test_audit_takes_audit(tmp_path, monkeypatch):
    monkeypatch.setattr("pipeline.audit.run_audit", stop)
    got = invoke(
        tmp_path,
        "[audit]\nalpha = 0.01\nbaseline = 'tl16'\n",
        "audit",
        BOX,
        "--json",
        tmp_path / "a.json",
        "--report",
        tmp_path / "rep",
    )
    settings = got.args_[2]
    assert (settings.alpha, settings.baseline) == (0.01, "tl16")


def test_vector_takes_vector(tmp_path, monkeypatch):
    """Its method and the fuzzy-R settings (ignored before: only the method was read)."""
    monkeypatch.setattr("pipeline.vector.stage.run_vector", stop)
    got = invoke(
        tmp_path,
        "[vector]\nmethod = 'batch'\nfuzzy_window_s = 0.7\nfuzzy_exponent = 0.5\n",
        "vector",
        BOX,
        "--out",
        tmp_path / "v.mcap",
        "--json",
        tmp_path / "v.json",
    )
    assert got.args_[2] == "batch"
    assert got.kwargs["settings"]["fuzzy_window_s"] == 0.7
    assert got.kwargs["settings"]["fuzzy_exponent"] == 0.5


def test_navigate_takes_navigate(tmp_path, monkeypatch):
    """Filter, INS grade, seed and the recording map's grid (the CLI re-typed them before);
    an option given on the command line still wins."""
    from pipeline.navigation import map_io
    from tests.mapfile import write_processed

    maps = write_processed(tmp_path / "maps.processed.mcap")[0]
    read = map_io.read_map
    channels = []

    def reading(path, channel):
        channels.append(channel)
        raise Reached(path, channel)

    monkeypatch.setattr(map_io, "read_map", reading)
    toml = "[navigate]\nfilter = 'pf'\nins = 'tactical'\nseed = 4\nmap = 'anomaly'\n"
    args = ("navigate", BOX, "--map", maps, "--json", tmp_path / "n.json")
    invoke(tmp_path, toml, *args)
    assert channels == ["/map/anomaly"]

    monkeypatch.setattr(map_io, "read_map", read)
    monkeypatch.setattr("pipeline.navigation.stage.track_coverage", lambda *a: None)
    monkeypatch.setattr("pipeline.navigation.stage.run_navigation", stop)
    settings = invoke(tmp_path, toml, *args, "--segments", "all").args_[4]
    assert (settings.filter, settings.ins, settings.seed) == ("pf", "tactical", 4)
    settings = invoke(tmp_path, toml, *args, "--segments", "all", "--seed", 9).args_[4]
    assert (settings.filter, settings.seed, settings.segments) == ("pf", 9, "all")


def test_enhance_takes_enhance(tmp_path, monkeypatch):
    from tests.mapfile import write_processed

    src = write_processed(tmp_path / "maps.processed.mcap")[0]
    monkeypatch.setattr("pipeline.maps.enhance.enhance", stop)
    got = invoke(
        tmp_path,
        "[enhance]\nproducts = ['dz', 'up:30']\n",
        "enhance",
        src,
        "--out",
        tmp_path / "e.mcap",
    )
    from pipeline.maps.enhance import Product

    assert list(got.args_[1]) == [Product("dz"), Product("up", 30.0)]


@pytest.mark.parametrize("section", ["vector", "navigate"])
def test_a_bad_section_value_is_one_line(tmp_path, section):
    """A wrong value in the command's own section fails as the file's one-line error,
    before anything is read or written."""
    from flows.cli import app
    from pipeline.errors import AeromagError

    cfg = tmp_path / "c.toml"
    bad = {"vector": "method = 'nope'", "navigate": "ins = 'nope'"}[section]
    cfg.write_text(f"config_version = 1\n[{section}]\n{bad}\n")
    args = {
        "vector": ["--out", tmp_path / "v.mcap", "--json", tmp_path / "v.json"],
        "navigate": ["--map", BOX, "--json", tmp_path / "n.json"],
    }[section]
    res = CliRunner().invoke(app, [section, str(BOX), *map(str, args), "--config", str(cfg)])
    assert isinstance(res.exception, AeromagError), res.output
    assert str(res.exception).startswith(f"{cfg}: {section}")
    assert not (tmp_path / "v.mcap").exists() and not (tmp_path / "n.json").exists()


def test_navigate_and_map_compensate_a_raw_recording_alike(tmp_path, monkeypatch):
    """One path: `navigate` despikes and compensates a raw recording as `map` does (it used
    to skip the despiking), so both stages get the same field."""
    import numpy as np

    from tests.mapfile import write_processed

    maps = write_processed(tmp_path / "maps.processed.mcap")[0]
    monkeypatch.setattr("pipeline.run.commands.build_map", stop)
    monkeypatch.setattr("pipeline.navigation.stage.track_coverage", lambda *a: None)
    monkeypatch.setattr("pipeline.navigation.stage.run_navigation", stop)
    toml = "[compensation]\nmodels = ['tl18']\n[despike]\nthreshold_sigma = 3.0\n"
    mapped = invoke(
        tmp_path, toml, "map", BOX, "--out", tmp_path / "m.mcap", "--json", tmp_path / "m.json"
    )
    navigated = invoke(
        tmp_path, toml, "navigate", BOX, "--map", maps, "--json", tmp_path / "n.json"
    )
    assert np.array_equal(mapped.args_[2], navigated.args_[2], equal_nan=True)
    assert np.array_equal(mapped.args_[0].data["scalar_nT"], navigated.args_[0].data["scalar_nT"])


def test_the_checked_flight_is_handed_to_the_flow_only_inside_the_block(tmp_path):
    """`aeromag process` reads a recording once: the flight read to check it reaches the flow
    only within checked() and only for the same, unchanged file."""
    import shutil

    from pipeline.run import postflight as pf

    src = tmp_path / "f.mcap"
    shutil.copy(BOX, src)
    assert pf.take_checked(str(src)) == (None, 0.0)
    with pf.checked(src) as flight:
        got, read_s = pf.take_checked(str(src))
        assert got is flight and read_s > 0
        assert pf.take_checked(str(BOX))[0] is None  # another file
    assert pf.take_checked(str(src)) == (None, 0.0)
    with pf.checked(src):
        src.write_bytes(src.read_bytes() + b"\0")  # changed since it was checked
        assert pf.take_checked(str(src))[0] is None
