"""The generated protobuf modules are what proto/ generates today (never edited by hand)."""

from __future__ import annotations

import subprocess
import sys

from conftest import ROOT


def test_generated_protobuf_modules_are_current() -> None:
    r = subprocess.run(
        [sys.executable, str(ROOT / "clients" / "python" / "gen_proto.py"), "--check"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr


def test_the_schema_needs_no_bag() -> None:
    from scancorr.v1 import scancorr_pb2 as pb

    b = pb.CorrectedPointBatch()
    p = b.points.add(seq=7, calibration_version=3)
    p.surface.x = 1.5
    import scancorr

    a = scancorr.arrays.decode_points(b.SerializeToString())
    assert a["seq"][0] == 7 and a["surface"][0][0] == 1.5 and a["calibration_version"][0] == 3
    try:
        scancorr.arrays.decode_points(b"\xff\xff\xff")
    except scancorr.DecodeError as e:
        assert "CorrectedPointBatch" in str(e)
    else:
        raise AssertionError("a bad payload decoded")


def _packed_and_per_point():
    """The same five points as a packed batch of two blocks (scancorr.v1.4; the second block
    has other effects, as after a calibration swap) and as per-point messages."""
    from scancorr.v1 import scancorr_pb2 as pb

    per = pb.CorrectedPointBatch()
    packed = pb.CorrectedPointBatch()
    blocks = [(range(0, 3), ["a", "b"]), (range(3, 5), ["c"])]
    for rng, effects in blocks:
        c = packed.columns.add(machine_id="m1", effects=effects)
        for k in rng:
            p = per.points.add(
                machine_id="m1", seq=k, t_ns=-1000 * k, sample_seq=k + 3, calibration_version=k // 3,
                estimator_valid=k % 2 == 0, segment_id=k % 5, tip_id=7,
            )
            p.surface.x, p.surface.y, p.surface.z = k, -k, 0.5
            p.tip_center.y = 2.0 * k
            p.normal.z = 1.0
            for name, val in [("seq", k), ("t_ns", -1000 * k), ("sample_seq", k + 3),
                              ("calibration_version", k // 3), ("estimator_valid", k % 2 == 0),
                              ("segment_id", k % 5), ("tip_id", 7), ("surface_x", k), ("surface_y", -k),
                              ("surface_z", 0.5), ("tip_center_x", 0.0), ("tip_center_y", 2.0 * k),
                              ("tip_center_z", 0.0), ("normal_x", 0.0), ("normal_y", 0.0), ("normal_z", 1.0)]:
                getattr(c, name).append(val)
            for j, e in enumerate(effects):
                p.corrections.add(effect=e, dx=k * 1e-3 + j, dy=-1e-6, dz=0.0)
                c.correction_dx.append(k * 1e-3 + j)
                c.correction_dy.append(-1e-6)
                c.correction_dz.append(0.0)
    return packed, per


def test_packed_point_batches_decode_as_their_per_point_messages() -> None:
    import numpy as np
    import scancorr

    packed, per = _packed_and_per_point()
    a = scancorr.arrays.decode_points(packed.SerializeToString())
    b = scancorr.arrays.decode_points(per.SerializeToString())
    assert len(a) == 5 and a.tobytes() == b.tobytes()
    assert list(a["t_ns"]) == [0, -1000, -2000, -3000, -4000] and list(a["valid"]) == [True, False, True, False, True]
    _, ba = scancorr.arrays.decode_breakdown(packed.SerializeToString())
    _, bb = scancorr.arrays.decode_breakdown(per.SerializeToString())
    assert sorted(ba) == ["a", "b", "c"] == sorted(bb)
    for e in ba:
        np.testing.assert_array_equal(ba[e], bb[e])
    assert ba["c"][0].tolist() == [0, 0, 0] and ba["c"][4].tolist() == [4e-3, -1e-6, 0.0]


def test_malformed_packed_point_batches_are_refused_with_the_column_named() -> None:
    import scancorr

    packed, per = _packed_and_per_point()
    short = type(packed)()
    short.CopyFrom(packed)
    del short.columns[1].normal_y[-1]
    for decode in (scancorr.arrays.decode_points, scancorr.arrays.decode_breakdown):
        try:
            decode(short.SerializeToString(), "cmm/m1/corrected/points")
        except scancorr.DecodeError as e:
            assert "`normal_y` holds 1 values for 2 points" in str(e) and "cmm/m1" in str(e), e
        else:
            raise AssertionError("a short column decoded")
    both = type(packed)()
    both.CopyFrom(packed)
    both.points.add(seq=9)
    try:
        scancorr.arrays.decode_points(both.SerializeToString())
    except scancorr.DecodeError as e:
        assert "both" in str(e), e
    else:
        raise AssertionError("a batch of both layouts decoded")
