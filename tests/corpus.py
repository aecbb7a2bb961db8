"""The bad-input corpus: the committed box fixture damaged in each way a recording arrives
damaged (empty, not MCAP, truncated, a chunk's CRC, no summary, wrong units and types, NaN
bursts, gaps, hostile sizes), each case with the outcome it must have; shared by
``test_hardening.py`` (the library and the CLI) and ``test_bad_input_flows.py`` (the flows)."""

from __future__ import annotations

import json
import math
import struct
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType

from flows.cli import main
from pipeline.io.scan import scan_mcap
from tests.conftest import FIXTURES
from tests.mcap_builder import build

BOX = FIXTURES / "box_uav.mcap"
SMALL_CHUNK = 64 * 1024  # many chunks, so damage to one leaves most of the flight


def box_messages() -> list[tuple[str, int, bytes]]:
    """The fixture's messages (topic, log time, payload) in log-time order."""
    sc = scan_mcap(BOX)
    msgs = [
        (ch.topic, t, d)
        for ch in sc.channels.values()
        for t, d in zip(ch.log_time_ns, ch.data, strict=True)
    ]
    return sorted(msgs, key=lambda m: m[1])


def rewrite(path: Path, msgs, **kw) -> Path:
    return build(path, msgs, chunk_size=SMALL_CHUNK, **kw)


def scale(msgs, topic: str, fields: tuple[str, ...], factor: float):
    out = []
    for tp, t, d in msgs:
        if tp == topic:
            p = json.loads(d)
            for f in fields:
                p[f] *= factor
            d = json.dumps(p).encode()
        out.append((tp, t, d))
    return out


def t_at(msgs, fraction: float) -> int:
    return msgs[0][1] + int(fraction * (msgs[-1][1] - msgs[0][1]))


# ---- the corpus: each builder writes one damaged recording ----------------------------------
def empty(p, msgs):
    p.write_bytes(b"")


def bad_magic(p, msgs):
    data = bytearray(BOX.read_bytes())
    data[:8] = b"PK\x03\x04zip!"
    p.write_bytes(bytes(data))


def random_bytes(p, msgs):
    p.write_bytes(np.random.default_rng(5).integers(0, 256, 4096, dtype=np.uint8).tobytes())


def only_the_magic(p, msgs):
    p.write_bytes(b"\x89MCAP0\r\n")


def text_file(p, msgs):
    p.write_text("time,total_nT\n0.0,51234.5\n0.1,51234.6\n")


def scalar_channel_missing(p, msgs):
    rewrite(p, [m for m in msgs if m[0] != "/mag/scalar"])


def truncated_mid_chunk(p, msgs):
    full = rewrite(p.with_suffix(".full"), msgs)
    with full.open("rb") as f:
        ci = make_reader(f).get_summary().chunk_indexes
    c = ci[int(len(ci) * 0.9)]
    p.write_bytes(full.read_bytes()[: c.chunk_start_offset + c.chunk_length // 2])


def flipped_byte_in_chunk(p, msgs):
    """Uncompressed chunks, one digit of one payload changed: still valid JSON, so only the
    chunk CRC can tell."""
    full = rewrite(p.with_suffix(".full"), msgs, compression=CompressionType.NONE)
    data = bytearray(full.read_bytes())
    at = data.index(b'"total_nT":5', len(data) // 2) + len(b'"total_nT":5')
    data[at] = ord("1") if data[at] != ord("1") else ord("2")
    p.write_bytes(bytes(data))


def no_summary_no_footer(p, msgs):
    """A logger killed after its last chunk: no Data End, summary or footer."""
    full = rewrite(p.with_suffix(".full"), msgs, summary=False)
    p.write_bytes(full.read_bytes()[: -(13 + 29 + 8)])  # Data End, Footer, magic


def required_channel_missing(p, msgs):
    rewrite(p, [m for m in msgs if m[0] != "/mag/vector"])


def wrong_field_types(p, msgs):
    out = []
    for tp, t, d in msgs:
        if tp == "/mag/scalar":
            q = json.loads(d)
            q["total_nT"] = str(q["total_nT"])
            d = json.dumps(q).encode()
        out.append((tp, t, d))
    rewrite(p, out)


NAN_BURST = (0.40, 0.42)


def nan_inf_burst(p, msgs):
    """NaN and infinity as Python's json writes them (not JSON) and as overflowing numbers."""
    lo, hi = t_at(msgs, NAN_BURST[0]), t_at(msgs, NAN_BURST[1])
    out = []
    for tp, t, d in msgs:
        if tp == "/mag/scalar" and lo <= t <= hi:
            q = json.loads(d)
            q["total_nT"] = math.nan if t % 2 else math.inf
            d = (
                json.dumps(q).encode().replace(b"Infinity", b"1e999")
                if t % 3 == 0
                else json.dumps(q).encode()
            )
        out.append((tp, t, d))
    rewrite(p, out)


def unsorted_and_duplicated(p, msgs):
    scal = [i for i, m in enumerate(msgs) if m[0] == "/mag/scalar"]
    a, b = scal[len(scal) // 3], scal[len(scal) // 3 + 40]
    block = msgs[a:b]
    out = msgs[:a] + block[::-1] + msgs[b:] + [msgs[i] for i in scal[100:110]]
    rewrite(p, out)


GAP = (0.55, 0.57)


def time_gap(p, msgs):
    lo, hi = t_at(msgs, GAP[0]), t_at(msgs, GAP[1])
    rewrite(p, [m for m in msgs if not lo <= m[1] <= hi])


def scalar_in_tesla(p, msgs):
    rewrite(p, scale(msgs, "/mag/scalar", ("total_nT",), 1e-9))


def vector_in_microtesla(p, msgs):
    rewrite(p, scale(msgs, "/mag/vector", ("x_nT", "y_nT", "z_nT"), 1e-3))


def absurd_chunk_size(p, msgs):
    full = rewrite(p.with_suffix(".full"), msgs)
    with full.open("rb") as f:
        c = make_reader(f).get_summary().chunk_indexes[5]
    data = bytearray(full.read_bytes())
    # Chunk body: start u64, end u64, uncompressed size u64, ...
    struct.pack_into("<Q", data, c.chunk_start_offset + 9 + 16, 1 << 62)
    p.write_bytes(bytes(data))


def non_utf8_json(p, msgs):
    scal = [i for i, m in enumerate(msgs) if m[0] == "/mag/scalar"]
    bad = set(scal[500:530])
    rewrite(
        p,
        [
            (tp, t, (b'{"total_nT": "\xff\xfe"}' if i in bad else d))
            for i, (tp, t, d) in enumerate(msgs)
        ],
    )


def attitude_in_radians(p, msgs):
    rewrite(p, scale(msgs, "/ins/attitude", ("roll_deg", "pitch_deg", "yaw_deg"), math.pi / 180))


# class -> (builder, outcome): ("error", channel or None, words) | ("processed", check)
CORPUS = {
    "empty file": (empty, ("error", None, "empty file")),
    "not MCAP (bad magic)": (bad_magic, ("error", None, "not a readable MCAP recording")),
    "random bytes": (random_bytes, ("error", None, "not a readable MCAP recording")),
    "only the MCAP magic": (only_the_magic, ("error", None, "not a readable MCAP recording")),
    "a text file": (text_file, ("error", None, "not a readable MCAP recording")),
    "no /mag/scalar": (
        scalar_channel_missing,
        ("error", "/mag/scalar", "no scalar magnetometer channel"),
    ),
    "truncated mid-chunk": (truncated_mid_chunk, ("processed", "file truncated")),
    "flipped byte in a chunk (CRC)": (flipped_byte_in_chunk, ("processed", "CRC mismatch")),
    "no summary, no footer": (no_summary_no_footer, ("processed", "no footer")),
    "required channel missing": (
        required_channel_missing,
        ("error", "/mag/vector", "channel is absent"),
    ),
    "wrong field types": (wrong_field_types, ("error", "/mag/scalar", "is str, not a number")),
    "NaN/inf burst": (nan_inf_burst, ("processed", "dropped")),
    "unsorted and duplicated timestamps": (unsorted_and_duplicated, ("processed", "order")),
    "time gap": (time_gap, ("processed", "gap")),
    "scalar in tesla": (scalar_in_tesla, ("error", "/mag/scalar", "look like tesla")),
    "vector in µT": (vector_in_microtesla, ("error", "/mag/vector", "look like uT")),
    "absurd uncompressed chunk size": (absurd_chunk_size, ("processed", "declares")),
    "non-UTF-8 JSON": (non_utf8_json, ("processed", "dropped")),
    "attitude in radians": (attitude_in_radians, ("error", "/ins/attitude", "radians")),
}


def run_cli(args: list[str], capsys) -> tuple[int, str, str]:
    old = sys.argv
    sys.argv = ["aeromag", *args]
    try:
        with pytest.raises(SystemExit) as ex:
            main()
    finally:
        sys.argv = old
    out = capsys.readouterr()
    return int(ex.value.code or 0), out.out, out.err
