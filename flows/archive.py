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
import csv
import io
import json
import logging
import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from prefect import flow, task

from flows.errors import install_one_line_errors
from pipeline.config import Config
from pipeline.errors import AeromagError
from pipeline.io.writer import write_json_atomic, write_text_atomic
from pipeline.products.summary import sha256_file

MCAP_MAGIC = b"\x89MCAP0\r\n"
INDEX_FIELDS = [
    "input",
    "sha256",
    "config_hash",
    "status",
    "reason",
    "output_dir",
    "seconds",
    "fom_nT",
    "heading_error_rms_nT",
    "heading_error_method",
    "crossover_rms_nT",
    "findings",
]
install_one_line_errors()
# called with (done, total, row) after each recording when set (the CLI's progress bar)
PROGRESS: Callable[[int, int, dict], None] | None = None


def discover(folder: Path, exclude: Path | None = None) -> list[Path]:
    """Recordings under ``folder`` (outputs of aeromag and anything under ``exclude`` left
    out)."""
    ex = exclude.resolve() if exclude is not None else None
    out = []
    for p in sorted(folder.rglob("*.mcap")):
        if p.name.endswith(".processed.mcap") or p.name.startswith("."):
            continue
        if ex is not None and (ex == p.resolve().parent or ex in p.resolve().parents):
            continue
        out.append(p)
    return out


def is_complete(path: Path, settle_s: float = 1.0) -> tuple[bool, str]:
    """A recording still being written is not processed: its size must hold still for
    ``settle_s`` and it must end with the MCAP footer magic."""
    try:
        size = path.stat().st_size
        time.sleep(settle_s)
        if path.stat().st_size != size:
            return False, "still growing"
        with path.open("rb") as f:
            f.seek(max(size - len(MCAP_MAGIC), 0))
            if f.read() != MCAP_MAGIC:
                return False, "no MCAP footer yet"
    except OSError as exc:
        return False, f"unreadable ({exc})"
    return True, ""


def job_dir(out_dir: Path, path: Path, sha: str, cfg_hash: str) -> Path:
    """Output folder of one recording and configuration: ``<stem>-<sha8>-<cfg8>``.

    Parameters
    ----------
    out_dir : Path
        The archive's output folder.
    path : Path
        The recording.
    sha : str
        Its sha256 (hex).
    cfg_hash : str
        The configuration's hash (hex).

    Returns
    -------
    Path
    """
    return out_dir / f"{path.stem}-{sha[:8]}-{cfg_hash[:8]}"


def _clean_partials(folder: Path) -> None:
    if folder.is_dir():
        for p in folder.iterdir():
            if p.name.startswith(".") and ".partial" in p.name:
                p.unlink(missing_ok=True)


def _figures(summary: dict) -> dict[str, Any]:
    comp = summary.get("compensation") or {}
    fom = None
    if comp:
        last = [k for k in comp if k != "final"][-1]
        fom = comp[last]["fom_nT"]["compensated"]
    q = summary.get("quality") or {}
    he = q.get("heading_error_rms_nT") or {}
    audit = summary.get("audit") or {}
    return {
        "fom_nT": fom,
        "heading_error_rms_nT": he.get("extended", he.get("agg_tl")),
        "heading_error_method": q.get("heading_error_method"),
        "crossover_rms_nT": (q.get("crossover_rms_nT") or {}).get("after"),
        "findings": " ".join(f["effect"] for f in audit.get("findings", [])),
    }


def process_one(
    path: str, out_dir: str, config_path: str | None, cfg_hash: str, sha: str
) -> dict[str, Any]:
    """Process one recording into its job folder; never raises (failures are quarantined)."""
    from flows.postflight import run_plain

    p, out = Path(path), Path(out_dir)
    dest = job_dir(out, p, sha, cfg_hash)
    row = {
        "input": str(p),
        "sha256": sha,
        "config_hash": cfg_hash,
        "output_dir": str(dest),
        "reason": "",
        "seconds": 0.0,
    }
    t0 = time.perf_counter()
    try:
        dest.mkdir(parents=True, exist_ok=True)
        _clean_partials(dest)
        summary = run_plain(str(p), str(dest), config_path)
        row.update(status="processed", **_figures(summary))
    except AeromagError as exc:
        row.update(status="quarantined", reason=str(exc))
    except Exception as exc:  # noqa: BLE001 - one bad file must not stop an archive
        row.update(
            status="quarantined",
            reason=f"{p}: internal error: {type(exc).__name__}: {' '.join(str(exc).split())[:300]}",
        )
    row["seconds"] = round(time.perf_counter() - t0, 2)
    if row["status"] == "quarantined":
        with contextlib.suppress(OSError):
            dest.rmdir()  # only if empty: nothing was produced
        q = out / "quarantine"
        write_text_atomic(q / f"{p.stem}-{sha[:8]}.txt", row["reason"] + "\n")
    return row


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
    return process_one(path, out_dir, config_path, cfg_hash, sha)


def plan(recordings: list[Path], out: Path, cfg: Config) -> tuple[list[dict], list[tuple]]:
    """Rows for recordings already done, and the (path, sha) still to do."""
    done, todo = [], []
    for p in recordings:
        sha = sha256_file(p)
        dest = job_dir(out, p, sha, cfg.hash)
        summary = dest / f"{p.stem}.summary.json"
        if summary.is_file():
            row = {
                "input": str(p),
                "sha256": sha,
                "config_hash": cfg.hash,
                "status": "done",
                "reason": "",
                "output_dir": str(dest),
                "seconds": 0.0,
            }
            with contextlib.suppress(OSError, ValueError):
                row.update(_figures(json.loads(summary.read_text())))
            done.append(row)
        else:
            todo.append((p, sha))
    return done, todo


def write_index(out: Path, rows: list[dict]) -> dict[str, str]:
    """Write ``index.csv`` and ``index.json`` (rows sorted by input path), atomically.

    Parameters
    ----------
    out : Path
        The archive's output folder.
    rows : list of dict
        One per recording (``INDEX_FIELDS`` go into the CSV; the JSON keeps every key).

    Returns
    -------
    dict
        ``{"csv": path, "json": path}``.
    """
    rows = sorted(rows, key=lambda r: r["input"])
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=INDEX_FIELDS, extrasaction="ignore")
    w.writeheader()
    for r in rows:
        w.writerow({k: r.get(k, "") for k in INDEX_FIELDS})
    write_text_atomic(out / "index.csv", buf.getvalue())
    write_json_atomic(out / "index.json", {"recordings": rows})
    return {"csv": str(out / "index.csv"), "json": str(out / "index.json")}


def _run_rows(recordings: list[Path], out: Path, config_path: str | None) -> list[dict]:
    cfg = Config.load(config_path)
    cfg.validate()
    out.mkdir(parents=True, exist_ok=True)
    rows, todo = plan(recordings, out, cfg)
    futures = [
        process_recording.submit(str(p), str(out), config_path, cfg.hash, sha) for p, sha in todo
    ]
    from prefect.futures import as_completed

    total = len(recordings)
    for k, fut in enumerate(as_completed(futures), start=1):
        row = fut.result()
        rows.append(row)
        if PROGRESS:
            PROGRESS(len(rows), total, row)
        if k % 4 == 0:  # the index survives a crash with most of its rows
            write_index(
                out,
                rows
                + [
                    {"input": str(p), "sha256": s, "status": "pending"}
                    for p, s in todo
                    if str(p) not in {r["input"] for r in rows}
                ],
            )
    return rows


@flow(name="reprocess-archive", log_prints=False)
def reprocess_archive(
    archive_dir: str, out_dir: str, config_path: str | None = None
) -> dict[str, Any]:
    """Every recording of an archive, in parallel on the flow's task runner."""
    out = Path(out_dir)
    recordings = discover(Path(archive_dir), exclude=out)
    rows = _run_rows(recordings, out, config_path)
    index = write_index(out, rows)
    counts = {s: sum(r["status"] == s for r in rows) for s in ("processed", "done", "quarantined")}
    return {"recordings": len(rows), **counts, "index": index}


@flow(name="process-new-recordings", log_prints=False)
def process_new(
    watch_dir: str, out_dir: str, config_path: str | None = None, settle_s: float = 1.0
) -> dict[str, Any]:
    """The scheduled job: recordings that appeared in ``watch_dir`` since the last run
    (those without a finished output for this configuration), skipping incomplete files."""
    out = Path(out_dir)
    found = discover(Path(watch_dir), exclude=out)
    ready, waiting = [], []
    for p in found:
        ok, why = is_complete(p, settle_s)
        (ready if ok else waiting).append((p, why))
    rows = _run_rows([p for p, _ in ready], out, config_path) if ready else []
    rows += [{"input": str(p), "status": "waiting", "reason": why} for p, why in waiting]
    index = write_index(out, rows) if rows else {}
    return {
        "recordings": len(found),
        "waiting": len(waiting),
        "processed": sum(r["status"] == "processed" for r in rows),
        "quarantined": sum(r["status"] == "quarantined" for r in rows),
        "index": index,
    }


class _SlowWorkerExit(logging.Filter):
    """Drops the nanny's "Worker process still alive after 4.0 seconds, killing": when the
    local cluster closes, every result is in; on a busy machine an idle worker may take longer
    than that to exit and is killed, losing nothing. The warning, one line per worker, broke
    the at-most-two-lines stderr of ``aeromag reprocess``; other nanny warnings (a worker
    restarted for memory, say) still show."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("Worker process still alive after")


def dask_runner(workers: int, address: str | None):
    """Prefect's Dask task runner: a cluster at ``address``, or a local one.

    Parameters
    ----------
    workers : int
        Worker processes of the local cluster (one thread each).
    address : str or None
        ``tcp://HOST:PORT`` of an existing scheduler.

    Returns
    -------
    prefect_dask.DaskTaskRunner
    """
    from prefect_dask import DaskTaskRunner

    for name in (
        "distributed",
        "distributed.scheduler",
        "distributed.nanny",
        "distributed.core",
        "distributed.worker",
        "distributed.http.proxy",
    ):
        logging.getLogger(name).setLevel(logging.WARNING)  # the scheduler's chatter
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
            "silence_logs": logging.WARNING,
        }
    )


# --------------------------------------------------------------------------------------------
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_prefect_server(env: dict[str, str] | None = None) -> tuple[str, subprocess.Popen]:
    """Start ``prefect server`` on a free 127.0.0.1 port (analytics off) in its own session;
    returns its API URL and the process (the caller waits for it: :func:`wait_healthy`, and
    terminates it). ``env``: the server's environment (default: this process's)."""
    port = _free_port()
    env = {
        **(os.environ if env is None else env),
        "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
        "DO_NOT_TRACK": "1",
    }
    proc = subprocess.Popen(
        [sys.executable, "-m", "prefect", "server", "start"]
        + ["--host", "127.0.0.1", "--port", str(port)],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    return f"http://127.0.0.1:{port}/api", proc


@contextlib.contextmanager
def prefect_api(timeout_s: float = 90.0) -> Iterator[str]:
    """A Prefect API for flows whose tasks run in other processes (Dask workers, served
    deployments): the configured ``PREFECT_API_URL``, else a local server started on
    127.0.0.1 for the duration (without one each worker process would start its own
    temporary server, 15-20 s apiece)."""
    url = os.environ.get("PREFECT_API_URL")
    if url:
        yield url
        return
    url, proc = start_prefect_server()
    try:
        wait_healthy(url, timeout_s, proc)
        os.environ["PREFECT_API_URL"] = url
        from prefect.settings import PREFECT_API_URL, temporary_settings

        with temporary_settings(updates={PREFECT_API_URL: url}):
            yield url
    finally:
        os.environ.pop("PREFECT_API_URL", None)
        proc.terminate()
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()


def wait_healthy(url: str, timeout_s: float, proc: subprocess.Popen | None = None) -> None:
    """Wait until the Prefect API at ``url`` answers ``/health`` with 200.

    Parameters
    ----------
    url : str
        The API URL (``http://HOST:PORT/api``).
    timeout_s : float
        How long to wait, s.
    proc : subprocess.Popen, optional
        The server process; its exit ends the wait at once.

    Raises
    ------
    AeromagError
        The server exited or did not become healthy in time.
    """
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
