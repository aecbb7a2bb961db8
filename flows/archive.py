"""Archive reprocessing on Dask, and scheduled processing of a watched folder.

Both map the post-flight steps over recordings whose (input hash, configuration hash) has
no finished output yet: each recording gets the folder ``OUT/<stem>-<sha8>-<cfg8>/`` and is
done when its summary JSON exists (written last, atomically). A recording that fails is
quarantined: ``OUT/quarantine/<stem>-<sha8>.txt`` holds its one-line reason; the others go
on. ``OUT/index.csv`` and ``index.json`` list every recording with its status and key
figures. After a crash (even ``kill -9``) a re-run only does the missing work; left-over
temporary files are removed first.
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextvars import ContextVar
from pathlib import Path
from typing import Any

from prefect import flow, task

from flows.errors import install_one_line_errors
from pipeline.config import Config
from pipeline.errors import AeromagError
from pipeline.run import archive as runs

install_one_line_errors()
# called with (done, total, row) after each recording, inside progress_to() only (the CLI's
# progress bar)
_PROGRESS: ContextVar[Callable[[int, int, dict], None] | None] = ContextVar(
    "aeromag_progress", default=None
)


@contextlib.contextmanager
def progress_to(callback: Callable[[int, int, dict], None]) -> Iterator[None]:
    """Within the block, archive flows call ``callback(done, total, row)`` after each
    recording."""
    token = _PROGRESS.set(callback)
    try:
        yield
    finally:
        _PROGRESS.reset(token)


@task(name="process-recording")
def process_recording(
    path: str, out_dir: str, config_path: str | None, cfg_hash: str, sha: str
) -> dict[str, Any]:
    """Prefect task: :func:`process_one` on a Dask worker (never raises; failures are
    quarantined).

    Returns
    -------
    dict
        The recording's index row.
    """
    row = runs.process_one(path, out_dir, config_path, cfg_hash, sha)
    if row["status"] == "processed":
        from flows.postflight import publish_artifact

        stem = Path(path).stem
        publish_artifact(stem, (Path(row["output_dir"]) / f"{stem}.report.md").read_text())
    return row


def _run_rows(recordings: list[Path], out: Path, config_path: str | None) -> list[dict]:
    cfg = Config.load(config_path)
    cfg.validate()
    out.mkdir(parents=True, exist_ok=True)
    rows, todo = runs.plan(recordings, out, cfg)
    futures = [
        process_recording.submit(str(p), str(out), config_path, cfg.hash, sha) for p, sha in todo
    ]
    from prefect.futures import as_completed

    total = len(recordings)
    for k, fut in enumerate(as_completed(futures), start=1):
        row = fut.result()
        rows.append(row)
        if (progress := _PROGRESS.get()) is not None:
            progress(len(rows), total, row)
        if k % 4 == 0:  # the index survives a crash with most of its rows
            runs.write_index(out, runs.with_pending(rows, todo))
    return rows


@flow(name="reprocess-archive", log_prints=False)
def reprocess_archive(
    archive_dir: str, out_dir: str, config_path: str | None = None
) -> dict[str, Any]:
    """Every recording of an archive, in parallel on the flow's task runner."""
    out = Path(out_dir)
    recordings = runs.discover(Path(archive_dir), exclude=out)
    rows = _run_rows(recordings, out, config_path)
    index = runs.write_index(out, rows)
    counts = {s: sum(r["status"] == s for r in rows) for s in ("processed", "done", "quarantined")}
    return {"recordings": len(rows), **counts, "index": index}


@flow(name="process-new-recordings", log_prints=False)
def process_new(
    watch_dir: str, out_dir: str, config_path: str | None = None, settle_s: float = 1.0
) -> dict[str, Any]:
    """The scheduled job: recordings that appeared in ``watch_dir`` since the last run
    (those without a finished output for this configuration), skipping incomplete files."""
    out = Path(out_dir)
    found = runs.discover(Path(watch_dir), exclude=out)
    ready, waiting = [], []
    for p in found:
        ok, why = runs.is_complete(p, settle_s)
        (ready if ok else waiting).append((p, why))
    rows = _run_rows([p for p, _ in ready], out, config_path) if ready else []
    rows += [{"input": str(p), "status": "waiting", "reason": why} for p, why in waiting]
    index = runs.write_index(out, rows) if rows else {}
    counts = {s: sum(r["status"] == s for r in rows) for s in ("processed", "quarantined")}
    return {"recordings": len(found), "waiting": len(waiting), **counts, "index": index}


class _SlowWorkerExit(logging.Filter):
    """Drops the nanny's "Worker process still alive after N seconds, killing": it comes once
    the cluster closes, with every result in, and loses nothing; other warnings still show."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("Worker process still alive after")


def dask_runner(workers: int, address: str | None):
    """Prefect's Dask task runner: the scheduler at ``address`` (``tcp://HOST:PORT``), or a
    local cluster of ``workers`` processes of one thread each."""
    from prefect_dask import DaskTaskRunner

    for name in ("", ".scheduler", ".nanny", ".core", ".worker", ".http.proxy"):
        logging.getLogger(f"distributed{name}").setLevel(logging.WARNING)  # its chatter
    nanny = logging.getLogger("distributed.nanny")
    if not any(isinstance(f, _SlowWorkerExit) for f in nanny.filters):
        nanny.addFilter(_SlowWorkerExit())
    if address:
        return DaskTaskRunner(address=address)
    # dashboard on a free port: two clusters at once must not fight over 8787
    return DaskTaskRunner(
        cluster_kwargs={
            "n_workers": workers,
            "threads_per_worker": 1,
            "processes": True,
            "dashboard_address": ":0",
            # a worker that outlives the scheduler at shutdown logs its failed heartbeat as a
            # warning with a traceback, every result already in: workers report errors only
            "silence_logs": logging.ERROR,
        }
    )


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_prefect_server(
    env: dict[str, str] | None = None, temporary: bool = False
) -> tuple[str, subprocess.Popen]:
    """Start ``prefect server`` on a free 127.0.0.1 port (analytics off) in its own session;
    returns its API URL and the process (the caller waits for it: :func:`wait_healthy`, and
    terminates it). ``env``: the server's environment (default: this process's).
    ``temporary``: the API app alone, as Prefect starts its own temporary server (no UI, no
    scheduler; healthy in about half the time; the flow's process need not import it)."""
    port = _free_port()
    env = {
        **(os.environ if env is None else env),
        "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
        "DO_NOT_TRACK": "1",
    }
    cmd = [sys.executable, "-m", "prefect", "server", "start"]
    if temporary:
        env |= {
            "PREFECT_UI_ENABLED": "0",
            "PREFECT__SERVER_EPHEMERAL": "1",
            "PREFECT__SERVER_FINAL": "1",
        }
        cmd = [sys.executable, "-m", "uvicorn", "--factory", "prefect.server.api.server:create_app"]
    proc = subprocess.Popen(
        cmd + ["--host", "127.0.0.1", "--port", str(port)],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    return f"http://127.0.0.1:{port}/api", proc


@contextlib.contextmanager
def prefect_api(timeout_s: float = 90.0, meanwhile=None) -> Iterator[Any]:
    """A Prefect API for flows whose tasks run in other processes (Dask workers, served
    deployments): the configured ``PREFECT_API_URL``, else a local server started on
    127.0.0.1 for the duration (without one each worker process would start its own
    temporary server, 15-20 s apiece); yields its URL. With ``meanwhile`` (one flow in this
    process): a temporary server, booting while the context ``meanwhile()`` is entered (the
    recording is read), whose value is yielded."""
    url = os.environ.get("PREFECT_API_URL")
    within = meanwhile or contextlib.nullcontext
    if meanwhile is not None:  # one flow in this process: a profile's API too
        from prefect.settings import PREFECT_API_URL

        url = url or PREFECT_API_URL.value()
    if url:
        with within() as got:
            yield got if meanwhile else url
        return
    url, proc = start_prefect_server(temporary=meanwhile is not None)
    try:
        with within() as got:
            wait_healthy(url, timeout_s, proc)
            os.environ["PREFECT_API_URL"] = url
            from prefect.settings import PREFECT_API_URL, temporary_settings

            with temporary_settings(updates={PREFECT_API_URL: url}):
                yield got if meanwhile else url
    finally:
        from prefect.logging.handlers import APILogWorker

        # a failed run's logs reach the server before it stops (no "Error logging to API")
        APILogWorker.drain_all(timeout=5)
        os.environ.pop("PREFECT_API_URL", None)
        proc.terminate()
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()


def wait_healthy(url: str, timeout_s: float, proc: subprocess.Popen | None = None) -> None:
    """Wait until the Prefect API at ``url`` (``http://HOST:PORT/api``) answers ``/health``
    with 200, at most ``timeout_s`` seconds; an AeromagError when the server process ``proc``
    exits or the time runs out."""
    import urllib.request

    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if proc is not None and proc.poll() is not None:
            raise AeromagError(f"the Prefect server exited with code {proc.returncode}")
        try:
            with urllib.request.urlopen(url + "/health", timeout=2) as r:
                if r.status == 200:
                    return
        except OSError:
            time.sleep(0.5)
    raise AeromagError(f"the Prefect server at {url} did not become healthy in {timeout_s} s")
