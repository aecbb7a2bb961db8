"""Prefect flows and the ``aeromag`` command line (thin wrappers around ``pipeline``).

Importing this package sets Prefect's environment defaults before Prefect itself is imported:
a temporary local server needs more than the default 20 s to start on a new database here, and
nothing may reach the network (see shared/docs/toolchain.md). Values already set win.

It also runs numpy's BLAS on one thread, as Dask does in its workers: the audit and the
compensation solve many small least-squares problems, for which a second thread gains little
and, on a busy machine, spin-waits (docs/benchmarks.md). Set before numpy is imported.
"""

import os

for _key, _value in {
    "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "90",
    "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
    "DO_NOT_TRACK": "1",
    "PREFECT_LOGGING_LEVEL": "WARNING",
    "OPENBLAS_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
}.items():
    os.environ.setdefault(_key, _value)
