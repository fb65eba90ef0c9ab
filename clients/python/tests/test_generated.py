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
