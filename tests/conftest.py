"""Shared test set-up: hermetic Prefect settings, simulated recordings, helpers."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile

# Prefect reads its settings at import: make them hermetic before anything imports it.
os.environ["PREFECT_HOME"] = tempfile.mkdtemp(prefix="aeromag-test-prefect-")
# each session (and each xdist worker) has its own home: gone with the process
atexit.register(shutil.rmtree, os.environ["PREFECT_HOME"], ignore_errors=True)
os.environ["PREFECT_SERVER_ANALYTICS_ENABLED"] = "false"
os.environ["DO_NOT_TRACK"] = "1"
os.environ["PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS"] = "90"
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
# BLAS on one thread, as the flows run it (flows/__init__.py): tests call pipeline directly,
# and on a busy 2-core machine OpenBLAS's second thread slows small SVDs ~100x
for _key in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_key, "1")

import hashlib  # noqa: E402
import subprocess  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

from pipeline.simulate import Scenario, simulate, write_simulation  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
FIXTURES = REPO / "fixtures"

# No noise, every stream at 10 Hz on the same clock: physics checks compare samples 1:1.
QUIET = [
    "sensors.scalar_noise_nT=0.0",
    "sensors.scalar_drift_nT_per_sqrt_s=0.0",
    "sensors.vector_noise_nT=0.0",
    "sensors.attitude_noise_deg=0.0",
    "sensors.gnss_noise_m=0.0",
    "sensors.base_noise_nT=0.0",
    "sensors.vector_rate_hz=10.0",
    "sensors.attitude_rate_hz=10.0",
    "sensors.gnss_rate_hz=10.0",
    "sensors.aux_rate_hz=10.0",
    "sensors.clock_offset_s={scalar=0.0, vector=0.0, attitude=0.0, gnss=0.0, base=0.0, aux=0.0}",
]

# two induced sources 300-500 m deep under the uav-small block (a negative margin keeps them
# inside it): geology the 50 m lines resolve, the largest anomaly an interior peak
MAPPED_SURVEY = (
    "uav-small",
    7,
    [
        "anomaly.depth_m=[300.0, 500.0]",
        "anomaly.dipoles=2",
        "anomaly.moment_A_m2=[2.0e7, 5.0e7]",
        "anomaly.margin_m=-100.0",
        "anomaly.remanent_fraction=0.0",
    ],
)


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def run_sim(name: str, seed: int, overrides: list[str] | None = None):
    return simulate(Scenario.load(name, overrides or []), seed)


@pytest.fixture(scope="session")
def box_path() -> Path:
    """The committed fixture: one calibration box with every contract channel."""
    return FIXTURES / "box_uav.mcap"


@pytest.fixture(scope="session")
def box_sim_file(tmp_path_factory):
    """A fresh calibration-only flight (one box) at the default rates and clock offsets."""
    folder = tmp_path_factory.mktemp("box")
    sim = run_sim("calibration-only", 11, ["calibration.passes=1"])
    path = write_simulation(sim, folder / "box.mcap", folder / "box.truth.json")
    return sim, path


@pytest.fixture(scope="session")
def prefect_harness(prefect_server):
    """In-process flows (and the CLI called in-process) run against the session's Prefect
    server: one server start-up per session (Prefect's own test harness would start a second
    one, 10-20 s on a busy machine)."""
    from prefect.settings import PREFECT_API_URL, temporary_settings

    with temporary_settings(updates={PREFECT_API_URL: prefect_server}):
        yield prefect_server


@pytest.fixture(scope="session")
def demo_output(tmp_path_factory, prefect_harness):
    """The README's demo, run once through the CLI: folder and summary document."""
    import json

    from typer.testing import CliRunner

    from flows.cli import app

    out = tmp_path_factory.mktemp("demo")
    res = CliRunner().invoke(app, ["demo", "--out", str(out)])
    assert res.exit_code == 0, res.output
    return out, json.loads((out / "demo_flight.summary.json").read_text())


@pytest.fixture(scope="session")
def prefect_server(tmp_path_factory):
    """A real Prefect server on 127.0.0.1 (its own PREFECT_HOME), for the whole session."""
    from flows.archive import start_prefect_server, wait_healthy

    home = tmp_path_factory.mktemp("prefect-home")
    env = {**os.environ, "PREFECT_HOME": str(home)}
    env.pop("PREFECT_API_URL", None)
    url, proc = start_prefect_server(env)
    try:
        wait_healthy(url, 120, proc)
        yield url
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
