"""The shape fits against a real CMM's printout (`shared/reference/cmm-printout/fc2.csv`, next
to the repository; see its README): two circles and two planes with the CMM's own centre,
diameter, circularity or flatness and each point's deviation (DEV and its components DX DY
DZ), and the largest deviation to 6 decimals (`Max error`). Mirrors
tests/tests/cli_cmm_printout.rs, which checks `scancorr shape fit` the same way.

What the printout is, as found here:

- circle: the orthogonal least-squares circle; `Cirlty` is the range (peak-to-valley) of its
  radial residuals; DEV is the signed radial residual, positive outside (away from the
  centre), and DX DY DZ = DEV × the unit vector from the centre through the point;
- plane: the least-squares plane; its printed X Y Z is the points' centroid, `Flat` the range
  of the residuals; DEV is the signed distance along the normal (I J K = 0 0 1, +Z: the
  normal's largest component positive, our convention), DX DY DZ = DEV × the normal.

Every value matches to the printed digit (|fit − printed| ≤ half a unit of the last printed
decimal) except a few, pinned in `NOT_TO_THE_DIGIT`: the CMM fitted its unrounded
coordinates, the printout gives them to 4 decimals (±0.05 µm), and that rounding alone moves
a fitted value by up to `bound`, its worst case to first order (each coordinate's rounding
error ≤ half a digit, propagated through the least-squares fit's linearisation). Those few
are off by less than half a digit + `bound`, and so is everything else. (Sampling rounding
errors within the box finds, for each feature, coordinates that reproduce every printed
value, the 6-decimal `Max error` included: the printout is consistent with these fits of its
unrounded points.)
"""

from __future__ import annotations

import itertools
import json
import pathlib
from typing import Dict, List, Tuple

import numpy as np
import pytest

from scancorr import shape

from conftest import ROOT, run

FC2 = ROOT.parent / "shared" / "reference" / "cmm-printout" / "fc2.csv"
# Half a unit of the printout's 4th decimal, mm: the tolerance "to the printed digit", and the
# largest rounding error of each printed coordinate.
H = 0.5e-4
# Half a unit of the `Max error` line's 6th decimal, mm.
H6 = 0.5e-6

# The printed values a fit of the printed (rounded) points does not reproduce to the printed
# digit; each is within half a digit + the rounding bound (asserted). Off by (fit − printed):
# CR4 X +0.054 µm, circularity +0.096 µm (0.04630 for 0.0462), DEV 1 +0.063 µm; CR5 DEV 2
# +0.066 µm, DX 2 −0.052 µm, DX 7 +0.053 µm; PL9 flatness +0.067 µm (0.00157 for 0.0015),
# DEV 1 −0.063 µm, DEV 9 +0.067 µm; PL10 DEV 9 −0.070 µm; and none of the four 6-decimal `Max error`s (|fit| larger
# by 0.022 to 0.027 µm: a 4-decimal point set cannot pin a 6th decimal).
NOT_TO_THE_DIGIT = {
    "CR4": {"X", "Cirlty", "DEV 1", "Max error 1"},
    "CR5": {"DEV 2", "DX 2", "DX 7", "Max error 7"},
    "PL9": {"Flat", "DEV 1", "DZ 1", "DEV 9", "DZ 9", "Max error 4"},
    "PL10": {"DEV 9", "DZ 9", "Max error 5"},
}


def features() -> List[Dict[str, object]]:
    """The printout's features: kind, name, printed values (X Y Z I J K D Cirlty Flat), the
    point rows (X Y Z DX DY DZ DEV) and the `Max error` (value, point number)."""
    assert FC2.is_file(), f"reference data missing: {FC2} (see shared/reference/README.md, cmm-printout)"
    out: List[Dict[str, object]] = []
    cur: Dict[str, object] = {}
    for line in FC2.read_text().splitlines():
        f = line.split(",")
        if len(f) > 2 and f[1] in ("CIRCLE", "PLANE"):
            cur = {"kind": f[1].lower(), "name": f[2], "printed": {}, "rows": []}
            out.append(cur)
        elif not cur:
            continue
        elif f[0] in ("X", "Y", "Z", "I", "J", "K", "D", "Cirlty", "Flat"):
            cur["printed"][f[0]] = float(f[1])
        elif f[0].isdigit():
            assert int(f[0]) == len(cur["rows"]) + 1, line
            cur["rows"].append([float(v) for v in f[1:8]])
        elif f[:2] == ["Max", "error"]:
            cur["max_error"] = (float(f[3]), int(f[6]))
            cur = {}
    assert [(x["name"], len(x["rows"])) for x in out] == [("CR4", 8), ("CR5", 8), ("PL9", 9), ("PL10", 9)]
    assert all("max_error" in x for x in out)
    return out


def range_bound(m: np.ndarray, w: np.ndarray) -> float:
    """Worst-case change of the residuals' range when the residuals change by m·e, |e| ≤ w."""
    return max(float(np.abs(m[a] - m[b]) @ w) for a, b in itertools.permutations(range(len(w)), 2))


def checks(feat: Dict[str, object], fit: shape.Fit) -> List[Tuple[str, float, float, float, float]]:
    """(what, fitted, printed, half a printed digit, rounding bound) of every printed value."""
    pr = feat["printed"]
    rows = np.array(feat["rows"])
    p = rows[:, :3]
    n = len(p)
    res = fit.residuals
    if feat["kind"] == "circle":
        # The radial residual moves by u·δ for a coordinate error δ (|δx|, |δy| ≤ H), and the
        # fit's centre and radius take up J·(JᵀJ)⁻¹Jᵀ of it, J = [uₓ u_y 1].
        u = p[:, :2] - fit.center[:2]
        u /= np.linalg.norm(u, axis=1)[:, None]
        w = H * np.abs(u).sum(axis=1)
        jac = np.column_stack([u, np.ones(n)])
        g = np.linalg.solve(jac.T @ jac, jac.T)
        m = np.eye(n) - jac @ g
        dirs = np.column_stack([u, np.zeros(n)])
        out = [
            ("X", fit.center[0], pr["X"], H, float(np.abs(g[0]) @ w)),
            ("Y", fit.center[1], pr["Y"], H, float(np.abs(g[1]) @ w)),
            # All the points have the same printed Z: the centre's is their mean.
            ("Z", fit.center[2], pr["Z"], H, H),
            ("D", fit.diameter, pr["D"], H, 2.0 * float(np.abs(g[2]) @ w)),
            ("Cirlty", fit.peak_to_valley, pr["Cirlty"], H, range_bound(m, w)),
        ]
    else:
        # The residual moves by δz (and by the slopes × δx, δy); the plane takes up the
        # projection onto [1, x, y].
        nx, ny, nz = fit.normal
        w = H * (1.0 + abs(nx / nz) + abs(ny / nz)) * np.ones(n)
        a = np.column_stack([np.ones(n), p[:, 0] - fit.center[0], p[:, 1] - fit.center[1]])
        m = np.eye(n) - a @ np.linalg.solve(a.T @ a, a.T)
        dirs = np.tile(fit.normal, (n, 1))
        out = [
            # The printed X Y Z is the centroid: each the mean of rounded coordinates.
            ("X", fit.center[0], pr["X"], H, H),
            ("Y", fit.center[1], pr["Y"], H, H),
            ("Z", fit.center[2], pr["Z"], H, H),
            ("Flat", fit.peak_to_valley, pr["Flat"], H, range_bound(m, w)),
        ]
    bres = np.abs(m) @ w
    for i in range(n):
        out.append((f"DEV {i + 1}", res[i], rows[i, 6], H, bres[i]))
        for j, c in enumerate("XYZ"):
            out.append((f"D{c} {i + 1}", res[i] * dirs[i, j], rows[i, 3 + j], H, abs(dirs[i, j]) * bres[i]))
    value, k = feat["max_error"]
    out.append((f"Max error {k}", res[k - 1], value, H6, bres[k - 1]))
    return [(what, float(f), float(p_), h, float(b)) for what, f, p_, h, b in out]


@pytest.mark.parametrize("feat", features(), ids=lambda f: f["name"])
def test_fits_reproduce_the_cmm_printout(feat: Dict[str, object], tmp_path: pathlib.Path) -> None:
    p = np.array(feat["rows"])[:, :3]
    fit = shape.fit_circle(p) if feat["kind"] == "circle" else shape.fit_plane(p)
    pr = feat["printed"]
    # The normal (circle plane, plane) is the printed I J K to the digit: 0 0 1.
    assert np.abs(fit.normal - [pr["I"], pr["J"], pr["K"]]).max() <= H, fit.normal
    # The largest deviation is where the printout says.
    assert int(np.argmax(np.abs(fit.residuals))) + 1 == feat["max_error"][1]
    table = checks(feat, fit)
    report = "\n".join(
        f"  {what:<12} fit {f:+.7f} printed {p_:+.6f} off {f - p_:+.2e} bound {h:.1e}+{b:.2e}"
        for what, f, p_, h, b in table
    )
    for what, f, p_, h, b in table:
        assert abs(f - p_) <= h + b, f"{feat['name']} {what}: beyond the printout's rounding\n{report}"
    missed = {what for what, f, p_, h, _ in table if abs(f - p_) > h}
    assert missed == NOT_TO_THE_DIGIT[feat["name"]], f"{feat['name']}: not to the digit: {missed}\n{report}"
    # `scancorr shape fit` gives the same fit, form and residuals.
    pts = tmp_path / "points.txt"
    pts.write_text("".join(f"{x} {y} {z}\n" for x, y, z in p))
    cli = json.loads(run(tmp_path, "shape", "fit", "--kind", feat["kind"], "--points", str(pts), "--json"))
    assert np.abs(np.array(cli["center"]) - fit.center).max() <= 1e-9
    assert np.abs(np.array(cli["residuals"]) - fit.residuals).max() <= 1e-9
    if feat["kind"] == "circle":
        assert abs(cli["roundness"] - shape.roundness(p)) <= 1e-9
    else:
        assert abs(cli["flatness"] - shape.flatness(p)) <= 1e-9
