"""An archive's jobs, without Prefect: which recordings are there and complete, each one's
job folder (``OUT/<stem>-<sha8>-<cfg8>/``, done when its summary JSON exists), processing one
into it (failures quarantined in ``OUT/quarantine/<stem>-<sha8>.txt`` with their one-line
reason), and ``OUT/index.csv`` / ``index.json``. ``flows/archive.py`` runs them on Dask.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import time
from pathlib import Path
from typing import Any

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


def clean_partials(folder: Path) -> None:
    if folder.is_dir():
        for p in folder.iterdir():
            if p.name.startswith(".") and ".partial" in p.name:
                p.unlink(missing_ok=True)


def index_figures(summary: dict) -> dict[str, Any]:
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
    from pipeline.run.postflight import run_plain

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
        clean_partials(dest)
        summary = run_plain(str(p), str(dest), config_path)
        row.update(status="processed", **index_figures(summary))
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
                row.update(index_figures(json.loads(summary.read_text())))
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


def with_pending(rows: list[dict], todo: list[tuple[Path, str]]) -> list[dict]:
    """The index rows so far, plus a ``pending`` row for each recording of ``todo`` (path,
    sha256) without one yet."""
    done = {r["input"] for r in rows}
    pending = [{"input": str(p), "sha256": s, "status": "pending"} for p, s in todo]
    return rows + [r for r in pending if r["input"] not in done]
