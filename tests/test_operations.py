"""Operations: configuration, resumable post-flight flow, archive reprocessing on Dask,
scheduled processing against a real Prefect server."""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.config import Config
from pipeline.errors import AeromagError
from tests.conftest import FIXTURES, sha256

BOX = FIXTURES / "box_uav.mcap"


# --------------------------------------------------------------------------------------------
def test_config_defaults_overrides_and_errors(tmp_path):
    base = Config.load()
    base.validate()
    assert base["config_version"] == 1 and base["compensation"]["models"][-1] == "agg-tl"
    f = tmp_path / "c.toml"
    f.write_text("config_version = 1\n[map]\ncell_m = 10\n[audit]\nenabled = false\n")
    c = Config.load(f)
    assert c["map"]["cell_m"] == 10.0 and c.map_settings().cell_m == 10.0
    assert c["audit"]["enabled"] is False and c["quality"]["overlap_m"] == 0.5
    assert c.hash != base.hash and Config.load(f).hash == c.hash
    for text, needle in (
        ("[map]\ncel_m = 3\n", "unknown configuration key 'map.cel_m'"),
        ("[map]\ncell_m = 'big'\n", "map.cell_m"),
        ("config_version = 7\n", "config_version 7"),
        ("[map\n", "not valid TOML"),
    ):
        f.write_text(text)
        with pytest.raises(AeromagError) as exc:
            Config.load(f)
        assert needle in str(exc.value) and str(f) in str(exc.value)
    f.write_text("[vector]\nmethod = 'magic'\n")
    with pytest.raises(AeromagError, match="vector.method"):
        Config.load(f).validate()


def test_config_command_prints_a_loadable_file(tmp_path):
    res = subprocess.run(
        [sys.executable, "-m", "flows.cli", "config"], capture_output=True, text=True, timeout=120
    )
    assert res.returncode == 0
    (tmp_path / "c.toml").write_text(res.stdout)
    assert Config.load(tmp_path / "c.toml").hash == Config.load().hash


def test_a_failed_flow_resumes_from_its_last_finished_task(prefect_harness, tmp_path, monkeypatch):
    """The vector stage fails once: the re-run takes ingest, segment, compensation and audit
    from the persisted results (task state Cached) and finishes."""
    import asyncio

    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterId
    from prefect.client.schemas.sorting import TaskRunSort

    from flows import postflight as pf

    src = tmp_path / "f.mcap"
    shutil.copy(BOX, src)
    real = pf.STEP_BY_NAME["vector"]
    calls = {"ingest": 0}
    real_ingest = pf.INGEST.function

    def counting_ingest(*a):
        calls["ingest"] += 1
        return real_ingest(*a)

    def broken(*a):
        raise RuntimeError("simulated crash in the vector stage")

    # the flow's tasks run the step of their name (STEP_BY_NAME)
    monkeypatch.setitem(pf.STEP_BY_NAME, "ingest", pf.Step("ingest", counting_ingest))
    monkeypatch.setitem(pf.STEP_BY_NAME, "vector", pf.Step("vector", broken))
    state = pf.postflight(str(src), str(tmp_path / "out"), return_state=True)
    assert state.is_failed()
    assert not (tmp_path / "out" / "f.summary.json").exists()
    monkeypatch.setitem(pf.STEP_BY_NAME, "vector", real)
    state2 = pf.postflight(str(src), str(tmp_path / "out"), return_state=True)
    assert state2.is_completed()
    assert calls["ingest"] == 1  # not run again: its persisted result was used
    assert (tmp_path / "out" / "f.summary.json").is_file()

    async def task_states(flow_run_id):
        async with get_client() as client:
            runs = await client.read_task_runs(
                flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=[flow_run_id])),
                sort=TaskRunSort.EXPECTED_START_TIME_ASC,
                limit=200,
            )
            return {r.name: r.state.name for r in runs}

    states = asyncio.run(task_states(state2.state_details.flow_run_id))
    cached = {k for k, v in states.items() if v == "Cached"}
    assert {
        "ingest",
        "despike",
        "segment",
        "compensate-tl16",
        "compensate-tl18",
        "compensate-agg-tl",
        "audit",
    } <= cached, states
    assert states.get("vector") == "Completed"
    # finished: the persisted results are gone
    key = pf.run_key(str(src), Config.load())
    assert not pf.cache_folder(key).exists()


# --------------------------------------------------------------------------------------------
def _archive(tmp_path: Path) -> Path:
    arch = tmp_path / "archive"
    (arch / "day2").mkdir(parents=True)
    shutil.copy(BOX, arch / "flight_a.mcap")
    shutil.copy(FIXTURES / "box_scalar_vector_only.mcap", arch / "day2" / "flight_b.mcap")
    (arch / "broken.mcap").write_bytes(b"this is not an MCAP file at all")
    data = BOX.read_bytes()
    # salvaged: the intact chunks of the first third are processed, the loss reported
    (arch / "day2" / "truncated.mcap").write_bytes(data[: len(data) // 3])
    (arch / "empty.mcap").write_bytes(b"")
    return arch


def _index(out: Path) -> dict[str, dict]:
    with (out / "index.csv").open() as f:
        return {Path(r["input"]).name: r for r in csv.DictReader(f)}


def test_archive_reprocessing_on_a_dask_cluster(prefect_server, tmp_path, monkeypatch):
    """Two Dask worker processes; a bad file is quarantined with its one-line reason, the
    others finish; a second run does nothing new; inputs are never modified."""
    from prefect.settings import PREFECT_API_URL, temporary_settings

    from flows.archive import dask_runner, reprocess_archive

    monkeypatch.setenv("PREFECT_API_URL", prefect_server)
    arch = _archive(tmp_path)
    hashes = {p: sha256(p) for p in arch.rglob("*.mcap")}
    out = tmp_path / "out"
    with temporary_settings(updates={PREFECT_API_URL: prefect_server}):
        res = reprocess_archive.with_options(task_runner=dask_runner(2, None))(str(arch), str(out))
    assert res["recordings"] == 5 and res["processed"] == 3 and res["quarantined"] == 2
    idx = _index(out)
    for good in ("flight_a.mcap", "flight_b.mcap", "truncated.mcap"):
        assert idx[good]["status"] == "processed", idx[good]
    cut = json.loads(
        (Path(idx["truncated.mcap"]["output_dir"]) / "truncated.summary.json").read_text()
    )
    assert cut["input"]["losses"], "the truncation is reported"
    for bad in ("broken.mcap", "empty.mcap"):
        assert idx[bad]["status"] == "quarantined"
        reason = idx[bad]["reason"]
        assert bad in reason and "\n" not in reason and "Traceback" not in reason
        q = list((out / "quarantine").glob(f"{Path(bad).stem}-*.txt"))
        assert len(q) == 1 and q[0].read_text().strip() == reason
    job = Path(idx["flight_a.mcap"]["output_dir"])
    assert (job / "flight_a.summary.json").is_file()
    assert (job / "flight_a.processed.mcap").is_file()
    assert float(idx["flight_a.mcap"]["fom_nT"]) > 0
    assert json.loads((out / "index.json").read_text())["recordings"]
    assert {p: sha256(p) for p in arch.rglob("*.mcap")} == hashes
    # the second run finds every output before it submits a task (plan), so it needs no
    # cluster: the flow's default runner spares a Dask start-up (the CLI's re-run on Dask is
    # test_reprocess_after_kill_9_does_only_the_missing_work)
    with temporary_settings(updates={PREFECT_API_URL: prefect_server}):
        again = reprocess_archive(str(arch), str(out))
    assert again["processed"] == 0 and again["done"] == 3 and again["quarantined"] == 2
    assert {p: sha256(p) for p in arch.rglob("*.mcap")} == hashes


def test_reprocess_after_kill_9_does_only_the_missing_work(prefect_server, tmp_path):
    arch = tmp_path / "archive"
    arch.mkdir()
    for k in range(2):
        shutil.copy(BOX, arch / f"flight_{k}.mcap")
    out = tmp_path / "out"
    env = {**os.environ, "PREFECT_API_URL": prefect_server}
    cmd = [
        sys.executable,
        "-m",
        "flows.cli",
        "reprocess",
        str(arch),
        "--out",
        str(out),
        "--workers",
        "1",
    ]
    proc = subprocess.Popen(
        cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True
    )
    t_end = time.monotonic() + 300
    while time.monotonic() < t_end and not list(out.glob("*/*.summary.json")):
        time.sleep(0.2)
        assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    finished = {p.parent for p in out.glob("*/*.summary.json")}
    assert len(finished) == 1
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    idx = _index(out)
    assert sorted(r["status"] for r in idx.values()).count("done") == len(finished)
    assert all(r["status"] in ("done", "processed") for r in idx.values())
    for job in out.iterdir():
        if job.is_dir() and job.name != "quarantine":
            assert not [p for p in job.iterdir() if ".partial" in p.name]
            mcaps = list(job.glob("*.processed.mcap"))
            assert len(mcaps) == 1 and mcaps[0].stat().st_size > 100_000


def test_serve_processes_new_complete_recordings(prefect_server, tmp_path):
    """`aeromag serve` registers a deployment; a run of it (through the API) processes the
    complete recording and leaves the one still being written for later."""
    import asyncio

    from prefect.client.orchestration import get_client
    from prefect.client.schemas.sorting import DeploymentSort
    from prefect.deployments import run_deployment
    from prefect.settings import PREFECT_API_URL, temporary_settings

    watch, out = tmp_path / "incoming", tmp_path / "out"
    watch.mkdir()
    # the scalar + vector box: processed in 0.2 s, where the full box takes ~6 s (its audit)
    shutil.copy(FIXTURES / "box_scalar_vector_only.mcap", watch / "done.mcap")
    data = BOX.read_bytes()
    (watch / "writing.mcap").write_bytes(data[: len(data) // 2])  # no footer yet
    env = {**os.environ, "PREFECT_API_URL": prefect_server}
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "flows.cli",
            "serve",
            "--watch",
            str(watch),
            "--out",
            str(out),
            "--cron",
            "0 0 1 1 *",
            "--name",
            "test-watch",
        ],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    try:
        with temporary_settings(updates={PREFECT_API_URL: prefect_server}):

            async def deployments():
                async with get_client() as client:
                    return [
                        d.name
                        for d in await client.read_deployments(
                            sort=DeploymentSort.NAME_ASC, limit=50
                        )
                    ]

            t_end = time.monotonic() + 120
            while "test-watch" not in asyncio.run(deployments()):
                assert time.monotonic() < t_end and proc.poll() is None, (
                    proc.stderr.read().decode()[-2000:]
                )
                time.sleep(1)
            run = run_deployment("process-new-recordings/test-watch", timeout=300)
            assert run.state.is_completed(), run.state
        idx = _index(out)
        assert idx["done.mcap"]["status"] == "processed"
        assert idx["writing.mcap"]["status"] == "waiting"
        assert "footer" in idx["writing.mcap"]["reason"]
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
