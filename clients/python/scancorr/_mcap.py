"""A verifying MCAP reader: the Python twin of the Rust bag reader (`clients/bag/src/reader/`).

Every checksum the file carries is verified: the summary CRC (a damaged summary is not used:
the data section is scanned instead), the data-section CRC (one pass over the file), each
chunk's CRC of its uncompressed records. A CRC of 0 means "not computed" and is the only way a
part passes unverified. A file cut short (no summary or footer) is read up to its last complete
record, and says so (`Truncation`). Every length is checked against what holds it before
anything is allocated, a chunk may claim at most `RECORD_LIMIT` uncompressed bytes and is
never decompressed beyond what it claims. Damage is a `BagError`, or, with `skip_damaged`, a
skipped chunk listed as a `DamagedChunk` with the messages lost with it.

The error texts are the Rust reader's: `<file>: damaged bag: chunk at byte offset 62: CRC
mismatch (expected 0x…, computed 0x…)`, `<file>: not an MCAP file: …`, `<file>: corrupt MCAP
file: …`.

`read(path, on_message, skip_damaged)` calls `on_message(channel_id, channel, schema, log_time,
data)` for every message in file order, after its chunk was verified, and returns what it found
(`Catalog`).
"""

from __future__ import annotations

import io
import zlib
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Tuple

from .errors import ScancorrError

MAGIC = b"\x89MCAP0\r\n"

# Opcodes.
HEADER = 0x01
FOOTER = 0x02
SCHEMA = 0x03
CHANNEL = 0x04
MESSAGE = 0x05
CHUNK = 0x06
MESSAGE_INDEX = 0x07
CHUNK_INDEX = 0x08
ATTACHMENT = 0x09
ATTACHMENT_INDEX = 0x0A
STATISTICS = 0x0B
METADATA = 0x0C
METADATA_INDEX = 0x0D
SUMMARY_OFFSET = 0x0E
DATA_END = 0x0F

#: Largest record (or decompressed chunk) the reader accepts; guards allocations against
#: corrupt length fields. scancorr bags use 1 MiB chunks. The Rust reader's limit.
RECORD_LIMIT = 256 << 20
#: Most decompressed chunk bytes reading in log-time order may hold at once (chunks whose time
#: ranges overlap): the Rust reader refuses indexes that exceed it; so does this one.
OVERLAP_LIMIT = 1 << 30
#: opcode + length + footer body (summary start, summary offset start, crc) + end magic.
FOOTER_AND_MAGIC = 1 + 8 + 20 + 8
#: The footer bytes the summary CRC covers: opcode, length, summary start, summary offset start.
FOOTER_CRC_PREFIX = 1 + 8 + 8 + 8
#: A data-end record: opcode, length, data section CRC.
DATA_END_LEN = 1 + 8 + 4
#: Loose (unchunked) messages are grouped in runs of at most this many bytes.
LOOSE_RUN_LIMIT = 4 << 20
#: Bytes read at a time when computing a CRC over a file range.
HASH_BLOCK = 1 << 20


class BagError(ScancorrError, ValueError):
    """A bag that cannot be read as it is. `kind` is `not_mcap` (empty, too short, wrong magic),
    `corrupt` (starts like MCAP, but its header or indexes cannot be used) or `damaged` (a
    checksum does not match, or a record of a finished file is malformed: `what` is `chunk`,
    `record` or `data section`, `offset` the record's byte offset). The message names the file
    and says what is wrong, as the Rust reader does."""

    def __init__(self, path: str, kind: str, reason: str, what: str = "", offset: Optional[int] = None):
        self.path = path
        self.kind = kind
        self.reason = reason
        self.what = what
        self.offset = offset
        if kind == "damaged":
            text = f"{path}: damaged bag: {what} at byte offset {offset}: {reason}"
        elif kind == "not_mcap":
            text = f"{path}: not an MCAP file: {reason}"
        else:
            text = f"{path}: corrupt MCAP file: {reason}"
        super().__init__(text)


@dataclass(frozen=True)
class Truncation:
    """The file was cut short (the recorder was killed, a copy stopped): what is readable is
    everything up to the last complete chunk.

    file_len:     the file's size
    readable_len: end of the last complete record that was read; messages after it are lost
    reason:       what the scan found at `readable_len`
    """

    file_len: int
    readable_len: int
    reason: str


@dataclass(frozen=True)
class DamagedChunk:
    """A chunk that failed verification and was skipped (`read_bag(…, skip_damaged=True)`).

    offset:        file offset of the chunk record
    length:        its length, bytes
    messages_lost: messages lost with it (all channels), when the file's message index tells
    reason:        what is wrong, e.g. `CRC mismatch (expected 0x1a2b3c4d, computed 0x5e6f7a8b)`
    """

    offset: int
    length: int
    messages_lost: Optional[int]
    reason: str

    def __str__(self) -> str:
        lost = (
            f"{self.messages_lost} messages lost"
            if self.messages_lost is not None
            else "an unknown number of messages lost"
        )
        return f"damaged chunk at byte offset {self.offset} ({self.length} bytes) skipped: {self.reason}; {lost}"


class _Bad(Exception):
    """Something in a record is wrong; the text says what."""


class _BadText(_Bad):
    """Every field fits, but a string is not UTF-8 (where the Rust reader's `mcap` parser
    fails, after its layout check)."""


def _crc_mismatch(expected: int, computed: int) -> str:
    return f"CRC mismatch (expected {expected:#010x}, computed {computed:#010x})"


def _u16(b, at: int) -> int:
    return int.from_bytes(b[at : at + 2], "little")


def _u32(b, at: int) -> int:
    return int.from_bytes(b[at : at + 4], "little")


def _u64(b, at: int) -> int:
    return int.from_bytes(b[at : at + 8], "little")


class _Walk:
    """A cursor over a record body (or a map inside it) that says which field does not fit,
    in the Rust reader's words (`layout.rs`). Strings are decoded (`texts`) only once every
    field was found to fit, as there."""

    def __init__(self, record: str, data, scope: str = "record body", pending: Optional[list] = None):
        self.record = record
        self.scope = scope
        self.data = memoryview(data)
        self.at = 0
        self.pending: list = [] if pending is None else pending

    def remaining(self) -> int:
        return len(self.data) - self.at

    def _short(self, what: str) -> _Bad:
        return _Bad(
            f"{self.record} record: {what}, but only {self.remaining()} bytes of the "
            f"{len(self.data)}-byte {self.scope} remain"
        )

    def uint(self, name: str, n: int) -> int:
        if n > self.remaining():
            raise self._short(f"field `{name}` needs {n} bytes")
        v = int.from_bytes(self.data[self.at : self.at + n], "little")
        self.at += n
        return v

    def prefixed(self, name: str, n: int, label: Optional[str] = None) -> memoryview:
        """A length prefix of `n` bytes and the bytes it counts; `label` names the field in
        messages (default `` `name` ``)."""
        label = label or f"`{name}`"
        if n > self.remaining():
            raise self._short(f"the {n}-byte length prefix of field {label} does not fit")
        size = int.from_bytes(self.data[self.at : self.at + n], "little")
        self.at += n
        if size > self.remaining():
            raise self._short(f"field {label} has length prefix {size}")
        v = self.data[self.at : self.at + size]
        self.at += size
        return v

    def string(self, name: str, label: Optional[str] = None) -> int:
        """A string field; its slot in `texts()`."""
        label = label or f"`{name}`"
        self.pending.append((label, self.prefixed(name, 4, label)))
        return len(self.pending) - 1

    def str_map(self, name: str) -> List[Tuple[int, int]]:
        """A (string, string) map: the slots of its keys and values in `texts()`."""
        m = _Walk(self.record, self.prefixed(name, 4), "map", self.pending)
        out = []
        i = 0
        while m.remaining():
            k = m.string(name, f"`{name}` entry {i} key")
            v = m.string(name, f"`{name}` entry {i} value")
            out.append((k, v))
            i += 1
        return out

    def texts(self) -> List[str]:
        """The string fields, decoded (after every field was found to fit)."""
        out = []
        for label, b in self.pending:
            try:
                out.append(str(b, "utf-8"))
            except UnicodeDecodeError as e:
                raise _BadText(f"{self.record} record: field {label} is not UTF-8: {e}") from None
        return out

    def entries(self, name: str, size: int) -> memoryview:
        b = self.prefixed(name, 4)
        if len(b) % size:
            raise _Bad(
                f"{self.record} record: field `{name}` holds {len(b)} bytes, not a whole number "
                f"of {size}-byte entries"
            )
        return b


# Record bodies, checked field by field (every field must fit inside the body). Trailing bytes
# (fields of a future MCAP version) are allowed, as in the Rust reader.


def _header(body) -> Tuple[str, str]:
    w = _Walk("header", body)
    w.string("profile")
    w.string("library")
    profile, library = w.texts()
    return profile, library


@dataclass
class _Schema:
    id: int
    name: str
    encoding: str
    data: bytes


def _schema(body) -> _Schema:
    w = _Walk("schema", body)
    sid = w.uint("id", 2)
    w.string("name")
    w.string("encoding")
    data = bytes(w.prefixed("data", 4))
    name, encoding = w.texts()
    return _Schema(sid, name, encoding, data)


@dataclass
class _Channel:
    id: int
    schema_id: int
    topic: str
    message_encoding: str


def _channel(body) -> _Channel:
    w = _Walk("channel", body)
    cid = w.uint("id", 2)
    schema_id = w.uint("schema_id", 2)
    w.string("topic")
    w.string("message_encoding")
    w.str_map("metadata")
    t = w.texts()
    return _Channel(cid, schema_id, t[0], t[1])


def _metadata(body) -> Tuple[str, Dict[str, str]]:
    w = _Walk("metadata", body)
    w.string("name")
    slots = w.str_map("metadata")
    t = w.texts()
    return t[0], {t[k]: t[v] for k, v in slots}


def _data_end(body) -> int:
    return _Walk("data end", body).uint("data_section_crc", 4)


def _message_header(body) -> Optional[Tuple[int, int]]:
    """(channel id, log time) of a message record body; None when it is too short."""
    if len(body) < 22:
        return None
    return _u16(body, 0), _u64(body, 6)


def _message_index_count(body) -> Tuple[int, int]:
    """(channel id, entries) of a message index record body."""
    w = _Walk("message index", body)
    cid = w.uint("channel_id", 2)
    return cid, len(w.entries("records", 16)) // 16


@dataclass
class _ChunkHeader:
    start_time: int
    end_time: int
    uncompressed_size: int
    uncompressed_crc: int
    compression: str
    records: memoryview


def _chunk_header(body) -> _ChunkHeader:
    w = _Walk("chunk", body)
    start = w.uint("message_start_time", 8)
    end = w.uint("message_end_time", 8)
    size = w.uint("uncompressed_size", 8)
    crc = w.uint("uncompressed_crc", 4)
    w.string("compression")
    records = w.prefixed("records", 8)
    (compression,) = w.texts()
    return _ChunkHeader(start, end, size, crc, compression, records)


@dataclass
class _ChunkIndex:
    start_time: int
    end_time: int
    offset: int
    length: int
    message_index_offsets: Dict[int, int]
    compression: str
    compressed_size: int
    uncompressed_size: int

    def compressed_data_offset(self) -> int:
        # opcode, length, start/end time, uncompressed size, crc, compression, records length.
        return self.offset + 1 + 8 + 8 + 8 + 8 + 4 + 4 + len(self.compression.encode()) + 8


def _chunk_index(body) -> _ChunkIndex:
    w = _Walk("chunk index", body)
    start = w.uint("message_start_time", 8)
    end = w.uint("message_end_time", 8)
    offset = w.uint("chunk_start_offset", 8)
    length = w.uint("chunk_length", 8)
    m = w.entries("message_index_offsets", 10)
    offsets = {_u16(m, i): _u64(m, i + 2) for i in range(0, len(m), 10)}
    w.uint("message_index_length", 8)
    w.string("compression")
    compressed = w.uint("compressed_size", 8)
    uncompressed = w.uint("uncompressed_size", 8)
    (compression,) = w.texts()
    return _ChunkIndex(start, end, offset, length, offsets, compression, compressed, uncompressed)


@dataclass
class _Statistics:
    message_count: int
    metadata_count: int
    chunk_count: int
    start_time: int
    end_time: int
    channel_message_counts: Dict[int, int]


def _statistics(body) -> _Statistics:
    w = _Walk("statistics", body)
    messages = w.uint("message_count", 8)
    w.uint("schema_count", 2)
    w.uint("channel_count", 4)
    w.uint("attachment_count", 4)
    metadata = w.uint("metadata_count", 4)
    chunks = w.uint("chunk_count", 4)
    start = w.uint("message_start_time", 8)
    end = w.uint("message_end_time", 8)
    m = w.entries("channel_message_counts", 10)
    counts = {_u16(m, i): _u64(m, i + 2) for i in range(0, len(m), 10)}
    return _Statistics(messages, metadata, chunks, start, end, counts)


def _metadata_index(body) -> Tuple[int, int, str]:
    w = _Walk("metadata index", body)
    offset = w.uint("offset", 8)
    length = w.uint("length", 8)
    w.string("name")
    (name,) = w.texts()
    return offset, length, name


@dataclass
class _Region:
    """What the message reader reads: a chunk (its index entry; from a scan, its messages are
    already read) or a run of loose message records."""

    offset: int
    t_min: int
    t_max: int
    size: int  # uncompressed bytes (at least 9, a filler record's worth)
    index: Optional[_ChunkIndex] = None


@dataclass
class Catalog:
    """What `read` found."""

    profile: str = ""
    library: str = ""
    schemas: Dict[int, _Schema] = field(default_factory=dict)
    channels: Dict[int, _Channel] = field(default_factory=dict)
    #: (name, entries) in file order.
    metadata: List[Tuple[str, Dict[str, str]]] = field(default_factory=list)
    truncation: Optional[Truncation] = None
    damaged: List[DamagedChunk] = field(default_factory=list)
    notes: List[str] = field(default_factory=list)
    # internal
    skip_damaged: bool = False
    scanned: bool = False
    regions: List[_Region] = field(default_factory=list)
    data_end: Optional[Tuple[int, int]] = None

    def add_schema(self, s: _Schema) -> None:
        if s.id != 0:
            self.schemas.setdefault(s.id, s)

    def add_channel(self, c: _Channel) -> None:
        self.channels.setdefault(c.id, c)


class _Source:
    """The file, read record by record."""

    def __init__(self, path: str, f, length: int):
        self.path = path
        self.f = f
        self.len = length
        self.rec = b""

    def read_at(self, offset: int, n: int) -> bytes:
        self.f.seek(offset)
        b = self.f.read(n)
        if len(b) != n:
            raise OSError(f"{self.path}: {n} bytes at offset {offset} are beyond the end of the file")
        return b

    def crc(self, start: int, end: int, crc: int = 0) -> int:
        at = start
        while at < end:
            n = min(end - at, HASH_BLOCK)
            crc = zlib.crc32(self.read_at(at, n), crc)
            at += n
        return crc

    def next_record(self, pos: int, limit: int):
        """The record at `pos` whose bytes must end by `limit`: ("record", op, end) with the
        whole record in `self.rec`, ("end", None, pos), ("cut", reason, pos) when it extends
        beyond the limit, ("long", reason, pos) when it claims more than the reader accepts."""
        if pos >= limit:
            return "end", None, pos
        avail = limit - pos
        if avail < 9:
            return "cut", f"{avail} stray bytes at offset {pos}, not a whole record", pos
        head = self.read_at(pos, 9)
        op = head[0]
        n = _u64(head, 1)
        if n > avail - 9:
            return "cut", f"record (opcode {op:#04x}) at offset {pos} needs {n} bytes, only {avail - 9} remain", pos
        if n > RECORD_LIMIT:
            return (
                "long",
                f"record (opcode {op:#04x}) at offset {pos} is {n} bytes long, more than the "
                f"{RECORD_LIMIT} the reader accepts",
                pos,
            )
        self.rec = head + self.read_at(pos + 9, n)
        return "record", op, pos + 9 + n

    def has_footer(self, data_end: int) -> bool:
        if self.len < data_end + FOOTER_AND_MAGIC:
            return False
        tail = self.read_at(self.len - FOOTER_AND_MAGIC, FOOTER_AND_MAGIC)
        return tail[0] == FOOTER and tail[29:] == MAGIC


def _decompress(compression: str, data: memoryview, size: int):
    """At most `size + 1` bytes of the chunk's records: never more than it claims (+1 to tell
    that there are more), in one buffer of that size."""
    if compression == "":
        return bytes(data[: size + 1])
    if compression == "zstd":
        import zstandard

        out = bytearray(size + 1)
        view = memoryview(out)
        reader = zstandard.ZstdDecompressor().stream_reader(io.BytesIO(data), read_across_frames=True)
        n = 0
        while n <= size:
            k = reader.readinto(view[n : n + (1 << 20)])
            if not k:
                break
            n += k
        del view
        if n <= size:
            del out[n:]
        return out
    if compression == "lz4":
        import lz4.frame

        return lz4.frame.LZ4FrameDecompressor().decompress(bytes(data), max_length=size + 1)
    raise _Bad(f"Unsupported compression format `{compression}`")


def _records(data: bytes):
    """(offset, opcode, body) of well-formed record data (as `_decode_chunk` returns)."""
    at = 0
    view = memoryview(data)
    while at < len(data):
        op = data[at]
        n = _u64(data, at + 1)
        yield at, op, view[at + 9 : at + 9 + n]
        at += 9 + n


def _decode_chunk(record: bytes) -> Tuple[_ChunkHeader, bytes]:
    """Decompresses one chunk record (opcode, length, body) and verifies the CRC of its
    uncompressed records (unless it is 0, "not computed"); checks that they are whole records
    filling exactly its uncompressed size. Raises `_Bad` saying what is damaged."""
    if len(record) < 9:
        raise _Bad("chunk record too short")
    h = _chunk_header(memoryview(record)[9:])
    size = h.uncompressed_size
    if size > RECORD_LIMIT:
        raise _Bad(f"chunk claims {size} uncompressed bytes, more than the {RECORD_LIMIT} the reader accepts")
    try:
        data = _decompress(h.compression, h.records, size)
    except _Bad:
        raise
    except Exception as e:  # zstandard.ZstdError, lz4's RuntimeError, …
        why = str(e).replace("zstd decompress error: ", "")
        raise _Bad(f"Error during decompression: `{why}`") from None
    if len(data) > size:
        raise _Bad("chunk records exceed its uncompressed size")
    if len(data) < size:
        raise _Bad(f"chunk records fill {len(data)} of its {size} uncompressed bytes")
    if h.uncompressed_crc != 0:
        computed = zlib.crc32(data)
        if computed != h.uncompressed_crc:
            raise _Bad(_crc_mismatch(h.uncompressed_crc, computed))
    at = 0
    while at < len(data):
        if len(data) - at < 9:
            raise _Bad(f"{len(data) - at} stray bytes at byte {at} of its uncompressed records, not a whole record")
        n = _u64(data, at + 1)
        if n > len(data) - at - 9:
            raise _Bad(
                f"record (opcode {data[at]:#04x}) at byte {at} of its uncompressed records needs "
                f"{n} bytes, only {len(data) - at - 9} remain"
            )
        at += 9 + n
    return h, data


def _parse_chunk(data: bytes) -> Tuple[List[_Schema], List[_Channel], List[Tuple[int, int, memoryview]]]:
    """The schemas, channels and messages (channel, log time, payload) of a chunk's verified
    records; `_Bad` when one does not parse."""
    schemas, channels, messages = [], [], []
    for at, op, body in _records(data):
        try:
            if op == SCHEMA:
                schemas.append(_schema(body))
            elif op == CHANNEL:
                channels.append(_channel(body))
            elif op == MESSAGE:
                h = _message_header(body)
                if h is None:
                    raise _Bad("message record too short")
                messages.append((h[0], h[1], body[22:]))
        except _Bad as e:
            raise _Bad(f"at byte {at} of its uncompressed records: {e}") from None
    return schemas, channels, messages


def _check_chunk(record: bytes, index: _ChunkIndex) -> bytes:
    """Checks the chunk record read where `index` points against its index entry and decodes
    it; returns its verified uncompressed records."""
    if len(record) < 9:
        raise _Bad("chunk record too short")
    op, n = record[0], _u64(record, 1)
    if op != CHUNK:
        raise _Bad(f"the chunk index points at a record with opcode {op:#04x}, not a chunk")
    if n + 9 != index.length:
        raise _Bad(f"chunk record length {n} differs from the {max(index.length - 9, 0)} bytes in its index entry")
    h, data = _decode_chunk(record)
    if (
        h.compression != index.compression
        or len(h.records) != index.compressed_size
        or h.uncompressed_size != index.uncompressed_size
    ):
        raise _Bad("chunk header differs from its index entry")
    for _, op, body in _records(data):
        if op == MESSAGE:
            mh = _message_header(body)
            if mh is None:
                raise _Bad("message record too short")
            t = mh[1]
            if t < index.start_time or t > index.end_time:
                raise _Bad(f"message log time {t} outside the chunk's time range {index.start_time}..={index.end_time}")
    return data


#: on_message(channel_id, channel, schema, log_time, payload): `channel` and `schema` as the
#: file declares them so far (None when it does not).
OnMessage = Callable[[int, Optional["_Channel"], Optional["_Schema"], int, memoryview], None]


class _Reader:
    def __init__(self, path: str, src: _Source, cat: Catalog, on_message: OnMessage):
        self.path = path
        self.src = src
        self.cat = cat
        self.on_message = on_message

    def damaged(self, what: str, offset: int, reason: str) -> BagError:
        return BagError(self.path, "damaged", reason, what, offset)

    def emit(self, channel_id: int, log_time: int, payload: memoryview) -> None:
        cat = self.cat
        ch = cat.channels.get(channel_id)
        schema = cat.schemas.get(ch.schema_id) if ch is not None and ch.schema_id != 0 else None
        self.on_message(channel_id, ch, schema, log_time, payload)

    def deliver(self, schemas, channels, messages) -> None:
        for s in schemas:
            self.cat.add_schema(s)
        for c in channels:
            self.cat.add_channel(c)
        for channel, t, payload in messages:
            self.emit(channel, t, payload)

    # ---- the summary ----

    def read_summary(self, header_end: int) -> Tuple[str, Optional[str]]:
        """Reads the summary section into the catalog: ("ok", None), or ("absent", why) when
        the file has no (complete) summary, ("unusable", why) when it is damaged."""
        src, cat = self.src, self.cat
        if src.len < header_end + FOOTER_AND_MAGIC:
            return "absent", "too short for a footer"
        footer_start = src.len - FOOTER_AND_MAGIC
        tail = src.read_at(footer_start, FOOTER_AND_MAGIC)
        if tail[29:] != MAGIC:
            return "absent", "no end magic"
        if tail[0] != FOOTER:
            return "absent", "no footer record"
        summary_start = _u64(tail, 9)
        summary_crc = _u32(tail, 25)
        if summary_start == 0:
            return "absent", "no summary section"
        try:
            self.read_summary_section(header_end, summary_start, footer_start, tail, summary_crc)
        except _Bad as e:
            return "unusable", str(e)
        return "ok", None

    def read_summary_section(self, header_end, summary_start, footer_start, footer, summary_crc) -> None:
        src, cat = self.src, self.cat
        if summary_start < header_end + DATA_END_LEN or summary_start > footer_start:
            raise _Bad(f"summary start {summary_start} out of range")
        if summary_crc != 0:
            crc = src.crc(summary_start, footer_start)
            computed = zlib.crc32(footer[:FOOTER_CRC_PREFIX], crc)
            if computed != summary_crc:
                raise _Bad(f"summary {_crc_mismatch(summary_crc, computed)}")
        # The data-end record sits right before the summary; it holds the data section CRC.
        data_end = summary_start - DATA_END_LEN
        rec = src.read_at(data_end, DATA_END_LEN)
        if rec[0] != DATA_END or rec[1:9] != (4).to_bytes(8, "little"):
            raise _Bad("no data-end record before the summary")
        cat.data_end = (data_end, _u32(rec, 9))
        stats: Optional[_Statistics] = None
        metadata_indexes: List[Tuple[int, int, str]] = []
        chunk_indexes: List[_ChunkIndex] = []
        pos = summary_start
        while True:
            kind, op, end = src.next_record(pos, footer_start)
            if kind == "end":
                break
            if kind != "record":
                raise _Bad(op)
            body = memoryview(src.rec)[9:]
            try:
                if op == SCHEMA:
                    cat.add_schema(_schema(body))
                elif op == CHANNEL:
                    cat.add_channel(_channel(body))
                elif op == STATISTICS:
                    stats = _statistics(body)
                elif op == CHUNK_INDEX:
                    chunk_indexes.append(_chunk_index(body))
                elif op == METADATA_INDEX:
                    metadata_indexes.append(_metadata_index(body))
            except _Bad as e:
                raise _Bad(f"record (opcode {op:#04x}) at offset {pos}: {e}") from None
            pos = end
        if stats is None:
            raise _Bad("no statistics record")
        if len(chunk_indexes) != stats.chunk_count:
            raise _Bad("chunk index count differs from statistics")
        if len(metadata_indexes) != stats.metadata_count:
            raise _Bad("metadata index count differs from statistics")
        if stats.message_count > 0 and stats.chunk_count == 0:
            raise _Bad("messages outside chunks")
        for cid, n in stats.channel_message_counts.items():
            if n > 0 and cid not in cat.channels:
                raise _Bad(f"summary lacks channel {cid}")
        for c in chunk_indexes:
            data = c.compressed_data_offset()
            fits = (
                c.offset >= header_end
                and c.offset + c.length <= data_end
                and data + c.compressed_size <= data_end
                and c.length <= RECORD_LIMIT + 9
                and c.uncompressed_size <= RECORD_LIMIT
                and c.compressed_size <= RECORD_LIMIT
                and c.start_time <= c.end_time
            )
            if not fits:
                raise _Bad(f"chunk index at {c.offset} out of range")
        for offset, length, _name in sorted(metadata_indexes):
            if offset < header_end or offset + length > data_end:
                raise _Bad("metadata index out of range")
            kind, op, _ = src.next_record(offset, offset + length)
            if kind != "record" or op != METADATA:
                raise _Bad("metadata index does not point at a metadata record")
            try:
                cat.metadata.append(_metadata(memoryview(src.rec)[9:]))
            except _Bad as e:
                raise _Bad(f"metadata record at offset {offset}: {e}") from None
        cat.regions = [
            _Region(c.offset, c.start_time, c.end_time, max(c.uncompressed_size, 9), c) for c in chunk_indexes
        ]

    def verify_data_section(self) -> None:
        """With a usable summary: checks the data section CRC (one pass over the file). On a
        mismatch finds the damaged chunks: the first is an error, or, when skipping, all are
        dropped and counted."""
        src, cat = self.src, self.cat
        if cat.data_end is None or cat.data_end[1] == 0:
            return
        data_end, expected = cat.data_end
        computed = src.crc(0, data_end)
        if computed == expected:
            return
        mismatch = _crc_mismatch(expected, computed)
        kept = []
        for r in cat.regions:
            index = r.index
            assert index is not None
            try:
                _check_chunk(src.read_at(index.offset, index.length), index)
                kept.append(r)
                continue
            except _Bad as e:
                reason = str(e)
            if not cat.skip_damaged:
                raise self.damaged("chunk", index.offset, reason)
            cat.damaged.append(DamagedChunk(index.offset, index.length, self.lost_messages(index), reason))
        cat.regions = kept
        self.data_section_mismatch(mismatch)

    def data_section_mismatch(self, mismatch: str) -> None:
        cat = self.cat
        if not cat.damaged:
            reason = f"{mismatch} although every chunk verifies: metadata or index records are damaged"
            if not cat.skip_damaged:
                raise self.damaged("data section", 0, reason)
            cat.notes.append(f"data section {reason}")
        else:
            cat.notes.append(
                f"data section {mismatch}: {len(cat.damaged)} damaged chunk(s) skipped; damage "
                "outside the chunks (metadata) cannot be ruled out"
            )

    def lost_messages(self, index: _ChunkIndex) -> Optional[int]:
        """Messages of the chunk `index`, from the message index records it points at; None
        when there are none or they are unreadable."""
        if not index.message_index_offsets:
            return None
        src = self.src
        total = 0
        for channel, offset in index.message_index_offsets.items():
            try:
                head = src.read_at(offset, 9)
            except OSError:
                return None
            n = _u64(head, 1)
            if head[0] != MESSAGE_INDEX or n > RECORD_LIMIT or offset + 9 + n > src.len:
                return None
            try:
                cid, entries = _message_index_count(src.read_at(offset + 9, n))
            except (_Bad, OSError):
                return None
            if cid != channel:
                return None
            total += entries
        return total

    def read_chunks(self) -> None:
        """The messages of the summary's chunks, each chunk verified as it is decoded."""
        src, cat = self.src, self.cat
        for r in sorted(cat.regions, key=lambda r: r.offset):
            index = r.index
            assert index is not None
            try:
                data = _check_chunk(src.read_at(index.offset, index.length), index)
                parsed = _parse_chunk(data)
            except _Bad as e:
                if not cat.skip_damaged:
                    raise self.damaged("chunk", index.offset, str(e)) from None
                cat.damaged.append(DamagedChunk(index.offset, index.length, self.lost_messages(index), str(e)))
                continue
            self.deliver(*parsed)

    # ---- the scan ----

    def scan(self, header_end: int, no_summary: str) -> None:
        """Scans the data section record by record, reading every complete chunk (CRC-verified)
        and computing the data section CRC; stops at the data end record or at the first
        incomplete record, which it reports as truncation. A damaged record, or an incomplete
        one in a file that has its footer, is an error — except that when skipping damaged
        chunks, a damaged chunk is counted and skipped and other damage ends the readable part
        like a truncation."""
        src, cat = self.src, self.cat
        cat.scanned = True
        crc = src.crc(0, header_end)
        data_crc: Optional[int] = None
        pos = header_end
        run: Optional[List[int]] = None  # loose run: start, end, t_min, t_max
        last_damaged: Optional[int] = None
        stop: Optional[str] = None

        def close_run() -> None:
            nonlocal run
            if run is not None:
                cat.regions.append(_Region(run[0], run[2], run[3], max(run[1] - run[0], 9)))
                run = None

        while True:
            kind, op, end = src.next_record(pos, src.len)
            if kind == "end":
                stop = "the file ends without a data-end record (the writer did not finish)"
                break
            if kind == "cut":
                # A finished file is not cut short: its record framing is damaged.
                if not cat.skip_damaged and src.has_footer(pos):
                    raise self.damaged("record", pos, op)
                stop = op
                break
            if kind == "long":
                if not cat.skip_damaged:
                    raise self.damaged("record", pos, op)
                stop = op
                break
            rec = src.rec
            body = memoryview(rec)[9:]
            if op != DATA_END:
                crc = zlib.crc32(rec, crc)
            if op != MESSAGE_INDEX:
                last_damaged = None
            if op in (CHUNK, DATA_END, FOOTER, HEADER):
                close_run()
            error: Optional[str] = None
            try:
                if op == CHUNK:
                    try:
                        _, data = _decode_chunk(rec)
                        schemas, channels, messages = _parse_chunk(data)
                    except _Bad as e:
                        if not cat.skip_damaged:
                            raise self.damaged("chunk", pos, str(e)) from None
                        cat.damaged.append(DamagedChunk(pos, end - pos, None, str(e)))
                        last_damaged = len(cat.damaged) - 1
                    else:
                        self.deliver(schemas, channels, messages)
                        if messages:
                            ts = [m[1] for m in messages]
                            cat.regions.append(_Region(pos, min(ts), max(ts), max(len(data), 9)))
                elif op == MESSAGE_INDEX:
                    if last_damaged is not None:
                        try:
                            _, n = _message_index_count(body)
                        except _Bad:
                            pass
                        else:
                            d = cat.damaged[last_damaged]
                            cat.damaged[last_damaged] = DamagedChunk(
                                d.offset, d.length, (d.messages_lost or 0) + n, d.reason
                            )
                elif op == MESSAGE:
                    h = _message_header(body)
                    if h is None:
                        raise _Bad("message record too short")
                    channel, t = h
                    self.emit(channel, t, body[22:])
                    if run is not None and end - run[0] <= LOOSE_RUN_LIMIT:
                        run[1] = end
                        run[2] = min(run[2], t)
                        run[3] = max(run[3], t)
                    else:
                        close_run()
                        run = [pos, end, t, t]
                elif op == SCHEMA:
                    cat.add_schema(_schema(body))
                elif op == CHANNEL:
                    cat.add_channel(_channel(body))
                elif op == METADATA:
                    cat.metadata.append(_metadata(body))
                elif op == DATA_END:
                    data_crc = _data_end(body)
                elif op == HEADER:
                    raise _Bad("a second header record")
            except _Bad as e:
                error = str(e)
            if error is not None:
                reason = f"damaged record (opcode {op:#04x}) at offset {pos}: {error}"
                if not cat.skip_damaged:
                    raise self.damaged("record", pos, reason)
                stop = reason
                break
            pos = end
            if op in (DATA_END, FOOTER):
                break
        close_run()
        if data_crc:
            computed = crc
            if computed != data_crc:
                self.data_section_mismatch(_crc_mismatch(data_crc, computed))
        if stop is not None:
            cat.truncation = Truncation(src.len, pos, stop)
        elif not src.has_footer(pos):
            cat.truncation = Truncation(
                src.len,
                pos,
                f"the summary or footer is missing or damaged ({no_summary}); the data section is complete",
            )


def _check_overlap(regions: List[_Region]) -> Optional[str]:
    """Why reading in log-time order would hold more than `OVERLAP_LIMIT` decompressed bytes
    at once (chunks overlapping in time), or None."""
    events = []
    for r in regions:
        if r.t_min > r.t_max:
            return f"chunk at offset {r.offset} has start time {r.t_min} after its end time {r.t_max}"
        events.append((r.t_min, 0, r.size))
        events.append((r.t_max, 1, r.size))
    events.sort()
    held = 0
    for t, kind, size in events:
        if kind == 0:
            held += size
            if held > OVERLAP_LIMIT:
                return (
                    f"chunks overlapping in time at log time {t} hold more than {OVERLAP_LIMIT} "
                    "bytes uncompressed; reading them in time order would need that much memory"
                )
        else:
            held -= size
    return None


def read(path: str, on_message: OnMessage, skip_damaged: bool = False) -> Catalog:
    """Reads the bag at `path`: checks the magic and header, then reads the summary (verifying
    the summary and data-section CRCs) or scans the file when it has none (cut short, written
    without one, or damaged). Calls `on_message(channel_id, log_time, payload)` for each message
    of each verified chunk (and each loose message), in file order, with its channel and schema
    records as declared so far; payloads are only valid during the call. Raises `BagError` on damage (unless `skip_damaged`), OSError when the file
    cannot be read."""
    cat = Catalog(skip_damaged=skip_damaged)
    with open(path, "rb") as f:
        f.seek(0, io.SEEK_END)
        length = f.tell()
        src = _Source(path, f, length)
        if length == 0:
            raise BagError(path, "not_mcap", "the file is empty")
        if length < len(MAGIC):
            raise BagError(path, "not_mcap", f"the file is only {length} bytes long")
        if src.read_at(0, len(MAGIC)) != MAGIC:
            raise BagError(path, "not_mcap", "wrong magic bytes at the start")
        header_start = len(MAGIC)
        if length > header_start:
            op = src.read_at(header_start, 1)[0]
            if op != HEADER:
                raise BagError(path, "corrupt", f"the first record has opcode {op:#04x}, not a header")
        kind, op, header_end = src.next_record(header_start, length)
        if kind == "long":
            raise BagError(path, "corrupt", op)
        if kind != "record":
            raise BagError(path, "corrupt", f"the file ends inside the MCAP header ({length} bytes)")
        try:
            cat.profile, cat.library = _header(memoryview(src.rec)[9:])
        except _BadText:
            raise BagError(path, "corrupt", "the header record does not parse") from None
        except _Bad as e:
            raise BagError(path, "damaged", str(e), "record", header_start) from None
        r = _Reader(path, src, cat, on_message)
        state, why = r.read_summary(header_end)
        if state == "ok":
            r.verify_data_section()
            problem = _check_overlap(cat.regions)
            if problem:
                raise BagError(path, "corrupt", problem)
            r.read_chunks()
        else:
            # Start over from the data section: nothing of the summary is used.
            cat = Catalog(skip_damaged=skip_damaged, profile=cat.profile, library=cat.library)
            if state == "unusable":
                cat.notes.append(f"the summary section is unusable ({why}); the data section was scanned instead")
            r.cat = cat
            r.scan(header_end, why or "")
            problem = _check_overlap(cat.regions)
            if problem:
                raise BagError(path, "corrupt", problem)
    return cat
