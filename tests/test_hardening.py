"""Bad input never loses data or crashes: a corpus of damaged recordings, each with its expected
outcome — a one-line error naming file, channel and problem, or processing with the damage
excluded and a loss report — and the input byte-identical afterwards."""

from __future__ import annotations

import json
import struct
import tracemalloc

import pytest
from mcap.reader import make_reader

from pipeline.io.reader import read_flight
from pipeline.io.scan import scan_mcap
from tests.conftest import sha256
from tests.corpus import (
    BOX,
    CORPUS,
    GAP,
    NAN_BURST,
    absurd_chunk_size,
    box_messages,
    rewrite,
    run_cli,
    t_at,
)
from tests.mcap_builder import NS


@pytest.fixture(scope="module")
def messages():
    return box_messages()


@pytest.mark.parametrize("case", list(CORPUS))
def test_bad_input_corpus(case, messages, tmp_path, capsys):
    builder, outcome = CORPUS[case]
    src = tmp_path / "flight.mcap"
    builder(src, messages)
    before = sha256(src)
    out, js = tmp_path / "out" / "c.mcap", tmp_path / "out" / "c.json"
    code, stdout, stderr = run_cli(
        ["compensate", str(src), "--out", str(out), "--json", str(js), "--model", "tl18"], capsys
    )
    assert sha256(src) == before, "the input was modified"
    assert "Traceback" not in stdout + stderr
    leftovers = [p.name for p in (tmp_path / "out").glob(".*")] if out.parent.exists() else []
    assert leftovers == [], "a partial output was left behind"
    if outcome[0] == "error":
        _, channel, words = outcome
        lines = [ln for ln in (stdout + stderr).splitlines() if ln.strip()]
        assert code == 2, stdout + stderr
        assert len(lines) == 1 and lines[0].startswith("aeromag: error: ")
        assert str(src) in lines[0] and words in lines[0], lines[0]
        if channel:
            assert f": {channel}: " in lines[0], lines[0]
        assert not out.exists() and not js.exists()
        return
    assert code == 0, stdout + stderr
    summary = json.loads(js.read_text())
    inp = summary["input"]
    text = json.dumps(inp)
    assert outcome[1] in text, inp["notes"]
    with out.open("rb") as f:  # the output is a complete, valid recording
        reader = make_reader(f, validate_crcs=True)
        assert reader.get_summary() is not None
        n_out = sum(1 for _ in reader.iter_messages(topics=["/mag/compensated"]))
    assert n_out > 0.5 * inp["epochs"]
    fom = summary["fom_nT"]
    if fom["uncompensated"] is not None:
        assert fom["compensated"] < fom["uncompensated"] / 5  # still compensates well
    if case in (
        "truncated mid-chunk",
        "flipped byte in a chunk (CRC)",
        "absurd uncompressed chunk size",
    ):
        loss = inp["losses"][0]
        assert loss["bytes_lost"] > 0 and loss["offset"] > 0
        assert inp["epochs"] < 0.99 * sum(1 for m in messages if m[0] == "/mag/scalar")
    if case == "NaN/inf burst":
        d = inp["dropped"]["/mag/scalar"]
        burst = [
            t
            for tp, t, _ in messages
            if tp == "/mag/scalar"
            and t_at(messages, NAN_BURST[0]) <= t <= t_at(messages, NAN_BURST[1])
        ]
        assert d["samples"] == len(burst)
        t0 = inp["start_ns"]
        assert d["ranges_s"] == [
            [
                pytest.approx((burst[0] - t0) / NS, abs=1e-3),
                pytest.approx((burst[-1] - t0) / NS, abs=1e-3),
            ]
        ]
    if case == "non-UTF-8 JSON":
        assert inp["dropped"]["/mag/scalar"]["samples"] == 30
    if case == "time gap":
        gaps = [g for g in inp["gaps"] if g["topic"] == "/mag/scalar"]
        span = (GAP[1] - GAP[0]) * (messages[-1][1] - messages[0][1]) / NS
        assert len(gaps) == 1 and gaps[0]["duration_s"] == pytest.approx(span, rel=0.05)
    if case == "unsorted and duplicated timestamps":
        assert any("duplicated timestamps" in n for n in inp["notes"])


def test_salvage_reads_every_intact_chunk(messages, tmp_path):
    """A truncated file gives back exactly the messages of its complete chunks."""
    full = rewrite(tmp_path / "full.mcap", messages)
    with full.open("rb") as f:
        ci = make_reader(f).get_summary().chunk_indexes
    cut = ci[len(ci) // 2]
    part = tmp_path / "cut.mcap"
    part.write_bytes(full.read_bytes()[: cut.chunk_start_offset + 100])
    sc = scan_mcap(part)
    got = sum(len(c.data) for c in sc.channels.values())
    with full.open("rb") as f:
        expected = sum(
            1
            for _, _, m in make_reader(f).iter_messages()
            if m.log_time <= ci[len(ci) // 2 - 1].message_end_time
            and any(
                c.message_start_time <= m.log_time <= c.message_end_time for c in ci[: len(ci) // 2]
            )
        )
    assert got == expected and got > 0
    assert [x.reason for x in sc.losses] == ["file truncated: the last record is incomplete"]


def test_hostile_declared_sizes_keep_memory_bounded(messages, tmp_path):
    p = tmp_path / "hostile.mcap"
    absurd_chunk_size(p, messages)
    tracemalloc.start()
    try:
        fl = read_flight(p)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 200 * 2**20 and fl.losses and "declares" in fl.losses[0].reason
    # a top-level record claiming more bytes than the file holds is a truncation, not a read
    data = bytearray(BOX.read_bytes()[:4096])
    struct.pack_into("<Q", data, 8 + 1, 1 << 60)  # the Header record's length
    (tmp_path / "huge.mcap").write_bytes(bytes(data))
    sc = scan_mcap(tmp_path / "huge.mcap")
    assert sc.losses and "truncated" in sc.losses[0].reason


def test_every_corpus_case_really_damages_the_recording(messages, tmp_path):
    """Each bad-input builder writes something other than the intact recording (a builder
    that silently wrote a clean file would make its corpus case pass vacuously), and the
    corpus holds both outcomes: refused with one line, and processed with a note."""
    clean = sha256(rewrite(tmp_path / "clean.mcap", messages))
    assert sha256(rewrite(tmp_path / "clean2.mcap", messages)) == clean  # deterministic
    for i, (case, (builder, _)) in enumerate(CORPUS.items()):
        path = tmp_path / f"case{i}.mcap"
        builder(path, messages)
        assert sha256(path) != clean, case
    outcomes = {o[0] for _, o in CORPUS.values()}
    assert outcomes == {"error", "processed"} and len(CORPUS) >= 12
