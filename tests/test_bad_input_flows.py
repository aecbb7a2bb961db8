"""Bad input through the Prefect flows: ``process`` and ``reprocess`` give the same one line
as the single-stage commands — no traceback (Prefect's included), at most two lines on stderr,
the input untouched, no half-written output."""

from __future__ import annotations

import csv
import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest

from flows.errors import OneLineErrors
from pipeline.errors import AeromagError
from tests.conftest import sha256
from tests.corpus import CORPUS, box_messages, run_cli

# The post-flight flow processes what a recording allows: without a fluxgate it skips
# compensation and says so, where `aeromag compensate` must stop.
FLOW_OUTCOME = {"required channel missing": ("processed", "no /mag/vector")}


def outcome(case: str) -> tuple:
    return (FLOW_OUTCOME.get(case, CORPUS[case][1]) + (None,))[:3]


@pytest.fixture(scope="module")
def corpus(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("corpus")
    msgs = box_messages()
    paths = {}
    for i, (case, (builder, _)) in enumerate(CORPUS.items()):
        p = folder / f"case{i:02d}.mcap"
        builder(p, msgs)
        for extra in folder.glob("*.full"):
            extra.unlink()
        paths[case] = p
    return paths


def _env(url: str) -> dict[str, str]:
    env = {**os.environ, "PREFECT_API_URL": url, "COLUMNS": "200"}
    env.pop("AEROMAG_DEBUG", None)
    return env


def _stderr_lines(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if ln.strip()]


# Each case once through `process`. In its own subprocess (the console script as a user runs
# it, with a real Prefect server): two refusals and two recordings the flow processes. The
# other refusals in-process through the same entry point (flows.cli.main), which they never
# leave for Prefect: they stop at the check before the flow (asserted below), ~0.1 s instead
# of ~2.5 s of interpreter start-up each. The other salvaged recordings (~10 s each, the whole
# flow) run only with `-m slow`; by default each is still processed by the same post-flight
# steps in test_reprocess_quarantines_with_the_same_line, and its salvage is checked in
# tests/test_hardening.py::test_bad_input_corpus.
SUBPROCESS = {"empty file", "scalar in tesla", "truncated mid-chunk", "required channel missing"}


def _case_param(case: str):
    if case in SUBPROCESS or outcome(case)[0] == "error":
        return case
    return pytest.param(case, marks=pytest.mark.slow)


def _check_process(case, src, out, code, stdout, stderr):
    err = _stderr_lines(stderr)
    assert "Traceback" not in stdout + stderr
    assert len(err) <= 2, stderr
    partial = [p.name for p in out.glob(".*")] if out.exists() else []
    assert partial == [], "a partial output was left behind"
    kind, channel, words = outcome(case)
    if kind == "error":
        assert code == 2, stdout + stderr
        assert len(err) == 1 and err[0].startswith("aeromag: error: "), stderr
        assert str(src) in err[0] and words in err[0], err[0]
        if channel:
            assert f": {channel}: " in err[0], err[0]
        assert not out.exists() or not any(out.iterdir())
    else:
        assert code == 0, stdout + stderr
        assert (out / f"{src.stem}.summary.json").is_file()
        # what the summary says the recording lost, the Markdown report (the flow's Prefect
        # artifact) says too, as the HTML report does
        inp = json.loads((out / f"{src.stem}.summary.json").read_text())["input"]
        said = [x["description"] for x in inp["losses"]] + inp["notes"]
        said += [f"gap on {g['topic']}" for g in inp["gaps"]]
        md = (out / f"{src.stem}.report.md").read_text()
        if any(channel in n for n in said):
            assert channel in md, md[:2000]


@pytest.mark.parametrize("case", [_case_param(c) for c in CORPUS])
def test_process_bad_input_is_one_line(case, corpus, tmp_path, request, monkeypatch, capsys):
    src = corpus[case]
    before = sha256(src)
    out = tmp_path / "out"
    if case in SUBPROCESS or outcome(case)[0] != "error":
        url = request.getfixturevalue("prefect_server")
        res = subprocess.run(
            [sys.executable, "-m", "flows.cli", "process", str(src), "--out", str(out)],
            env=_env(url),
            capture_output=True,
            text=True,
            timeout=600,
        )
        code, stdout, stderr = res.returncode, res.stdout, res.stderr
    else:
        from flows import postflight

        def no_flow(*a, **k):
            raise AssertionError("bad input reached the Prefect flow")

        monkeypatch.setattr(postflight, "postflight", no_flow)
        monkeypatch.delenv("AEROMAG_DEBUG", raising=False)
        code, stdout, stderr = run_cli(["process", str(src), "--out", str(out)], capsys)
    assert sha256(src) == before, "the input was modified"
    _check_process(case, src, out, code, stdout, stderr)


def test_reprocess_quarantines_with_the_same_line(corpus, prefect_server, tmp_path):
    archive = tmp_path / "archive"
    archive.mkdir()
    for p in corpus.values():
        (archive / p.name).write_bytes(p.read_bytes())
    out = tmp_path / "out"
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "flows.cli",
            "reprocess",
            str(archive),
            "--out",
            str(out),
            "--workers",
            "2",
        ],
        env=_env(prefect_server),
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert res.returncode == 0, res.stdout + res.stderr
    assert "Traceback" not in res.stdout + res.stderr
    assert len(_stderr_lines(res.stderr)) <= 2, res.stderr
    with (out / "index.csv").open() as f:
        rows = {Path(r["input"]).name: r for r in csv.DictReader(f)}
    for case, path in corpus.items():
        row = rows[path.name]
        kind, channel, words = outcome(case)
        if kind == "error":
            assert row["status"] == "quarantined", (case, row)
            reason = row["reason"]
            assert "\n" not in reason and str(archive / path.name) in reason and words in reason
            if channel:
                assert f": {channel}: " in reason
            q = out / "quarantine" / f"{path.stem}-{row['sha256'][:8]}.txt"
            assert q.read_text().strip() == reason
        else:
            assert row["status"] == "processed", (case, row)


def test_errors_inside_a_flow_are_logged_as_one_line():
    """The filter on Prefect's run loggers: first record of an AeromagError becomes one line,
    repetitions and 'Finished in state Failed' lines go, other exceptions keep tracebacks."""
    filt = OneLineErrors()
    err = AeromagError("no survey lines", file="f.mcap", channel="/mag/scalar")

    def record(msg, exc=None, level=logging.ERROR):
        exc_info = (type(exc), exc, None) if exc else None
        return logging.LogRecord("prefect.task_runs", level, __file__, 1, msg, (), exc_info)

    first = record("Task run failed with exception: %r", err)
    assert filt.filter(first)
    assert first.getMessage() == "aeromag: error: f.mcap: /mag/scalar: no survey lines"
    assert first.exc_info is None
    assert not filt.filter(record("Encountered exception during execution", err))
    assert not filt.filter(
        record(
            "Finished in state Failed('Task run encountered an exception "
            "AeromagError: f.mcap: /mag/scalar: no survey lines')"
        )
    )
    bug = ValueError("a bug")
    kept = record("Task run failed with exception", bug)
    assert filt.filter(kept) and kept.exc_info[1] is bug
    assert filt.filter(record("Finished in state Completed()", level=logging.INFO))


FAILING_FLOW = """
from prefect import flow, task
import flows.postflight  # installs the one-line filter, as every aeromag flow does
from pipeline.errors import AeromagError

@task
def stage():
    raise AeromagError("no survey lines to grid", file="f.mcap", channel="/gnss/fix")

@flow
def job():
    return stage()

try:
    job()
except AeromagError as exc:
    print(f"caught: {exc}")
"""


def test_an_error_raised_inside_a_flow_run_is_one_line(prefect_server):
    res = subprocess.run(
        [sys.executable, "-c", FAILING_FLOW],
        env=_env(prefect_server),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert res.returncode == 0, res.stderr
    assert "caught: f.mcap: /gnss/fix: no survey lines to grid" in res.stdout
    assert "Traceback" not in res.stderr
    err = _stderr_lines(res.stderr)
    assert len(err) == 1 and err[0].endswith(
        "aeromag: error: f.mcap: /gnss/fix: no survey lines to grid"
    ), res.stderr


def test_a_slow_worker_exit_at_cluster_close_is_no_stderr_line():
    """On a busy machine the local cluster's idle workers may take over 4 s to exit at its
    close; the nanny's "killing" warning must not add a line per worker to stderr."""
    from flows.archive import dask_runner

    dask_runner(2, None)  # configures the loggers; the cluster starts only with a flow
    nanny = logging.getLogger("distributed.nanny")

    def record(msg):
        return logging.LogRecord(nanny.name, logging.WARNING, __file__, 1, msg, (), None)

    assert not nanny.filter(record("Worker process still alive after 4.0 seconds, killing"))
    assert nanny.filter(record("Worker exceeded 95% memory budget. Restarting..."))
