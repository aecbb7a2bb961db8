"""Writer: every input record preserved byte for byte, new channels added, atomic output."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from pipeline.errors import AeromagError
from pipeline.io.writer import OutputChannel, write_with_new_channels
from tests.conftest import sha256
from tests.mcap_builder import NS, T0, build, scalar, vector
from tests.recordings import records


def make_rich_input(path: Path) -> Path:
    """Contract channels plus what a real logger adds: a protobuf channel, a channel without a
    schema, an empty channel, attachments and metadata."""
    msgs = []
    for i in range(200):
        t = T0 + i * NS // 10
        msgs += [
            ("/mag/scalar", t, scalar(t, 50000.0 + np.sin(i))),
            ("/mag/vector", t + 3_000_000, vector(t + 3_000_000, 1.0 * i, 2.0, 3.0)),
            ("/cam/pb", t + 1, bytes([i % 256, 0, 255, 17]) * 5),
            ("/raw/noschema", t + 2, b"raw-bytes-%d" % i),
        ]

    def extra(w):
        w.add_attachment(
            create_time=T0, log_time=T0, name="calib.txt", media_type="text/plain", data=b"hello"
        )
        w.add_metadata(name="logger", data={"version": "1.2", "pilot": "X"})
        sid = w.register_schema(name="aeromag.Scalar", encoding="jsonschema", data=b"{}")
        w.register_channel(topic="/aux/unused", message_encoding="json", schema_id=sid)

    def builder(path):
        return build(
            path,
            msgs,
            schema_of={"/cam/pb": "foxglove.CompressedImage", "/raw/noschema": ""},
            encoding={"/cam/pb": "protobuf", "/raw/noschema": "cbor"},
            extra=extra,
        )

    return builder(path)


def test_round_trip_preserves_every_record_byte_for_byte(tmp_path):
    src = make_rich_input(tmp_path / "in.mcap")
    before = sha256(src)
    new = OutputChannel("/aeromag/log", "foxglove.Log")
    for k in range(5):
        new.add(
            T0 + k * NS, {"level": 2, "message": f"line {k}", "name": "t", "file": "", "line": 0}
        )
    dst = write_with_new_channels(
        src,
        tmp_path / "out" / "out.mcap",
        [new],
        metadata={"aeromag.run": {"aeromag_version": "x"}},
    )
    assert sha256(src) == before  # the input is never modified
    m_in, a_in, md_in, ch_in = records(src)
    m_out, a_out, md_out, ch_out = records(dst)
    kept = [m for m in m_out if m[0] != "/aeromag/log"]
    assert sorted(kept, key=repr) == sorted(m_in, key=repr)  # content, times, sequence, bytes
    assert a_out == a_in
    assert md_out[: len(md_in)] == md_in and ("aeromag.run", {"aeromag_version": "x"}) in md_out
    assert "/aux/unused" in ch_out and set(ch_in) <= set(ch_out)  # empty channel kept
    added = [m for m in m_out if m[0] == "/aeromag/log"]
    assert len(added) == 5 and added[0][3][0] == "foxglove.Log"
    # the merged file is in log-time order, so viewers stream it without seeking back
    times = [m[4] for m in m_out]
    assert times == sorted(times)


def test_output_refuses_to_overwrite_the_input(tmp_path):
    src = make_rich_input(tmp_path / "in.mcap")
    before = sha256(src)
    with pytest.raises(AeromagError, match="the input is never overwritten"):
        write_with_new_channels(src, src, [])
    with pytest.raises(AeromagError, match="the input is never overwritten"):
        write_with_new_channels(src, tmp_path / "." / "in.mcap", [])
    assert sha256(src) == before


def test_failed_write_leaves_no_partial_file(tmp_path):
    src = make_rich_input(tmp_path / "in.mcap")
    dst = tmp_path / "out.mcap"
    dst.write_bytes(b"previous result")
    bad = OutputChannel("/aeromag/log", "foxglove.Log")
    bad.add(T0 + 10 * NS, {"level": 2, "message": object()})  # not serialisable
    with pytest.raises(TypeError):
        write_with_new_channels(src, dst, [bad])
    assert dst.read_bytes() == b"previous result"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.mcap", "out.mcap"]


def test_existing_output_channel_is_refused(tmp_path):
    src = make_rich_input(tmp_path / "in.mcap")
    ch = OutputChannel("/aeromag/log", "foxglove.Log")
    ch.add(T0, {"level": 2, "message": "x", "name": "t", "file": "", "line": 0})
    once = write_with_new_channels(src, tmp_path / "once.mcap", [ch])
    with pytest.raises(AeromagError, match="/aeromag/log: the input already has this output"):
        write_with_new_channels(once, tmp_path / "twice.mcap", [ch])


def unchunked_copy(src: Path, dst: Path) -> Path:
    """``src`` rewritten with every record outside chunks, messages in file order."""
    from mcap.writer import Writer

    with src.open("rb") as f, dst.open("wb") as g:
        w = Writer(g, use_chunking=False)
        w.start()
        done = set()
        for s, c, m in make_reader(f).iter_messages(log_time_order=False):
            if c.id not in done:
                w.register_schema(name=s.name, encoding=s.encoding, data=s.data)
                w.register_channel(c.topic, c.message_encoding, s.id, dict(c.metadata))
                done.add(c.id)
            w.add_message(c.id, m.log_time, m.data, m.publish_time, m.sequence)
        w.finish()
    return dst


@pytest.mark.parametrize("chunk_size", [1 << 20, 300, 0])
def test_input_out_of_log_time_order_is_merged_like_a_stable_sort(tmp_path, chunk_size):
    """The writer reads the input's records again while writing (not held in memory): a file
    out of log-time order, with equal times on different channels, across small chunks (or
    none: ``chunk_size`` 0), still comes out as the stable time sort of (input by channel,
    file order within; then the new channel), every input record exactly once."""
    rng = np.random.default_rng(3)
    msgs = []
    for i in rng.permutation(120).tolist():
        t = T0 + int(i) * NS // 10
        msgs += [
            ("/mag/vector", t, vector(t, 1.0 * i, 2.0, 3.0)),
            ("/mag/scalar", t, scalar(t, float(i))),
        ]
    src = build(tmp_path / "in.mcap", msgs, chunk_size=chunk_size or 1 << 20)
    if not chunk_size:
        src = unchunked_copy(src, tmp_path / "unchunked.mcap")
    new = OutputChannel("/aeromag/log", "foxglove.Log")
    for k in (30, 0, 60):  # equal to input times, out of order
        new.add(
            T0 + k * NS // 10, {"level": 2, "message": f"{k}", "name": "t", "file": "", "line": 0}
        )
    dst = write_with_new_channels(src, tmp_path / "out.mcap", [new])
    with src.open("rb") as f:
        r = make_reader(f)
        inp = [
            (c.id, c.topic, m.log_time, m.data) for _, c, m in r.iter_messages(log_time_order=False)
        ]
    grouped = sorted(enumerate(inp), key=lambda x: x[1][0])  # by channel id, file order within
    expected = [
        (topic, t, data) for _, (_, topic, t, data) in sorted(grouped, key=lambda x: x[1][2])
    ]
    got = [m for m in records(dst)[0]]
    added = [(m[0], m[4]) for m in got if m[0] == "/aeromag/log"]
    assert added == [("/aeromag/log", T0 + k * NS // 10) for k in (0, 30, 60)]
    # input records at their places; each new message after the input ones of its time
    assert [(m[0], m[4], m[7]) for m in got if m[0] != "/aeromag/log"] == expected
    times = [m[4] for m in got]
    assert times == sorted(times)
    for k in (0, 30, 60):
        at = [j for j, m in enumerate(got) if m[4] == T0 + k * NS // 10]
        assert got[at[-1]][0] == "/aeromag/log"


def test_column_channels_write_the_bytes_of_their_payloads(tmp_path):
    """A channel given as columns (encoded a block at a time) writes the same file, byte for
    byte, as the same messages given one payload at a time: floats of every magnitude,
    NaN and infinities as null, float32 as float64, ints, repeated and escaped strings,
    constants, unsorted times across several blocks."""
    import orjson

    from pipeline.io.writer import encode_rows

    rng = np.random.default_rng(7)
    n = 40_000  # more than one encoding block
    x = rng.normal(0.0, 1.0, n) * 10.0 ** rng.integers(-12, 17, n)
    x[:6] = [np.nan, np.inf, -np.inf, -0.0, 1e16, 5e-324]
    labels = np.array([f'L{k % 7}"\\ é' for k in range(n)], object)
    columns = {
        "sensor_id": "mag-1",
        "total_nT": x,
        "single": rng.normal(50_000.0, 10.0, n).astype(np.float32),
        "fiducial": np.arange(n, dtype=np.int64) * 3,
        "line_id": labels,
        "model": None,
    }
    t = T0 + rng.permutation(n).astype(np.int64) * (NS // 10)

    def payload(i: int) -> dict:
        return {
            "sensor_id": "mag-1",
            "total_nT": float(x[i]) if np.isfinite(x[i]) else None,
            "single": float(columns["single"][i]),
            "fiducial": int(columns["fiducial"][i]),
            "line_id": str(labels[i]),
            "model": None,
        }

    ix = np.arange(0, n, 97)
    bulk = encode_rows(columns, ix, t[ix])
    one = [
        orjson.dumps({**payload(i), "timestamp": {"sec": int(t[i]) // NS, "nsec": int(t[i]) % NS}})
        for i in ix
    ]
    assert bulk == one
    src = make_rich_input(tmp_path / "in.mcap")
    as_rows = OutputChannel.rows("/x", "aeromag.CompensatedField", t, payload)
    as_columns = OutputChannel.columns("/x", "aeromag.CompensatedField", t, columns)
    a = write_with_new_channels(src, tmp_path / "rows.mcap", [as_rows])
    b = write_with_new_channels(src, tmp_path / "columns.mcap", [as_columns])
    assert sha256(a) == sha256(b)
    assert as_columns.messages[5] == as_rows.messages[5]  # read one at a time: the same


def test_bulk_writer_failing_records_leave_no_thread(tmp_path):
    """Chunks are compressed on a second thread while the next is packed: a record source that
    fails part-way raises its own error and leaves no compression thread behind; chunks packed
    before the failure were written whole, in order (the file's atomic writer discards them)."""
    import io
    import threading

    from pipeline.io.bulk import BulkWriter

    def records(n_ok: int):
        for i in range(n_ok):
            yield b"\x05" + (40).to_bytes(8, "little") + bytes(40) + bytes([i % 256])
        raise RuntimeError("source failed")

    before = threading.active_count()
    w = BulkWriter(io.BytesIO(), chunk_size=500)
    n = 10_000
    with pytest.raises(RuntimeError, match="source failed"):
        w.add_messages(records(9_000), np.zeros(n, np.uint16), np.arange(n, dtype=np.uint64))
    assert threading.active_count() == before
    # records are taken 8 192 at a time: the first block's 819 full chunks of ten 50-byte
    # records were written (the last one from the failure's cleanup), in order
    assert [c.uncompressed_size for c in w.chunk_indexes] == [500] * 819
    starts = [c.chunk_start_offset for c in w.chunk_indexes]
    assert starts == sorted(starts)


def test_an_output_under_a_file_is_one_line_before_the_work(tmp_path, box_path):
    """An output path whose folder is a regular file: exit 2 and one line naming the path,
    no traceback; ``process`` refuses before any flow starts."""
    import tests.cli
    from pipeline.run.outputs import require_writable
    from pipeline.run.postflight import checked

    blocker = tmp_path / "afile"
    blocker.write_text("")
    res = tests.cli.run(
        "compensate",
        str(box_path),
        "--out",
        str(blocker / "o.mcap"),
        "--json",
        str(blocker / "s.json"),
    )
    assert res.returncode == 2, res.stdout + res.stderr
    lines = [ln for ln in (res.stdout + res.stderr).splitlines() if ln.strip()]
    assert lines[-1].startswith("aeromag: error:") and str(blocker) in lines[-1]
    assert "Traceback" not in res.stdout + res.stderr
    with pytest.raises(AeromagError, match="a file, not a folder"):
        with checked(box_path, blocker / "sub"):
            pass
    with pytest.raises(AeromagError, match="a folder, not a file"):
        require_writable(tmp_path)
    require_writable(tmp_path / "new" / "deeper", folder=True)  # made when written
    assert list(tmp_path.iterdir()) == [blocker]
