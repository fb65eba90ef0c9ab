"""Reading scancorr bags (MCAP, protobuf) into numpy arrays (the message classes come from the
schema each channel carries).

    bag = scancorr.read_bag("corrected.mcap")
    pts = bag.points()                    # every corrected point, arrays.POINT_DTYPE
    scale = bag["cmm/m1/raw/scale"]        # one channel's samples: seq, t_ns, x, y, z
    frames = bag.frames()                  # the same as pandas DataFrames (needs pandas)

The bag is read as the Rust reader reads it (`scancorr._mcap`): every checksum verified, every
length checked before it is allocated, decompression capped; damage raises `BagError` naming
the file, the record and its byte offset. Nothing is lost in silence: a bag cut short is read
up to its last complete chunk (`Bag.truncation`), messages that do not decode are counted
(`Bag.undecodable`), with `skip_damaged=True` damaged chunks are skipped and listed
(`Bag.damaged_chunks`); each of these also issues a `BagWarning`, and `Bag.problems()` lists
them.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field
from operator import attrgetter
from os import PathLike
from typing import Any, Dict, List, Optional, Tuple, Union

import numpy as np

from . import _mcap, arrays
from ._mcap import RECORD_LIMIT, BagError, DamagedChunk, Truncation

__all__ = [
    "RECORD_LIMIT",
    "Bag",
    "BagError",
    "BagWarning",
    "Channel",
    "DamagedChunk",
    "Truncation",
    "flat_columns",
    "read_bag",
]


class BagWarning(UserWarning):
    """Issued by `read_bag` when a bag was read with something missing: cut short, damaged
    chunks skipped, messages that do not decode or are no valid batch."""


# protobuf FieldDescriptor types → numpy.
_NP = {
    1: "<f8",  # double
    2: "<f4",  # float
    3: "<i8",  # int64
    4: "<u8",  # uint64
    5: "<i4",  # int32
    6: "<u8",  # fixed64
    7: "<u4",  # fixed32
    8: "?",  # bool
    13: "<u4",  # uint32
    14: "<i4",  # enum
    15: "<i4",  # sfixed32
    16: "<i8",  # sfixed64
    17: "<i4",  # sint32
    18: "<i8",  # sint64
}
_STRING = 9


@dataclass
class Channel:
    """One channel of a bag.

    topic:    its key expression (`cmm/m1/raw/scale`, `cmm/m1/corrected/points`, …)
    schema:   the protobuf message (`scancorr.v1.ScaleBatch`, …)
    messages: messages read
    data:     every sample (or point, or alarm) of it, in log-time order
    """

    topic: str
    schema: str
    messages: int
    data: np.ndarray


@dataclass
class Bag:
    """What `read_bag` read.

    skipped:        messages per topic of channels that are not scancorr protobuf channels
                    (other schemas or encodings, or a channel the bag never declares)
    malformed:      messages per topic that decode but are no valid batch (packed columns of
                    unequal lengths, or both forms in one batch): counted, not read
    undecodable:    messages per topic whose payload does not decode as the channel's
                    message (or whose schema cannot be used): counted, not read
    truncation:     set when the file was cut short: everything up to its last complete chunk
                    was read (`Truncation.readable_len` of `file_len` bytes)
    damaged_chunks: chunks skipped because they failed verification, with the messages lost
                    (only with `skip_damaged=True`; otherwise damage raises `BagError`)
    damage_notes:   damage that cost no message (a damaged summary: the data section was
                    scanned and verified instead) or, skipping, a data-section CRC mismatch
    metadata:       the last metadata record of each name (as the Rust reader's
                    `metadata_named`): name → its entries
    metadata_records: every metadata record, a list per name in file order: a bag of five
                    features has five `scancorr.artifact` records (`Bag.artifacts()`)
    """

    path: str
    channels: Dict[str, Channel] = field(default_factory=dict)
    metadata: Dict[str, Dict[str, str]] = field(default_factory=dict)
    skipped: Dict[str, int] = field(default_factory=dict)
    malformed: Dict[str, int] = field(default_factory=dict)
    undecodable: Dict[str, int] = field(default_factory=dict)
    truncation: Optional[Truncation] = None
    damaged_chunks: List[DamagedChunk] = field(default_factory=list)
    damage_notes: List[str] = field(default_factory=list)
    metadata_records: Dict[str, List[Dict[str, str]]] = field(default_factory=dict)

    def problems(self) -> List[str]:
        """What was not read, one line each (empty when the whole bag was read): the
        warnings `read_bag` issues."""
        out = []
        t = self.truncation
        if t is not None:
            out.append(
                f"{self.path}: the bag is cut short ({t.reason}); read the {t.readable_len} of "
                f"{t.file_len} bytes that form complete chunks"
            )
        out += [f"{self.path}: {d}" for d in self.damaged_chunks]
        out += [f"{self.path}: {n}" for n in self.damage_notes]
        for what, counts in (("could not be decoded", self.undecodable), ("are no valid batch", self.malformed)):
            for topic, n in sorted(counts.items()):
                out.append(f"{self.path}: {n} message(s) on {topic} {what}: skipped")
        return out

    def artifacts(self) -> List[Dict[str, str]]:
        """Every `scancorr.artifact` record (one per measured artifact or feature), in file
        order."""
        return list(self.metadata_records.get("scancorr.artifact", []))

    def __getitem__(self, topic: str) -> np.ndarray:
        return self.channels[topic].data

    def __contains__(self, topic: object) -> bool:
        return topic in self.channels

    def topics(self) -> List[str]:
        return sorted(self.channels)

    def points(self) -> np.ndarray:
        """Every corrected point of every machine in the bag (`arrays.POINT_DTYPE`)."""
        return arrays.concat(
            [c.data for c in self.channels.values() if c.schema == "scancorr.v1.CorrectedPointBatch"],
            arrays.POINT_DTYPE,
        )

    def alarms(self) -> np.ndarray:
        """Every estimator alarm (`arrays.ALARM_DTYPE`)."""
        return arrays.concat(
            [c.data for c in self.channels.values() if c.schema == "scancorr.v1.EstimatorAlarm"],
            arrays.ALARM_DTYPE,
        )

    def frames(self) -> Dict[str, Any]:
        """Each channel as a pandas DataFrame (vector fields as `surface_x`, … columns).
        Needs pandas (`pip install scancorr[pandas]`)."""
        try:
            import pandas as pd
        except ImportError as e:
            raise ImportError("Bag.frames() needs pandas: pip install 'scancorr[pandas]'") from e
        return {t: pd.DataFrame(flat_columns(c.data)) for t, c in self.channels.items()}


def flat_columns(a: np.ndarray) -> Dict[str, np.ndarray]:
    """The fields of a structured array as 1-D columns (a (3,) field as `_x`, `_y`, `_z`)."""
    out: Dict[str, np.ndarray] = {}
    for name in a.dtype.names or ():
        col = a[name]
        if col.ndim == 2:
            for k in range(col.shape[1]):
                out[f"{name}_{'xyz'[k] if col.shape[1] == 3 else k}"] = col[:, k]
        else:
            out[name] = col
    return out


def _sample_dtype(desc: Any) -> tuple:
    names, formats = [], []
    for f in desc.fields:
        if f.name == "machine_id" or getattr(f, "is_repeated", False):
            continue
        # An `optional` scalar (scancorr.v1.5's probing force, `force_n`) is not read here:
        # absent in most samples, it would read as 0 (not yet a column of these arrays).
        oneof = getattr(f, "containing_oneof", None)
        if oneof is not None and oneof.name.startswith("_"):
            continue
        if f.type == _STRING:
            names.append(f.name)
            formats.append(object)
        elif f.type in _NP:
            names.append(f.name)
            formats.append(_NP[f.type])
    return names, np.dtype({"names": names, "formats": formats})


def _samples(batch: Any, cache: Dict[str, tuple]) -> np.ndarray:
    """The `samples` of a raw batch (CommandBatch, ScaleBatch, …) as a structured array of
    their scalar fields (without the machine id), from either form of the batch: one message
    per sample, or packed columns (scancorr.v1.3). Raises ValueError for a batch with both
    forms or with columns of unequal lengths."""
    desc = batch.DESCRIPTOR.fields_by_name["samples"].message_type
    got = cache.get(desc.full_name)
    if got is None:
        names, dt = _sample_dtype(desc)
        got = cache[desc.full_name] = (attrgetter(*names), dt, len(names))
    get, dt, n = got
    if "columns" in batch.DESCRIPTOR.fields_by_name and batch.HasField("columns"):
        if len(batch.samples):
            raise ValueError(f"{batch.DESCRIPTOR.name} with both `samples` and `columns`")
        return _columns(batch.columns, dt)
    rows = list(map(get, batch.samples))
    if n == 1:
        rows = [(r,) for r in rows]
    return np.array(rows, dtype=dt)


def _columns(columns: Any, dt: np.dtype) -> np.ndarray:
    """A packed batch's columns (scancorr.v1.3: the sample's fields, one value per sample
    each) as the structured array `_samples` makes of per-sample messages."""
    n = len(columns.seq)
    a = np.empty(n, dtype=dt)
    for name in dt.names:
        col = getattr(columns, name)
        if len(col) != n:
            raise ValueError(
                f"{columns.DESCRIPTOR.name}: column `{name}` holds {len(col)} values for {n} samples"
            )
        a[name] = list(col) if dt[name] == object else np.asarray(col, dtype=dt[name])
    return a


# Message classes built from schema data (a FileDescriptorSet), by (data, name): bags of one
# release share their schemas, and building a descriptor pool costs milliseconds.
_CLASSES: Dict[Tuple[bytes, str], Any] = {}


def _message_class(data: bytes, name: str) -> Any:
    """The message class `name` of the FileDescriptorSet `data`; raises when the schema cannot
    be used (does not parse, lacks the message)."""
    key = (data, name)
    cls = _CLASSES.get(key)
    if cls is None:
        from google.protobuf.descriptor_pb2 import FileDescriptorSet
        from google.protobuf.descriptor_pool import DescriptorPool
        from google.protobuf.message_factory import GetMessageClass

        fds = FileDescriptorSet.FromString(data)
        files = {fd.name: fd for fd in fds.file}
        if len(files) != len(fds.file):
            raise ValueError("the FileDescriptorSet holds a file twice")
        pool = DescriptorPool()
        added: set = set()

        def add(fd: Any, depth: int = 0) -> None:
            if fd.name in added or depth > 100:
                return
            added.add(fd.name)
            for dep in fd.dependency:
                if dep in files:
                    add(files[dep], depth + 1)
            pool.Add(fd)

        for fd in fds.file:
            add(fd)
        cls = GetMessageClass(pool.FindMessageTypeByName(name))
        if len(_CLASSES) >= 64:
            _CLASSES.clear()
        _CLASSES[key] = cls
    return cls


def read_bag(path: Union[str, "PathLike[str]"], *, skip_damaged: bool = False) -> Bag:
    """Every channel of a scancorr bag as numpy arrays: raw samples per stream, corrected
    points (`arrays.POINT_DTYPE`), alarms (`arrays.ALARM_DTYPE`); the bag's metadata records
    as dicts: every one in `metadata_records` (a list per name), the last of each name in
    `metadata`. Samples are in log-time order (file order on equal times).

    Every checksum is verified and every length checked, as the Rust reader does: a damaged
    bag raises `BagError` (`<file>: damaged bag: chunk at byte offset N: CRC mismatch …`), or,
    with `skip_damaged=True`, its damaged chunks are skipped and listed in `damaged_chunks`. A
    bag cut short is read up to its last complete chunk (`truncation`). Channels of other
    schemas are counted in `skipped`, messages that do not decode in `undecodable`, batches
    that are not valid (packed columns of unequal lengths) in `malformed`; none of them is
    read. Whatever was not read is also issued as a `BagWarning` (see `Bag.problems()`).
    Raises OSError when the file cannot be read."""
    path_s = os.fspath(path)
    bag = Bag(path=str(path_s))
    # topic -> [(log time, order, array)]
    parts: Dict[str, List[Tuple[int, int, np.ndarray]]] = {}
    schemas: Dict[str, str] = {}
    cache: Dict[str, tuple] = {}
    # channel id -> (topic, schema name, message class; None: not a scancorr protobuf
    # channel, False: its schema cannot be used)
    routes: Dict[int, Tuple[str, str, Any]] = {}
    order = 0

    def count(d: Dict[str, int], topic: str) -> None:
        d[topic] = d.get(topic, 0) + 1

    def route(channel_id: int, ch: Any, schema: Any) -> Tuple[str, str, Any]:
        r = routes.get(channel_id)
        if r is not None:
            return r
        if ch is None:
            # Not kept: a later channel record may declare it.
            return (f"<undeclared channel {channel_id}>", "", None)
        name = schema.name if schema is not None else ""
        if (
            schema is None
            or not name.startswith("scancorr.v1.")
            or schema.encoding != "protobuf"
            or ch.message_encoding != "protobuf"
        ):
            r = (ch.topic, "", None)
        else:
            try:
                r = (ch.topic, name, _message_class(schema.data, name))
            except Exception:  # protobuf raises several types for a schema it cannot use
                r = (ch.topic, name, False)
        routes[channel_id] = r
        return r

    def on_message(channel_id: int, ch: Any, schema: Any, log_time: int, payload: memoryview) -> None:
        nonlocal order
        topic, name, cls = route(channel_id, ch, schema)
        if cls is None:
            count(bag.skipped, topic)
            return
        if cls is False:
            count(bag.undecodable, topic)
            return
        try:
            msg = cls.FromString(bytes(payload))
        except Exception:  # protobuf raises several types
            count(bag.undecodable, topic)
            return
        if name == "scancorr.v1.CorrectedPointBatch":
            try:
                a = arrays.points_from_message(msg)
            except arrays.DecodeError:
                count(bag.malformed, topic)
                return
        elif name == "scancorr.v1.EstimatorAlarm":
            a = arrays.alarm_from_message(msg)
        elif "samples" in msg.DESCRIPTOR.fields_by_name:
            try:
                a = _samples(msg, cache)
            except ValueError:
                count(bag.malformed, topic)
                return
        else:
            count(bag.skipped, topic)
            return
        parts.setdefault(topic, []).append((log_time, order, a))
        schemas[topic] = name
        order += 1

    cat = _mcap.read(path_s, on_message, skip_damaged=skip_damaged)
    for topic, msgs in parts.items():
        msgs.sort(key=lambda m: (m[0], m[1]))
        bag.channels[topic] = Channel(
            topic=topic,
            schema=schemas[topic],
            messages=len(msgs),
            data=np.concatenate([m[2] for m in msgs]),
        )
    for name, entries in cat.metadata:
        bag.metadata[name] = dict(entries)
        bag.metadata_records.setdefault(name, []).append(dict(entries))
    bag.truncation = cat.truncation
    bag.damaged_chunks = list(cat.damaged)
    bag.damage_notes = list(cat.notes)
    for line in bag.problems():
        warnings.warn(line, BagWarning, stacklevel=2)
    return bag
