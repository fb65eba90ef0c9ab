"""The shape fits against the NIST least-squares reference circles and `scancorr shape fit`."""

from __future__ import annotations

import json
import pathlib

import numpy as np
import pytest

from scancorr import shape

from conftest import ROOT, run

NIST = ROOT.parent / "shared" / "reference" / "nist-l2-circle2d"


def nist_sets():
    sets = sorted(NIST.glob("*.ds"))
    assert len(sets) == 30, f"expected the 30 NIST circle sets in {NIST}, found {len(sets)}"
    return sets


def load(ds: pathlib.Path):
    lines = ds.read_text().split("\n")
    n = int(lines[0])
    p = np.array([[float(v) for v in line.split()] for line in lines[1 : n + 1]])
    ref = [float(v) for v in ds.with_suffix(".fit").read_text().split()]
    return p, np.array(ref[:3]), ref[6]


@pytest.mark.parametrize("ds", nist_sets(), ids=lambda p: p.stem)
def test_circle_matches_the_nist_reference_and_the_cli(ds: pathlib.Path, tmp_path: pathlib.Path) -> None:
    p, center, diameter = load(ds)
    f = shape.fit_circle(p)
    assert abs(f.diameter - diameter) <= 1e-10 * diameter
    assert np.linalg.norm(f.center - center) <= 1e-10 * diameter
    # The same data through `scancorr shape fit`: the same circle to 1e-9 relative, the same
    # roundness.
    cli = json.loads(run(tmp_path, "shape", "fit", "--kind", "circle", "--points", str(ds), "--json"))
    assert abs(cli["diameter"] - f.diameter) <= 1e-9 * diameter
    assert np.linalg.norm(np.array(cli["center"]) - f.center) <= 1e-9 * diameter
    assert abs(cli["roundness"] - f.peak_to_valley) <= 1e-9 * max(diameter, 1.0)


def test_straightness_matches_the_cli(tmp_path: pathlib.Path) -> None:
    t = np.linspace(0.0, 200.0, 41)
    p = np.column_stack([t, 0.5 * t, 3e-3 * np.sin(t / 13.0)])
    f = tmp_path / "line.txt"
    f.write_text("\n".join(" ".join(repr(float(v)) for v in row) for row in p))
    cli = json.loads(run(tmp_path, "shape", "fit", "--kind", "line", "--points", str(f), "--json"))
    assert abs(cli["straightness"] - shape.straightness(p)) <= 1e-12 * 200
    assert np.linalg.norm(np.array(cli["normal"]) - shape.fit_line(p).normal) < 1e-12


def test_fits_recover_known_shapes() -> None:
    rng = np.random.default_rng(7)
    # A sphere of Ø 25 mm at (1, 2, 3), a 1 µm noise.
    d = rng.normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    p = np.array([1.0, 2.0, 3.0]) + 12.5 * d + rng.normal(scale=1e-3, size=(500, 1)) * d
    s = shape.fit_sphere(p)
    assert abs(s.diameter - 25.0) < 2e-4 and np.linalg.norm(s.center - [1, 2, 3]) < 2e-4
    # A tilted plane and a line through it.
    u, v = np.array([1.0, 0, 0.1]), np.array([0, 1.0, -0.2])
    n = np.cross(u, v) / np.linalg.norm(np.cross(u, v))
    ab = rng.uniform(-50, 50, size=(400, 2))
    pl = ab[:, :1] * u + ab[:, 1:] * v + 5.0
    f = shape.fit_plane(pl)
    assert abs(abs(f.normal @ n) - 1) < 1e-12 and f.rms < 1e-12 and f.normal[np.argmax(np.abs(f.normal))] > 0
    t = np.linspace(0, 100, 50)[:, None]
    line = t * np.array([0.6, 0.8, 0.0]) + np.array([0.0, 0.0, 1.0])
    line[::2, 2] += 0.002
    ln = shape.fit_line(line)
    assert abs(ln.normal @ [0.6, 0.8, 0.0] - 1) < 1e-12
    # Every point about 1 µm from the least-squares line (which runs nearly midway): a
    # cylinder of about Ø 2 µm, twice the largest distance.
    assert abs(shape.straightness(line) - 0.002) < 2e-4
    assert shape.straightness(line) == 2 * ln.residuals.max()
    # 2-D rows are points in z = 0; roundness of a trefoil of ±1 µm is 2 µm.
    th = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    r = 20.0 + 1e-3 * np.cos(3 * th)
    xy = np.column_stack([r * np.cos(th), r * np.sin(th)])
    c = shape.fit_circle(xy)
    assert abs(c.diameter - 40.0) < 1e-9 and list(c.normal) == [0.0, 0.0, 1.0]
    assert abs(shape.roundness(xy) - 2e-3) < 1e-8


def test_bad_points_are_refused_with_a_reason() -> None:
    with pytest.raises(ValueError, match="at least 3 points"):
        shape.fit_circle([[0, 0, 0], [1, 0, 0]])
    with pytest.raises(ValueError, match="the points are collinear"):
        shape.fit_circle([[0, 0, 0], [1, 0, 0], [2, 0, 0]])
    with pytest.raises(ValueError, match="point 2 has a non-finite coordinate"):
        shape.fit_sphere([[0, 0, 0], [np.nan, 0, 0], [0, 1, 0], [0, 0, 1]])
    with pytest.raises(ValueError, match="all 2 points are the same point"):
        shape.fit_line([[1, 1, 1], [1, 1, 1]])
    with pytest.raises(ValueError, match="the points are coplanar"):
        shape.fit_sphere([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
