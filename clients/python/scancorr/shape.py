"""Least-squares geometry: circle, sphere, line and plane fits, roundness and straightness.

The same definitions as `scancorr shape fit` (service/core/src/shape/):

- every fit minimises the sum of squared **orthogonal** distances (ISO 10360-6 / ASME
  B89.4.10 least-squares features);
- a circle in 3-D: the least-squares plane through the centroid, then the least-squares
  circle of the points projected on it; 2-D points (`x y`) lie in z = 0;
- residuals: a circle's are radial within its plane (positive outside), a sphere's radial, a
  plane's signed along its normal, a line's the (non-negative) distance from it;
- a normal or direction has its largest-magnitude component positive;
- `roundness` (circle) is the peak-to-valley of the least-squares circle's residuals,
  `flatness` (plane) that of the least-squares plane's;
  `straightness` (line) the diameter of the cylinder about the least-squares line that holds
  every point (twice the largest distance), in the points' unit.

Each fit returns a `Fit` with `center` (a line's and a plane's: the centroid), `normal` (a
line's: its direction), `diameter` (circle, sphere; else None), `rms` and `residuals`.

A fit that the points do not determine raises `scancorr.ShapeError` (a `ValueError`), with the
guards and the words of `scancorr shape fit`: too few points, a non-finite coordinate, all
points the same, collinear points for a circle or a plane (σ₂/σ₁ ≤ 1e-9), coplanar points for
a sphere, a best-fit radius over 1e6 times the points' extent. One guard more than the CLI's:
a circle whose points span less than `min_arc_deg` (1°) of it — a straightedge's scan is no
circle, though its bow fits one of some kilometres: the points lie on a nearly straight line,
the circle is undetermined. `min_arc_deg=0` fits it anyway, as the CLI does.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from .errors import ShapeError

__all__ = [
    "ShapeError",
    "MIN_ARC_DEG",
    "Fit",
    "fit_circle",
    "fit_sphere",
    "fit_line",
    "fit_plane",
    "roundness",
    "straightness",
    "flatness",
    "peak_to_valley",
]


#: σ₂/σ₁ (circle, plane) or σ₃/σ₁ (sphere) at or below which the points count as collinear or
#: coplanar (service/core/src/shape/mod.rs: DEGENERATE_RATIO).
DEGENERATE_RATIO = 1e-9
#: Fitted radius over the points' RMS extent above which an arc or cap counts as flat
#: (shape.rs: MAX_RADIUS_RATIO).
MAX_RADIUS_RATIO = 1e6
#: The least arc, in degrees, a circle's points must span (`fit_circle(min_arc_deg=…)`).
MIN_ARC_DEG = 1.0

_FLAT_CIRCLE = "the points lie on a nearly straight line, the circle is undetermined; scan more of the circle's circumference"
_FLAT_SPHERE = ("the points lie on a nearly flat surface, the sphere is undetermined; probe points over a larger "
                "part of the sphere (e.g. around the equator and one at the pole)")


@dataclass
class Fit:
    """A fitted feature (units: those of the points, mm for scancorr's)."""

    kind: str
    center: np.ndarray
    normal: Optional[np.ndarray]
    diameter: Optional[float]
    rms: float
    residuals: np.ndarray
    plane_rms: float = 0.0

    @property
    def radius(self) -> Optional[float]:
        return None if self.diameter is None else self.diameter / 2.0

    @property
    def peak_to_valley(self) -> float:
        return peak_to_valley(self.residuals)


def peak_to_valley(residuals: np.ndarray) -> float:
    """Largest minus smallest residual (0 for none)."""
    r = np.asarray(residuals, dtype=float)
    return float(r.max() - r.min()) if r.size else 0.0


def _points(points: object, kind: str, need: int) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] not in (2, 3):
        raise ShapeError(f"{kind} fit: points must be an (n, 3) or (n, 2) array, got shape {p.shape}")
    if p.shape[1] == 2:
        p = np.column_stack([p, np.zeros(len(p))])
    if len(p) < need:
        raise ShapeError(
            f"{kind} fit: a {kind} fit needs at least {need} points, got {len(p)}: measure at least "
            f"{need - len(p)} more point(s) on the feature"
        )
    bad = ~np.isfinite(p).all(axis=1)
    if bad.any():
        raise ShapeError(
            f"{kind} fit: point {int(np.argmax(bad)) + 1} has a non-finite coordinate (NaN or infinity): "
            "re-measure or remove it"
        )
    return p


def _orient(v: np.ndarray) -> np.ndarray:
    v = v / np.linalg.norm(v)
    return -v if v[np.argmax(np.abs(v))] < 0 else v


def _frame(p: np.ndarray, kind: str):
    """Centroid, scale (RMS distance from it), singular values (of the points, mm) and the right
    singular vectors (rows, by decreasing singular value) of the centred points."""
    c = p.mean(axis=0)
    q = p - c
    with np.errstate(over="ignore", invalid="ignore"):
        scale = float(np.sqrt((q * q).sum(axis=1).mean()))
    if not (np.isfinite(scale) and np.isfinite(c).all()):
        raise ShapeError(
            f"{kind} fit: the coordinates are too large to fit in double precision (up to about 1e150 mm is "
            "supported): check the units of the points"
        )
    if scale == 0.0 or scale <= 1e-13 * float(np.abs(p).max()):
        raise ShapeError(
            f"{kind} fit: all {len(p)} points are the same point: the {kind} is undetermined; measure points "
            "spread over the feature"
        )
    _, s, vt = np.linalg.svd(q / scale, full_matrices=False)
    s = np.concatenate([s, np.zeros(3 - len(s))])
    return c, scale, s, vt


def _collinear(kind: str) -> ShapeError:
    hint = ("scan more of the circle's circumference (at least 3 points not on one line)" if kind == "circle" else
            "the plane is undetermined; probe points spread in two directions over the surface (at least 3 not "
            "on one line)")
    return ShapeError(f"{kind} fit: the points are collinear: {hint}")


def _e(x: float) -> str:
    """`x` as Rust's `{:.6e}` prints it (`5.000000e8`, `2.886607e1`)."""
    m, _, exp = f"{x:.6e}".partition("e")
    return f"{m}e{int(exp)}" if exp else m


def _too_flat(kind: str, radius: float, extent: float) -> ShapeError:
    return ShapeError(
        f"{kind} fit: best-fit radius {_e(radius)} mm over a point extent of {_e(extent)} mm: "
        f"{_FLAT_SPHERE if kind == 'sphere' else _FLAT_CIRCLE}"
    )


def _arc_span(uv: np.ndarray, center: np.ndarray) -> float:
    """The angle (radians) the points span about `center`: 2π less the widest gap between
    neighbouring points' angles."""
    th = np.sort(np.arctan2(uv[:, 1] - center[1], uv[:, 0] - center[0]))
    gaps = np.diff(np.concatenate([th, th[:1] + 2 * np.pi]))
    return float(2 * np.pi - gaps.max())


def _ls_sphere(q: np.ndarray) -> np.ndarray:
    """Orthogonal-distance least squares of a circle (2 columns) or sphere (3 columns) to
    `q` (centred, scaled): algebraic start, Levenberg–Marquardt, Gauss–Newton polish.
    Returns [centre…, radius]."""
    d = q.shape[1]
    a = np.column_stack([2 * q, np.ones(len(q))])
    sol, *_ = np.linalg.lstsq(a, (q * q).sum(axis=1), rcond=None)
    x = np.append(sol[:d], np.sqrt(max(sol[d] + sol[:d] @ sol[:d], 1e-300)))

    def resid(x: np.ndarray):
        diff = q - x[:d]
        dist = np.sqrt((diff * diff).sum(axis=1))
        return dist - x[d], diff, dist

    r, diff, dist = resid(x)
    cost = r @ r
    lam = 1e-3
    for _ in range(500):
        j = np.column_stack([-diff / dist[:, None], -np.ones(len(q))])
        jtj, jtr = j.T @ j, j.T @ r
        step = np.linalg.solve(jtj + lam * np.diag(np.diag(jtj)), -jtr)
        xn = x + step
        rn, diffn, distn = resid(xn)
        cn = rn @ rn
        if cn <= cost:
            x, r, diff, dist = xn, rn, diffn, distn
            small = np.linalg.norm(step) <= 1e-15 * (1.0 + np.linalg.norm(x))
            done = cost - cn <= 1e-30 + 1e-16 * cost
            cost = cn
            lam = max(lam / 10.0, 1e-12)
            if small or done:
                break
        else:
            lam *= 10.0
            if lam > 1e12:
                break
    # Newton polish (undamped Gauss–Newton until the step stops shrinking).
    for _ in range(20):
        j = np.column_stack([-diff / dist[:, None], -np.ones(len(q))])
        step, *_ = np.linalg.lstsq(j, -r, rcond=None)
        x = x + step
        r, diff, dist = resid(x)
        if np.linalg.norm(step) <= 1e-16 * (1.0 + np.linalg.norm(x)):
            break
    return x


def fit_circle(points: object, *, min_arc_deg: float = MIN_ARC_DEG) -> Fit:
    """Least-squares circle of 3-D points lying (nearly) in a plane, or of 2-D points.
    Raises `ShapeError` when the points do not determine a circle: on one line, a best-fit
    radius over 1e6 times their extent, or spanning less than `min_arc_deg` degrees of it (a
    straightedge; 0: no such guard, as `scancorr shape fit`)."""
    p = _points(points, "circle", 3)
    c, scale, s, vt = _frame(p, "circle")
    if s[1] <= DEGENERATE_RATIO * s[0]:
        raise _collinear("circle")
    u, v, n = vt[0], vt[1], vt[2]
    q = (p - c) / scale
    uv = np.column_stack([q @ u, q @ v])
    x = _ls_sphere(uv)
    if not np.isfinite(x).all() or abs(x[2]) > MAX_RADIUS_RATIO or np.abs(x[:2]).max() > 1e3 * MAX_RADIUS_RATIO:
        raise _too_flat("circle", abs(x[2]) * scale, scale)
    x[2] = abs(x[2])
    span = np.degrees(_arc_span(uv, x[:2]))
    if span < min_arc_deg:
        raise ShapeError(
            f"circle fit: the points span {span:.3g}° of the best-fit circle (radius {_e(x[2] * scale)} mm over a "
            f"point extent of {_e(scale)} mm), less than {min_arc_deg:g}°: {_FLAT_CIRCLE}"
        )
    center = c + scale * (x[0] * u + x[1] * v)
    radius = scale * x[2]
    rel = p - center
    inplane = rel - np.outer(rel @ n, n)
    res = np.sqrt((inplane * inplane).sum(axis=1)) - radius
    out = (p - c) @ n
    return Fit(
        kind="circle",
        center=center,
        normal=_orient(n),
        diameter=2.0 * radius,
        rms=float(np.sqrt(np.mean(res * res))),
        residuals=res,
        plane_rms=float(np.sqrt(np.mean(out * out))),
    )


def fit_sphere(points: object) -> Fit:
    """Least-squares sphere of 3-D points (at least 4, not in one plane)."""
    p = _points(points, "sphere", 4)
    c, scale, s, _ = _frame(p, "sphere")
    if s[1] <= DEGENERATE_RATIO * s[0] or s[2] <= DEGENERATE_RATIO * s[0]:
        raise ShapeError(
            "sphere fit: the points are coplanar: the sphere is undetermined; probe points off that plane "
            "(e.g. one near the pole)"
        )
    x = _ls_sphere((p - c) / scale)
    if not np.isfinite(x).all() or abs(x[3]) > MAX_RADIUS_RATIO or np.abs(x[:3]).max() > 1e3 * MAX_RADIUS_RATIO:
        raise _too_flat("sphere", abs(x[3]) * scale, scale)
    center = c + scale * x[:3]
    radius = scale * abs(x[3])
    res = np.linalg.norm(p - center, axis=1) - radius
    return Fit("sphere", center, None, 2.0 * radius, float(np.sqrt(np.mean(res * res))), res)


def fit_line(points: object) -> Fit:
    """Least-squares straight line: through the centroid along the principal direction."""
    p = _points(points, "line", 2)
    c, _, _, vt = _frame(p, "line")
    d = _orient(vt[0])
    rel = p - c
    perp = rel - np.outer(rel @ d, d)
    res = np.sqrt((perp * perp).sum(axis=1))
    return Fit("line", c, d, None, float(np.sqrt(np.mean(res * res))), res)


def fit_plane(points: object) -> Fit:
    """Least-squares plane: through the centroid, normal to the two principal directions."""
    p = _points(points, "plane", 3)
    c, _, s, vt = _frame(p, "plane")
    if s[1] <= DEGENERATE_RATIO * s[0]:
        raise _collinear("plane")
    n = _orient(vt[2])
    res = (p - c) @ n
    return Fit("plane", c, n, None, float(np.sqrt(np.mean(res * res))), res)


def roundness(points: object) -> float:
    """Peak-to-valley of the least-squares circle's radial residuals."""
    return fit_circle(points).peak_to_valley


def flatness(points: object) -> float:
    """Peak-to-valley of the least-squares plane's residuals."""
    return fit_plane(points).peak_to_valley


def straightness(points: object) -> float:
    """Diameter of the cylinder about the least-squares line that holds every point (as
    `scancorr shape fit --kind line`)."""
    return 2.0 * float(fit_line(points).residuals.max())
