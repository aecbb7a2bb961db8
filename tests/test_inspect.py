"""``aeromag inspect`` and the CLI's error discipline (one line, no traceback, exit code)."""

from __future__ import annotations

import subprocess

import orjson
import pytest

import tests.cli
from pipeline.io.inspect import inspect_recording
from pipeline.simulate import write_simulation
from tests.conftest import run_sim
from tests.mcap_builder import NS, T0, attitude, build, scalar, ts, vector


def cli(*args: str) -> subprocess.CompletedProcess:
    """The command in-process (tests/cli.py): no interpreter start-up per call."""
    return tests.cli.run(*args)


def test_clean_recording_has_no_violations(box_path):
    rep = inspect_recording(box_path)
    assert rep.violations == []
    d = rep.to_dict()
    assert {t["topic"] for t in d["topics"]} >= {
        "/mag/scalar",
        "/mag/vector",
        "/ins/attitude",
        "/gnss/fix",
        "/base/scalar",
    }
    rates = {t["topic"]: t["rate_hz"] for t in d["topics"]}
    assert rates["/mag/scalar"] == pytest.approx(10.0) and rates["/gnss/fix"] == pytest.approx(2.0)
    res = cli("inspect", str(box_path))
    assert res.returncode == 0 and "contract: ok" in res.stdout


def test_injected_gaps_are_reported(tmp_path):
    sim = run_sim(
        "calibration-only",
        1,
        [
            "calibration.passes=1",
            'sensors.dropouts=[{topic="/gnss/fix", start_s=120.0, duration_s=4.0}]',
        ],
    )
    path = write_simulation(sim, tmp_path / "gap.mcap")
    rep = inspect_recording(path)
    assert rep.violations == []
    gaps = rep.gaps
    assert len(gaps) == 1 and gaps[0].topic == "/gnss/fix"
    assert abs(gaps[0].duration_s - 4.2) < 0.25  # 4 s plus one 5 Hz period
    t0 = rep.start_ns
    assert abs((gaps[0].start_ns - t0) / NS - 120.0) < 0.3
    res = cli("inspect", str(path), "--json", str(tmp_path / "rep.json"))
    assert res.returncode == 0 and "/gnss/fix: gap of" in res.stdout
    js = orjson.loads((tmp_path / "rep.json").read_bytes())
    assert [len(t["gaps"]) for t in js["topics"] if t["topic"] == "/gnss/fix"] == [1]


def test_contract_violations_each_get_one_line_and_exit_1(tmp_path):
    msgs = []
    for i in range(50):
        t = T0 + i * NS // 10
        msgs += [
            ("/mag/scalar", t, scalar(t, 5e4)),
            (
                "/mag/vector",
                t,
                vector(t, 1, 2, 3)
                if i != 7
                else {"timestamp": ts(t), "sensor_id": "v", "x_nT": "1", "y_nT": 2, "z_nT": 3},
            ),
            ("/ins/attitude", t, attitude(t, 0, 0, 10)),
            ("/base/scalar", t, scalar(t + (5 if i == 3 else 0), 5e4)),
        ]
    msgs.append(("/mag/scalar", T0, scalar(T0, 5e4)))  # duplicate
    path = build(tmp_path / "bad.mcap", msgs, schema_of={"/ins/attitude": "my.Attitude"})
    rep = inspect_recording(path)
    text = "\n".join(rep.violations)
    assert "/ins/attitude: schema is 'my.Attitude'" in text
    assert "/mag/vector: 1 of 50 messages do not match aeromag.VectorField" in text
    assert "/base/scalar: 1 of 50 messages have a payload timestamp that differs" in text
    assert "/mag/scalar: 1 duplicated timestamps" in text
    res = cli("inspect", str(path))
    assert res.returncode == 1
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("violation:")]
    assert len(lines) == len(rep.violations) and "Traceback" not in res.stderr


def test_missing_channels_are_warnings_not_violations(tmp_path):
    msgs = [("/mag/scalar", T0 + i * NS, scalar(T0 + i * NS, 5e4)) for i in range(5)]
    rep = inspect_recording(build(tmp_path / "only.mcap", msgs))
    assert rep.violations == []
    assert any(w.startswith("/ins/attitude: absent") for w in rep.warnings)


def test_bad_files_give_one_line_errors(tmp_path):
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x89PNG not an mcap" * 100)
    truncated = tmp_path / "trunc.mcap"
    good = build(
        tmp_path / "good.mcap",
        [("/mag/scalar", T0 + i * NS, scalar(T0 + i * NS, 5e4)) for i in range(2000)],
    )
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    for path, needle in (
        (empty, "empty file"),
        (junk, "not a readable MCAP"),
        (tmp_path / "missing.mcap", "file not found"),
    ):
        res = cli("inspect", str(path))
        assert res.returncode == 2, res.stderr
        err = res.stderr.strip().splitlines()
        assert len(err) == 1 and needle in err[0] and str(path) in err[0], res.stderr
        assert "Traceback" not in res.stderr
    # a truncated file is salvaged: what it lost is a violation, the rest is reported
    res = cli("inspect", str(truncated))
    assert res.returncode == 1 and "Traceback" not in res.stderr
    assert "violation:" in res.stderr and "file truncated" in res.stderr
    assert "/mag/scalar" in res.stdout


def test_simulate_cli_and_bad_scenario(tmp_path):
    res = cli(
        "simulate",
        "--scenario",
        "calibration-only",
        "--seed",
        "2",
        "--set",
        "calibration.passes=1",
        "--out",
        str(tmp_path / "f.mcap"),
        "--truth",
        str(tmp_path / "t.json"),
    )
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "f.mcap").is_file() and (tmp_path / "t.json").is_file()
    res = cli("simulate", "--scenario", "nope", "--out", str(tmp_path / "g.mcap"))
    assert res.returncode == 2 and "unknown scenario 'nope'" in res.stderr
    assert not (tmp_path / "g.mcap").exists()
