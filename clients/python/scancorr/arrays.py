"""Corrected points and estimator alarms as numpy structured arrays.

`POINT_DTYPE` (one row per corrected point):

    seq                  uint64   consecutive per machine: a jump means points were missed
    t_ns                 int64    controller time of the scale sample, ns
    sample_seq           uint64   seq of that scale sample
    surface              3×f8     corrected contact point, mm
    tip_center           3×f8     corrected tip centre, mm
    normal               3×f8     unit surface normal (zero when the probe is not deflected)
    calibration_version  uint64   calibration the point was corrected with
    valid                bool     False while an estimator-validity alarm is raised
    segment_id           uint32   scan segment of the command
    tip_id               uint32   active tip

`ALARM_DTYPE`: seq, t_ns, raised, axis (1 x, 2 y, 3 z), estimated_accel, measured_accel,
difference, threshold (mm/s²), action (1 flag, 2 suspend), calibration_version.

Decoding parses each batch with protobuf (upb). A packed batch (scancorr.v1.4, what the
service writes) is read column by column; a batch of per-point messages (older bags) into one
flat record per point, which numpy lays out in a single pass (`python bench/decode_points.py`
prints the rate).
"""

from __future__ import annotations

from typing import Dict, List, Tuple

import numpy as np

from .errors import ScancorrError
from .v1 import scancorr_pb2 as pb

POINT_DTYPE = np.dtype(
    [
        ("seq", "<u8"),
        ("t_ns", "<i8"),
        ("sample_seq", "<u8"),
        ("surface", "<f8", (3,)),
        ("tip_center", "<f8", (3,)),
        ("normal", "<f8", (3,)),
        ("calibration_version", "<u8"),
        ("valid", "?"),
        ("segment_id", "<u4"),
        ("tip_id", "<u4"),
    ]
)

# The same memory as POINT_DTYPE with every vector component a field of its own, so that a
# list of flat tuples converts in one call and is then viewed as POINT_DTYPE.
_FLAT_NAMES = ["seq", "t_ns", "sample_seq"]
_FLAT_FORMATS = ["<u8", "<i8", "<u8"]
_FLAT_OFFSETS = [POINT_DTYPE.fields[n][1] for n in _FLAT_NAMES]
for _v in ("surface", "tip_center", "normal"):
    for _k, _c in enumerate("xyz"):
        _FLAT_NAMES.append(f"{_v}_{_c}")
        _FLAT_FORMATS.append("<f8")
        _FLAT_OFFSETS.append(POINT_DTYPE.fields[_v][1] + 8 * _k)
for _n in ("calibration_version", "valid", "segment_id", "tip_id"):
    _FLAT_NAMES.append(_n)
    _FLAT_FORMATS.append(POINT_DTYPE.fields[_n][0].str)
    _FLAT_OFFSETS.append(POINT_DTYPE.fields[_n][1])
_FLAT = np.dtype(
    {
        "names": _FLAT_NAMES,
        "formats": _FLAT_FORMATS,
        "offsets": _FLAT_OFFSETS,
        "itemsize": POINT_DTYPE.itemsize,
    }
)

ALARM_DTYPE = np.dtype(
    [
        ("seq", "<u8"),
        ("t_ns", "<i8"),
        ("raised", "?"),
        ("axis", "<u1"),
        ("estimated_accel", "<f8"),
        ("measured_accel", "<f8"),
        ("difference", "<f8"),
        ("threshold", "<f8"),
        ("action", "<u1"),
        ("calibration_version", "<u8"),
    ]
)


class DecodeError(ScancorrError, ValueError):
    """A payload that does not decode as the message its key or channel promises."""


def _parse(cls, data: bytes, what: str):
    try:
        return cls.FromString(data)
    except Exception as e:  # protobuf raises several types
        raise DecodeError(f"{what}: {len(data)} bytes do not decode as {cls.DESCRIPTOR.full_name}: {e}") from e


def _per_point(points) -> np.ndarray:
    """Per-point messages (scancorr.v1.0–v1.3) as a `POINT_DTYPE` array."""
    rows = [
        (
            p.seq,
            p.t_ns,
            p.sample_seq,
            s.x,
            s.y,
            s.z,
            c.x,
            c.y,
            c.z,
            n.x,
            n.y,
            n.z,
            p.calibration_version,
            p.estimator_valid,
            p.segment_id,
            p.tip_id,
        )
        for p in points
        for s, c, n in ((p.surface, p.tip_center, p.normal),)
    ]
    return np.array(rows, dtype=_FLAT).view(POINT_DTYPE)


# A packed block's columns (scancorr.v1.4) by POINT_DTYPE's flat field.
_BLOCK_COLUMNS = {n: ("estimator_valid" if n == "valid" else n) for n in _FLAT_NAMES}


def _checked(block: "pb.CorrectedPointColumns") -> int:
    """A packed block's point count; DecodeError when a column holds another number of values
    (the corrections: one per point and effect)."""
    n = len(block.seq)
    for col in _BLOCK_COLUMNS.values():
        if len(getattr(block, col)) != n:
            raise DecodeError(
                f"CorrectedPointColumns: column `{col}` holds {len(getattr(block, col))} values for {n} points"
            )
    want = n * len(block.effects)
    for col in ("correction_dx", "correction_dy", "correction_dz"):
        if len(getattr(block, col)) != want:
            raise DecodeError(
                f"CorrectedPointColumns: column `{col}` holds {len(getattr(block, col))} values "
                f"for {n} points × {len(block.effects)} effects"
            )
    return n


def _block(block: "pb.CorrectedPointColumns") -> np.ndarray:
    """A packed block (scancorr.v1.4) as a `POINT_DTYPE` array, column by column."""
    flat = np.empty(_checked(block), dtype=_FLAT)
    for name, col in _BLOCK_COLUMNS.items():
        flat[name] = np.asarray(getattr(block, col), dtype=_FLAT.fields[name][0])
    return flat.view(POINT_DTYPE)


def points_from_message(batch: "pb.CorrectedPointBatch") -> np.ndarray:
    """The points of a decoded `CorrectedPointBatch` as a `POINT_DTYPE` array, from either
    layout: one message per point, or packed blocks (scancorr.v1.4). Raises DecodeError for
    a batch with both, or with a block whose columns hold other numbers of values."""
    if not len(batch.columns):
        return _per_point(batch.points)
    if len(batch.points):
        raise DecodeError(
            f"CorrectedPointBatch with both {len(batch.points)} per-point messages and {len(batch.columns)} packed blocks"
        )
    blocks = [_block(b) for b in batch.columns]
    return blocks[0] if len(blocks) == 1 else np.concatenate(blocks)


def decode_points(data: bytes, what: str = "points") -> np.ndarray:
    """One `CorrectedPointBatch` payload as a `POINT_DTYPE` array."""
    b = _parse(pb.CorrectedPointBatch, data, what)
    try:
        return points_from_message(b)
    except DecodeError as e:
        raise DecodeError(f"{what}: {e}") from None


def breakdown_from_message(batch: "pb.CorrectedPointBatch") -> Dict[str, np.ndarray]:
    """The per-effect corrections of each point: effect id → (n, 3) array, mm (zero where a
    point does not carry that effect), from either layout (see `points_from_message`)."""
    if len(batch.columns) and len(batch.points):
        raise DecodeError("CorrectedPointBatch with both per-point messages and packed blocks")
    n = len(batch.points) + sum(len(b.seq) for b in batch.columns)
    out: Dict[str, np.ndarray] = {}

    def column(effect: str) -> np.ndarray:
        a = out.get(effect)
        if a is None:
            a = out[effect] = np.zeros((n, 3))
        return a

    for i, p in enumerate(batch.points):
        for c in p.corrections:
            column(c.effect)[i] = (c.dx, c.dy, c.dz)
    at = 0
    for b in batch.columns:
        m, e = _checked(b), len(b.effects)
        if e:
            d = np.stack(
                [np.asarray(getattr(b, f"correction_d{k}"), dtype="<f8").reshape(m, e) for k in "xyz"], axis=-1
            )
            for j, effect in enumerate(b.effects):
                column(effect)[at : at + m] = d[:, j]
        at += m
    return out


def decode_breakdown(data: bytes, what: str = "points") -> Tuple[np.ndarray, Dict[str, np.ndarray]]:
    """One `CorrectedPointBatch` payload: its points and their per-effect corrections."""
    b = _parse(pb.CorrectedPointBatch, data, what)
    try:
        return points_from_message(b), breakdown_from_message(b)
    except DecodeError as e:
        raise DecodeError(f"{what}: {e}") from None


def alarm_from_message(a: "pb.EstimatorAlarm") -> np.ndarray:
    """One decoded `EstimatorAlarm` as a one-row `ALARM_DTYPE` array."""
    return np.array(
        [
            (
                a.seq,
                a.t_ns,
                a.raised,
                a.axis,
                a.estimated_accel,
                a.measured_accel,
                a.difference,
                a.threshold,
                a.action,
                a.calibration_version,
            )
        ],
        dtype=ALARM_DTYPE,
    )


def decode_alarm(data: bytes, what: str = "alarm") -> np.ndarray:
    """One `EstimatorAlarm` payload as a one-row `ALARM_DTYPE` array."""
    return alarm_from_message(_parse(pb.EstimatorAlarm, data, what))


def concat(arrays: List[np.ndarray], dtype: np.dtype) -> np.ndarray:
    """Concatenates arrays of one dtype (an empty array of `dtype` for none)."""
    return np.concatenate(arrays) if arrays else np.zeros(0, dtype)
