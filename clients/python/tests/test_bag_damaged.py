"""Damaged, hostile and truncated bags: `read_bag` reads them as the Rust reader
(`clients/bag`, run here as `scancorr correct`) does — every checksum verified, decompression
capped, undecodable messages counted, a bag cut short read up to its last complete chunk —
and never returns changed arrays without saying so.

The bags are the simulator's (zstd chunks, as `sim` and `record` write them), damaged here;
the hostile ones carry valid checksums (`fix_crcs`), as a hostile writer's would."""

from __future__ import annotations

import json
import pathlib
import random
import struct
import subprocess
import sys
import warnings
import zlib
from concurrent.futures import ThreadPoolExecutor
from typing import Dict, List, Optional, Tuple

import numpy as np
import pytest

import scancorr
from scancorr.bag import RECORD_LIMIT, BagError, BagWarning

from conftest import binary, run

MAGIC = b"\x89MCAP0\r\n"
CHUNK, MESSAGE, MESSAGE_INDEX, DATA_END, FOOTER = 0x06, 0x05, 0x07, 0x0F, 0x02


# ---- helpers: the file's layout, read independently of the package -------------------------


def u64(b: bytes, at: int) -> int:
    return struct.unpack_from("<Q", b, at)[0]


def records(b: bytes) -> List[Tuple[int, int, int]]:
    """(offset, opcode, end) of the top-level records of a complete bag, header to footer."""
    out, pos = [], len(MAGIC)
    while pos < len(b) - len(MAGIC):
        op, n = b[pos], u64(b, pos + 1)
        out.append((pos, op, pos + 9 + n))
        pos += 9 + n
    assert pos == len(b) - len(MAGIC) and out[-1][1] == FOOTER
    return out


def chunks(b: bytes) -> List[Tuple[int, int]]:
    """(start, end) of each chunk record."""
    return [(s, e) for s, op, e in records(b) if op == CHUNK]


def summary_start(b: bytes) -> int:
    return u64(b, len(b) - 37 + 9)


def fix_crcs(b: bytearray) -> None:
    """Recomputes the data-section CRC (in the data-end record) and the summary CRC (in the
    footer) after `b` was edited: a hostile file carries valid checksums."""
    s = summary_start(b)
    data_end = s - 13
    assert b[data_end] == DATA_END
    b[s - 4 : s] = struct.pack("<I", zlib.crc32(b[:data_end]))
    footer = len(b) - 37
    b[len(b) - 12 : len(b) - 8] = struct.pack("<I", zlib.crc32(b[s : footer + 25]))


def chunk_record(compressed: bytes, claimed: int, compression: bytes = b"zstd") -> bytes:
    """A chunk record holding `compressed`, claiming `claimed` uncompressed bytes."""
    body = (
        struct.pack("<QQQI", 0, 10**9, claimed, 0)
        + struct.pack("<I", len(compression))
        + compression
        + struct.pack("<Q", len(compressed))
        + compressed
    )
    return bytes([CHUNK]) + struct.pack("<Q", len(body)) + body


def zstd_bomb(total: int) -> bytes:
    """A zstd frame of RLE blocks: `total` zero bytes in 4 bytes per 128 KiB."""
    block = 1 << 17
    out = bytearray(b"\x28\xb5\x2f\xfd\x00\x38")  # magic; no content size; 128 KiB window
    n = total // block
    for i in range(n):
        out += ((i == n - 1) | 1 << 1 | block << 3).to_bytes(3, "little") + b"\x00"
    return bytes(out)


def correct(d: pathlib.Path, bag: pathlib.Path, calib: str, out: str) -> Tuple[int, str, Optional[dict]]:
    """`scancorr correct` of `bag` (the Rust reader): exit code, stderr, its JSON summary."""
    r = subprocess.run(
        [str(binary("scancorr")), "correct", "--bag", str(bag), "--calib", calib, "--out", out, "--force", "--json"],
        cwd=d,
        capture_output=True,
        text=True,
    )
    return r.returncode, r.stderr, json.loads(r.stdout) if r.returncode == 0 else None


def read(path: pathlib.Path, **kw) -> Tuple[scancorr.Bag, List[str]]:
    """read_bag, with the BagWarnings it issued."""
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        b = scancorr.read_bag(path, **kw)
    return b, [str(x.message) for x in w if issubclass(x.category, BagWarning)]


def same_arrays(a: scancorr.Bag, b: scancorr.Bag) -> bool:
    if a.topics() != b.topics() or a.metadata != b.metadata:
        return False
    for t in a.topics():
        x, y = a[t], b[t]
        if x.dtype != y.dtype or len(x) != len(y):
            return False
        for n in x.dtype.names:
            eq = np.array_equal(x[n], y[n]) if x.dtype[n] == object else np.array_equal(x[n], y[n], equal_nan=True)
            if not eq:
                return False
    return True


def location(e: BagError) -> str:
    """Where the error says the damage is, in the Rust reader's words."""
    if e.kind == "damaged":
        return f"{e.path}: damaged bag: {e.what} at byte offset {e.offset}: "
    return str(e)


def samples(b: scancorr.Bag) -> int:
    return sum(len(c.data) for c in b.channels.values())


# ---- fixtures ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> Dict[str, object]:
    """A small zstd bag (a ring at 100 Hz: 200 kB, one chunk) and its calibration."""
    d = tmp_path_factory.mktemp("small")
    run(d, "sim", "--program", "ring", "--rate", "100", "--seed", "3", "--out", "s.mcap", "--calib-out", "c.json")
    rc, err, _ = correct(d, d / "s.mcap", "c.json", "o.mcap")
    assert rc == 0, err
    return {"dir": d, "bag": d / "s.mcap", "bytes": (d / "s.mcap").read_bytes()}


@pytest.fixture(scope="module")
def ring(tmp_path_factory: pytest.TempPathFactory) -> Dict[str, object]:
    """A ring at 1000 Hz: 900 kB in three zstd chunks."""
    d = tmp_path_factory.mktemp("ring3")
    run(d, "sim", "--program", "ring", "--seed", "4", "--out", "r.mcap", "--calib-out", "c.json")
    b = (d / "r.mcap").read_bytes()
    assert len(chunks(b)) >= 3, chunks(b)
    return {"dir": d, "bag": d / "r.mcap", "bytes": b}


# ---- the tests -----------------------------------------------------------------------------


def test_every_bit_flip_the_rust_reader_refuses_is_refused(small: Dict[str, object]) -> None:
    """Single bit flips over a zstd bag, densely where the structure is (every record's opcode
    and length, every byte of the header, the chunk's header, the data end and the footer) and
    at random elsewhere: the Python reader refuses exactly the flips `scancorr correct`
    refuses, naming the same place (file, record or chunk, byte offset); every other flip
    reads the very same arrays, and says what it found (a damaged summary, a missing footer)."""
    d: pathlib.Path = small["dir"]  # type: ignore[assignment]
    bag: bytes = small["bytes"]  # type: ignore[assignment]
    ref, warned = read(small["bag"])  # type: ignore[arg-type]
    assert not warned and not ref.problems()
    recs = records(bag)
    (c_start, c_end), = chunks(bag)
    rng = random.Random(44)
    where = set(range(len(MAGIC), c_start + 60))  # header, chunk header
    for start, op, end in recs:
        where |= {start, start + 1 + rng.randrange(8)}  # opcode, length
        if op in (DATA_END, FOOTER):
            where |= set(range(start, end))
    where |= set(range(len(bag) - len(MAGIC), len(bag)))  # end magic
    where |= {rng.randrange(len(bag)) for _ in range(150)}
    where |= {rng.randrange(c_start, c_end) for _ in range(50)}
    flips = [(at, 1 << rng.randrange(8)) for at in sorted(where)]
    assert len(flips) > 400

    def damaged(i: int) -> pathlib.Path:
        at, bit = flips[i]
        b = bytearray(bag)
        b[at] ^= bit
        p = d / f"flip-{i}.mcap"
        p.write_bytes(b)
        return p

    paths = [damaged(i) for i in range(len(flips))]

    def rust_reads(i: int) -> Tuple[int, str]:
        rc, err, _ = correct(d, paths[i], "c.json", f"flip-out-{i}.mcap")
        (d / f"flip-out-{i}.mcap").unlink(missing_ok=True)
        return rc, err

    # The Rust reader's runs go on beside the Python reader's.
    with ThreadPoolExecutor(4) as pool:
        rust = pool.map(rust_reads, range(len(flips)))
        python = []
        for p in paths:
            try:
                b, w = read(p)
                python.append((b, w))
            except BagError as e:
                python.append(e)
        rust = list(rust)
    for p in paths:
        p.unlink()
    tally = {"refused": 0, "same": 0, "in chunk": 0}
    for (at, bit), p, (rc, err), got in zip(flips, paths, rust, python):
        what = f"bit {bit:#04x} of byte {at}"
        if isinstance(got, BagError):
            assert rc != 0, f"{what}: the Rust reader reads it, the Python reader refuses: {got}"
            assert str(p) in str(got), f"{what}: {got}"
            assert location(got) in err, f"{what}: Python: {got}\nRust: {err}"
            if c_start <= at < c_end:
                # Damage inside the chunk is pinned on it — unless its records come out intact
                # (its time range, a zstd frame header's window size): then the data-section
                # CRC finds it, as in the Rust reader.
                assert location(got) in (
                    f"{p}: damaged bag: chunk at byte offset {c_start}: ",
                    f"{p}: damaged bag: data section at byte offset 0: ",
                ), f"{what}: {got}"
                tally["in chunk"] += location(got).endswith(f"chunk at byte offset {c_start}: ")
            tally["refused"] += 1
        else:
            b, w = got
            assert rc == 0, f"{what}: the Rust reader refuses it, the Python reader reads it:\n{err}"
            assert same_arrays(b, ref), f"{what}: read without an error, but other arrays"
            # Every byte is covered by a checksum or checked: a flip that costs nothing is
            # still reported (the summary was not used, or the footer is missing).
            assert b.problems() and w == b.problems(), f"{what}: not reported"
            tally["same"] += 1
    print(f"{len(flips)} flips: {tally}")
    assert tally["refused"] > len(flips) / 2 and tally["same"] > 0 and tally["in chunk"] >= 50, tally


def test_a_damaged_chunk_is_skipped_and_counted_when_asked(ring: Dict[str, object]) -> None:
    """A bit flipped in the middle chunk: an error naming the chunk (complete bag, and the
    same cut after its data section, which is scanned); with `skip_damaged=True` the other
    chunks are read and the skipped one is listed with the messages lost with it."""
    d: pathlib.Path = ring["dir"]  # type: ignore[assignment]
    bag: bytes = ring["bytes"]  # type: ignore[assignment]
    ref, _ = read(ring["bag"])  # type: ignore[arg-type]
    cs = chunks(bag)
    start, end = cs[len(cs) // 2]
    # Its messages, per channel id, from the message index records that follow it.
    recs = records(bag)
    i = [r[0] for r in recs].index(start)
    lost = 0
    for s, op, e in recs[i + 1 :]:
        if op != MESSAGE_INDEX:
            break
        lost += (u64(bag, s + 1) - 2 - 4) // 16
    assert lost > 0
    b = bytearray(bag)
    b[(start + end) // 2] ^= 0x01
    cut = summary_start(bag) + 5
    for how, data in (("complete", bytes(b)), ("cut short", bytes(b[:cut]))):
        p = d / "skip.mcap"
        p.write_bytes(data)
        with pytest.raises(BagError) as e:
            scancorr.read_bag(p)
        assert f"{p}: damaged bag: chunk at byte offset {start}: " in str(e.value), how
        assert (e.value.kind, e.value.what, e.value.offset) == ("damaged", "chunk", start)
        rc, err, _ = correct(d, p, "c.json", "skip-out.mcap")
        assert rc != 0 and f"damaged bag: chunk at byte offset {start}: " in err, (how, err)

        got, w = read(p, skip_damaged=True)
        assert len(got.damaged_chunks) == 1, (how, got.damaged_chunks)
        dc = got.damaged_chunks[0]
        assert (dc.offset, dc.length, dc.messages_lost) == (start, end - start, lost), (how, dc)
        assert "messages lost" in str(dc) and any(str(dc) in line for line in w), (how, w)
        assert sum(c.messages for c in got.channels.values()) == sum(c.messages for c in ref.channels.values()) - lost
        for t in ref.topics():
            # What is read is the reference without the lost chunk's samples, in order.
            a, r = got[t], ref[t]
            assert np.isin(a["seq"], r["seq"]).all() and (np.diff(a["seq"]) > 0).all(), (how, t)
        if how == "complete":
            assert got.truncation is None
            assert any("data section CRC mismatch" in n for n in got.damage_notes), got.damage_notes
        else:
            assert got.truncation is not None


def test_a_bag_cut_short_is_read_up_to_its_last_complete_chunk(ring: Dict[str, object]) -> None:
    """Cut inside and between chunks, in the data section's tail, the summary and the footer:
    each reads the messages of its complete chunks — the samples `scancorr correct` reads —
    as a prefix of each channel, and says it was cut short and where."""
    d: pathlib.Path = ring["dir"]  # type: ignore[assignment]
    bag: bytes = ring["bytes"]  # type: ignore[assignment]
    ref, _ = read(ring["bag"])  # type: ignore[arg-type]
    cs = chunks(bag)
    s = summary_start(bag)
    header_end = len(MAGIC) + 9 + u64(bag, len(MAGIC) + 1)
    cuts = [header_end, cs[0][0] + 30]
    for start, end in cs:
        cuts += [end - 1, end, end + 1, (start + end) // 2]
    cuts += [s - 1, s, s + 5, len(bag) - 40, len(bag) - 1]
    p = d / "cut.mcap"
    for cut in cuts:
        p.write_bytes(bag[:cut])
        got, w = read(p)
        t = got.truncation
        assert t is not None and t.file_len == cut and t.readable_len <= cut, (cut, t)
        assert w == got.problems() and "cut short" in w[0], (cut, w)
        complete = sum(1 for _, e in cs if e <= cut)
        for topic in got.topics():
            a = got[topic]
            assert same_arrays_prefix(a, ref[topic]), (cut, topic)
        if complete == len(cs):
            assert samples(got) == samples(ref), cut
        if complete == 0:
            assert samples(got) == 0, cut
        else:
            assert 0 < samples(got) <= samples(ref), cut
        if cut >= s:
            assert "the data section is complete" in t.reason, (cut, t)
        rc, err, summary = correct(d, p, "c.json", "cut-out.mcap")
        if samples(got) == 0:
            assert rc != 0 and ("no scancorr streams" in err or "holds machine(s) none" in err), (cut, err)
            continue
        assert rc == 0, (cut, err)
        # The same samples, and the same readable length in its warning.
        assert summary["samples"] == samples(got), (cut, summary)
        assert f"the bag is cut short ({t.reason}); reading the {t.readable_len} of {cut} bytes" in err, (cut, err, t)

    # Cut inside the magic or the header: a clear error.
    for cut, expected in ((0, "not an MCAP file: the file is empty"), (5, "not an MCAP file: the file is only 5 bytes"),
                          (8, "ends inside the MCAP header"), (header_end - 1, "ends inside the MCAP header")):
        p.write_bytes(bag[:cut])
        with pytest.raises(BagError, match=expected):
            scancorr.read_bag(p)


def same_arrays_prefix(a: np.ndarray, r: np.ndarray) -> bool:
    if a.dtype != r.dtype or len(a) > len(r):
        return False
    r = r[: len(a)]
    return all(
        np.array_equal(a[n], r[n]) if a.dtype[n] == object else np.array_equal(a[n], r[n], equal_nan=True)
        for n in a.dtype.names
    )


def test_decompression_is_capped(small: Dict[str, object], tmp_path: pathlib.Path) -> None:
    """A chunk claiming 100 GB (checksums valid) is refused before anything is decompressed; a
    56 kB decompression bomb (2 GiB of zeros) is never decompressed beyond what its chunk
    claims: both refused, by both readers, in a few tens of MB."""
    d: pathlib.Path = small["dir"]  # type: ignore[assignment]
    bag: bytes = small["bytes"]  # type: ignore[assignment]
    (start, _), = chunks(bag)
    huge = 100 << 30
    b = bytearray(bag)
    b[start + 25 : start + 33] = struct.pack("<Q", huge)  # the chunk header's uncompressed size
    fix_crcs(b)
    claims = f"chunk claims {huge} uncompressed bytes, more than the {RECORD_LIMIT} the reader accepts"
    p = tmp_path / "claims.mcap"
    p.write_bytes(b)

    header_end = len(MAGIC) + 9 + u64(bag, len(MAGIC) + 1)
    bomb = zstd_bomb(2 << 30)
    bags = {"claims": (p, claims)}
    for name, claimed, why in (
        ("bomb", 370_000, "chunk records exceed its uncompressed size"),
        ("bomb-claimed", 2 << 30, f"chunk claims {2 << 30} uncompressed bytes, more than the {RECORD_LIMIT}"),
    ):
        q = tmp_path / f"{name}.mcap"
        q.write_bytes(bag[:header_end] + chunk_record(bomb, claimed))
        assert q.stat().st_size < 70_000
        bags[name] = (q, why)

    for name, (q, why) in bags.items():
        rc, err, _ = correct(d, q, "c.json", str(tmp_path / "o.mcap"))
        at = f"{q}: damaged bag: chunk at byte offset {start}: "
        assert rc != 0 and at in err, (name, err)
        # In a fresh interpreter, to measure its peak memory (VmHWM: getrusage's maximum
        # would be this process's, inherited across fork and exec).
        code = (
            "import re, sys, scancorr\n"
            "try:\n    scancorr.read_bag(sys.argv[1]); print('read')\n"
            "except scancorr.BagError as e:\n    print(e)\n"
            "print(re.search(r'VmHWM:\\s*(\\d+) kB', open('/proc/self/status').read()).group(1))\n"
        )
        r = subprocess.run([sys.executable, "-c", code, str(q)], capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        msg, peak_kb = r.stdout.splitlines()
        assert msg.startswith(at) and why in msg, (name, msg)
        assert int(peak_kb) < 150_000, f"{name}: {int(peak_kb) / 1024:.0f} MB"


def rewrite(src: pathlib.Path, dst: pathlib.Path, compression: str, bad_topic: str, bad: bytes) -> str:
    """`src` rewritten with the `mcap` package's writer (chunks of `compression`, every CRC),
    the first message on `bad_topic` replaced by `bad`."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    with open(src, "rb") as f, open(dst, "wb") as g:
        r = make_reader(f)
        s = r.get_summary()
        w = Writer(g, compression=getattr(CompressionType, compression), enable_data_crcs=True)
        w.start("scancorr", "test")
        sid = {i: w.register_schema(x.name, x.encoding, x.data) for i, x in s.schemas.items()}
        cid = {
            i: w.register_channel(c.topic, c.message_encoding, sid[c.schema_id], dict(c.metadata))
            for i, c in s.channels.items()
        }
        done = False
        for _, ch, m in r.iter_messages(log_time_order=False):
            data = m.data
            if ch.topic == bad_topic and not done:
                data, done = bad, True
            w.add_message(cid[ch.id], m.log_time, data, m.publish_time, m.sequence)
        for md in r.iter_metadata():
            w.add_metadata(md.name, dict(md.metadata))
        w.finish()
    assert done
    return bad_topic


@pytest.mark.parametrize("compression", ["ZSTD", "LZ4", "NONE"])
def test_an_undecodable_message_is_counted_not_fatal(small: Dict[str, object], tmp_path: pathlib.Path, compression: str) -> None:
    """One message whose payload is no protobuf (checksums valid: recorded so): counted in
    `undecodable` and warned about, every other message read — as `scancorr correct` counts
    it in `bad_messages`."""
    d: pathlib.Path = small["dir"]  # type: ignore[assignment]
    ref, _ = read(small["bag"])  # type: ignore[arg-type]
    p = tmp_path / "bad.mcap"
    topic = rewrite(small["bag"], p, compression, "cmm/m1/raw/scale", b"\x0a\x7f\x00")  # type: ignore[arg-type]
    got, w = read(p)
    assert got.undecodable == {topic: 1}
    assert w == [f"{p}: 1 message(s) on {topic} could not be decoded: skipped"]
    assert got.truncation is None and not got.damaged_chunks and not got.damage_notes
    for t in ref.topics():
        if t == topic:
            assert got.channels[t].messages == ref.channels[t].messages - 1
            assert same_arrays_prefix(got[t][::-1], ref[t][::-1])  # all but the first batch
        else:
            assert same_arrays_prefix(got[t], ref[t]) and len(got[t]) == len(ref[t]), t
    rc, err, s = correct(d, p, "c.json", str(tmp_path / "o.mcap"))
    assert rc == 0, err
    assert s["bad_messages"] == 1 and s["samples"] == samples(got), s
