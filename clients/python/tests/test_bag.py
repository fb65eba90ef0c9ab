"""read_bag: every channel of a campaign bag, and the corrected points of its correction."""

from __future__ import annotations

import json
import pathlib

import numpy as np
import pytest

import scancorr

from conftest import run


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> pathlib.Path:
    d = tmp_path_factory.mktemp("campaign")
    run(d, "sim", "--program", "campaign", "--out", "c.mcap", "--calib-out", "v1.json")
    return d


def test_read_bag_reads_every_channel_of_a_campaign(campaign: pathlib.Path) -> None:
    b = scancorr.read_bag(campaign / "c.mcap")
    counts = {k: int(v) for k, v in b.metadata["scancorr.sample_counts"].items()}
    assert set(b.topics()) == set(counts), (b.topics(), counts)
    assert not b.skipped and not b.malformed and not b.undecodable
    assert b.truncation is None and not b.damaged_chunks and not b.problems()
    for topic, n in counts.items():
        a = b[topic]
        assert len(a) == n, topic
        # seq consecutive from 0, time never decreasing.
        assert np.array_equal(a["seq"], np.arange(n)), topic
        assert (np.diff(a["t_ns"]) >= 0).all(), topic
    scale = b["cmm/m1/raw/scale"]
    assert scale.dtype.names == ("seq", "t_ns", "x", "y", "z")
    assert np.isfinite(scale["x"]).all() and np.ptp(scale["x"]) > 10.0
    temp = b["cmm/m1/raw/temperature"]
    assert set(temp["sensor"]) and np.isfinite(temp["celsius"]).all()
    assert b.metadata["scancorr.run"]["program"] == "campaign"
    # pandas: each channel a DataFrame with the same rows.
    frames = b.frames()
    assert {t: len(f) for t, f in frames.items()} == counts


def test_read_bag_reads_the_corrected_points(campaign: pathlib.Path) -> None:
    s = json.loads(run(campaign, "correct", "--bag", "c.mcap", "--calib", "v1.json", "--out", "cc.mcap", "--json"))
    b = scancorr.read_bag(campaign / "cc.mcap")
    pts = b.points()
    assert len(pts) == s["points"]
    assert np.array_equal(pts["seq"], np.arange(len(pts)))
    assert (pts["calibration_version"] == 1).all()
    assert (~pts["valid"]).sum() == s["points_flagged"]
    assert b.alarms()["raised"].sum() == s["alarms"]
    # A contact point's normal is a unit vector; the tip centre lies inside the part along it.
    n = pts["normal"]
    contact = np.abs(n).sum(axis=1) > 0
    assert contact.mean() > 0.5
    assert np.allclose(np.linalg.norm(n[contact], axis=1), 1.0, atol=1e-9)
    f = b.frames()["cmm/m1/corrected/points"]
    assert {"surface_x", "surface_y", "surface_z", "valid"} <= set(f.columns)


def test_every_metadata_record_is_kept(campaign: pathlib.Path) -> None:
    """A campaign bag has five `scancorr.artifact` records (one per feature): all read, in
    file order, as an independent reader (the `mcap` package) reads them."""
    b = scancorr.read_bag(campaign / "c.mcap")
    arts = b.metadata_records["scancorr.artifact"]
    assert [a["feature_id"] for a in arts] == ["1", "2", "3", "4", "5"]
    assert [a["kind"] for a in arts] == ["ring", "ring", "ring", "sphere", "straightedge"]
    assert b.artifacts() == arts
    assert b.metadata["scancorr.artifact"] == arts[-1]  # the last, as the Rust reader's metadata_named
    assert b.metadata_records["scancorr.run"] == [b.metadata["scancorr.run"]]
    from mcap.reader import make_reader

    with open(campaign / "c.mcap", "rb") as fh:
        theirs = [(m.name, dict(m.metadata)) for m in make_reader(fh).iter_metadata()]
    ours = [(n, r) for n, rs in b.metadata_records.items() for r in rs]
    assert sorted(ours, key=repr) == sorted(theirs, key=repr) and len(theirs) == 8


def test_a_file_that_is_not_a_bag_is_refused(tmp_path: pathlib.Path) -> None:
    p = tmp_path / "x.mcap"
    p.write_bytes(b"not an mcap file")
    with pytest.raises(scancorr.BagError, match=f"^{p}: not an MCAP file: wrong magic bytes at the start$"):
        scancorr.read_bag(p)
    with pytest.raises(FileNotFoundError):
        scancorr.read_bag(tmp_path / "missing.mcap")


def test_the_readme_example_runs(tmp_path: pathlib.Path) -> None:
    """The README's ten-line example, as printed, on a corrected ring."""
    import re
    import subprocess
    import sys

    from conftest import ROOT

    text = (ROOT / "clients" / "python" / "README.md").read_text()
    code = re.findall(r"```python\n(.*?)```", text, re.S)[0]
    assert len(code.strip().splitlines()) <= 12, code
    (tmp_path / "example.py").write_text(code)
    run(tmp_path, "sim", "--program", "ring", "--out", "r.mcap", "--calib-out", "v1.json", "--truth", "t.json")
    run(tmp_path, "correct", "--bag", "r.mcap", "--calib", "v1.json", "--out", "c.mcap")
    r = subprocess.run([sys.executable, "example.py", "c.mcap"], cwd=tmp_path, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    truth = 2 * json.loads((tmp_path / "t.json").read_text())["features"][0]["radius_mm"]
    lines = r.stdout.splitlines()
    assert len(lines) == 2, r.stdout  # the CCW and the CW scan
    for line in lines:
        d = float(re.search(r"Ø (\S+) mm", line).group(1))
        assert abs(d - truth) < 1e-3, (line, truth)
