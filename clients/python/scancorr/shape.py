"""Least-squares geometry: circle, sphere, line and plane fits, roundness and straightness.

The same definitions as `scancorr shape fit` (service/core/src/shape.rs):

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
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

__all__ = [
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
        raise ValueError(f"{kind} fit: points must be an (n, 3) or (n, 2) array, got shape {p.shape}")
    if p.shape[1] == 2:
        p = np.column_stack([p, np.zeros(len(p))])
    if len(p) < need:
        raise ValueError(f"{kind} fit needs at least {need} points, got {len(p)}")
    bad = ~np.isfinite(p).all(axis=1)
    if bad.any():
        raise ValueError(f"{kind} fit: point {int(np.argmax(bad)) + 1} has a coordinate that is not a finite number")
    return p


def _orient(v: np.ndarray) -> np.ndarray:
    v = v / np.linalg.norm(v)
    return -v if v[np.argmax(np.abs(v))] < 0 else v


def _frame(p: np.ndarray, kind: str):
    """Centroid, scale (RMS distance from it) and the right singular vectors (rows, by
    decreasing singular value) of the centred points."""
    c = p.mean(axis=0)
    q = p - c
    scale = float(np.sqrt((q * q).sum(axis=1).mean()))
    if not scale > 0.0:
        raise ValueError(f"{kind} fit: all {len(p)} points coincide")
    _, s, vt = np.linalg.svd(q / scale, full_matrices=False)
    return c, scale, s, vt


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


def fit_circle(points: object) -> Fit:
    """Least-squares circle of 3-D points lying (nearly) in a plane, or of 2-D points."""
    p = _points(points, "circle", 3)
    c, scale, s, vt = _frame(p, "circle")
    if s[1] <= 1e-12 * s[0]:
        raise ValueError("circle fit: the points lie on one line")
    u, v, n = vt[0], vt[1], vt[2]
    q = (p - c) / scale
    uv = np.column_stack([q @ u, q @ v])
    x = _ls_sphere(uv)
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
    if s[2] <= 1e-12 * s[0]:
        raise ValueError("sphere fit: the points lie in one plane")
    x = _ls_sphere((p - c) / scale)
    center = c + scale * x[:3]
    radius = scale * x[3]
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
    if s[1] <= 1e-12 * s[0]:
        raise ValueError("plane fit: the points lie on one line")
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
