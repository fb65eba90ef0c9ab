"""Reading scancorr bags (MCAP, protobuf) into numpy arrays, with `mcap` and
`mcap-protobuf-support` (the message classes come from the schema each channel carries).

    bag = scancorr.read_bag("corrected.mcap")
    pts = bag.points()                    # every corrected point, arrays.POINT_DTYPE
    scale = bag["cmm/m1/raw/scale"]        # one channel's samples: seq, t_ns, x, y, z
    frames = bag.frames()                  # the same as pandas DataFrames (needs pandas)
"""

from __future__ import annotations

from dataclasses import dataclass, field
from operator import attrgetter
from os import PathLike
from typing import Any, Dict, List, Union

import numpy as np

from . import arrays

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
    """What `read_bag` read."""

    path: str
    channels: Dict[str, Channel] = field(default_factory=dict)
    metadata: Dict[str, Dict[str, str]] = field(default_factory=dict)
    skipped: Dict[str, int] = field(default_factory=dict)
    # Messages per topic that decode but are no valid batch (packed columns of unequal
    # lengths, or both forms in one batch): counted, not read.
    malformed: Dict[str, int] = field(default_factory=dict)

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


def read_bag(path: Union[str, "PathLike[str]"]) -> Bag:
    """Every channel of a scancorr bag as numpy arrays: raw samples per stream, corrected
    points (`arrays.POINT_DTYPE`), alarms (`arrays.ALARM_DTYPE`); the bag's metadata records
    as dicts. Channels of other schemas are counted in `skipped`, batches that are not valid
(packed columns of unequal lengths) in `malformed`; neither is read."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    bag = Bag(path=str(path))
    parts: Dict[str, List[np.ndarray]] = {}
    info: Dict[str, tuple] = {}
    cache: Dict[str, tuple] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, _message, msg in reader.iter_decoded_messages(log_time_order=True):
            name = schema.name if schema is not None else ""
            if not name.startswith("scancorr.v1.") or msg is None:
                bag.skipped[channel.topic] = bag.skipped.get(channel.topic, 0) + 1
                continue
            if name == "scancorr.v1.CorrectedPointBatch":
                try:
                    a = arrays.points_from_message(msg)
                except arrays.DecodeError:
                    bag.malformed[channel.topic] = bag.malformed.get(channel.topic, 0) + 1
                    continue
            elif name == "scancorr.v1.EstimatorAlarm":
                a = arrays.alarm_from_message(msg)
            elif "samples" in msg.DESCRIPTOR.fields_by_name:
                try:
                    a = _samples(msg, cache)
                except ValueError:
                    bag.malformed[channel.topic] = bag.malformed.get(channel.topic, 0) + 1
                    continue
            else:
                bag.skipped[channel.topic] = bag.skipped.get(channel.topic, 0) + 1
                continue
            parts.setdefault(channel.topic, []).append(a)
            n = info.get(channel.topic, (name, 0))[1]
            info[channel.topic] = (name, n + 1)
        f.seek(0)
        for m in make_reader(f).iter_metadata():
            bag.metadata[m.name] = dict(m.metadata)
    for topic, arrs in parts.items():
        name, n = info[topic]
        bag.channels[topic] = Channel(topic=topic, schema=name, messages=n, data=np.concatenate(arrs))
    return bag
