"""Fuzzing ingest: mutated recordings give data or a one-line AeromagError — never another
exception, never a hang.

1000 cases per run here (derandomized: the same cases every run, ~4 s);
``AEROMAG_FUZZ_EXAMPLES=10000 .venv/bin/python -m pytest tests/test_fuzz.py`` is the long run
(~25 s).
"""

from __future__ import annotations

import os
import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.writer import CompressionType

from pipeline.errors import AeromagError
from pipeline.io.reader import read_flight
from tests.mcap_builder import NS, T0, attitude, build, scalar, vector

EXAMPLES = int(os.environ.get("AEROMAG_FUZZ_EXAMPLES", "1000"))


def _seed_recordings(folder) -> list[bytes]:
    msgs = []
    for i in range(120):
        t = T0 + i * NS // 10
        msgs += [
            ("/mag/scalar", t, scalar(t, 5.2e4 + 0.1 * i)),
            ("/mag/vector", t + 3, vector(t + 3, 2e4 + i, -3e3, 4.5e4)),
            ("/ins/attitude", t + 5, attitude(t + 5, 1.0, -2.0, (3.0 * i) % 360)),
        ]
    out = []
    for k, kw in enumerate(
        (
            {"compression": CompressionType.NONE, "chunk_size": 4096},
            {"compression": CompressionType.ZSTD, "chunk_size": 4096},
            {"summary": False},
        )
    ):
        out.append(build(folder / f"seed{k}.mcap", msgs, **kw).read_bytes())
    return out


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    return _seed_recordings(tmp_path_factory.mktemp("fuzz"))


# one mutation: (kind, position fraction, value)
mutation = st.tuples(
    st.sampled_from(["flip", "set", "cut", "insert", "delete", "u64", "u32", "dup"]),
    st.floats(0.0, 1.0, allow_nan=False),
    st.integers(0, 2**64 - 1),
)


def mutate(data: bytes, muts) -> bytes:
    b = bytearray(data)
    for kind, where, value in muts:
        if not b:
            break
        i = min(int(where * len(b)), len(b) - 1)
        if kind == "flip":
            b[i] ^= 1 << (value % 8)
        elif kind == "set":
            b[i] = value % 256
        elif kind == "cut":
            del b[i:]
        elif kind == "insert":
            b[i:i] = value.to_bytes(8, "little")[: 1 + value % 8]
        elif kind == "delete":
            del b[i : i + 1 + value % 64]
        elif kind == "u64" and i + 8 <= len(b):  # a hostile length or time field
            struct.pack_into("<Q", b, i, value)
        elif kind == "u32" and i + 4 <= len(b):
            struct.pack_into("<I", b, i, value % 2**32)
        elif kind == "dup":
            j = min(i + 1 + value % 512, len(b))
            b[j:j] = b[i:j]
    return bytes(b)


def _check(seeds, tmp_path_factory, which, muts):
    path = tmp_path_factory.getbasetemp() / "fuzz-case.mcap"
    path.write_bytes(mutate(seeds[which], muts))
    try:
        fl = read_flight(path)
    except AeromagError as exc:
        assert "\n" not in str(exc) and str(path) in str(exc)
        return
    assert fl.time_ns.size >= 2 and len(fl.data) == fl.time_ns.size


@settings(
    max_examples=EXAMPLES,
    deadline=5000,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(which=st.integers(0, 2), muts=st.lists(mutation, min_size=1, max_size=4))
def test_mutated_recordings_never_crash_ingest(seeds, tmp_path_factory, which, muts):
    _check(seeds, tmp_path_factory, which, muts)
