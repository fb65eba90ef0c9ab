//! Least squares for the lab: artifact fits with shared placements, and the joint linear fit
//! of effect parameters and artifact placements.
//!
//! Equation: with e_i the deviation of point i from its fitted artifact along the gradient g_i
//! (radial for circles, the normal for faces), adding corrections Σθ_k r_ik and moving the
//! artifact by ν changes it to e_i + Σ_k θ_k (g_i·r_ik) + Σ_j ν_j ∂e_i/∂ν_j; θ and ν minimise
//! the sum of squares. Every scan of one artifact placement shares its ν, so errors that only
//! move the apparent centre stay visible.

use super::dataset::{Dataset, LabPoint};
use super::program::{circle_plane, FeatureKind};
use crate::sample::Vec3;
use nalgebra::{DMatrix, DVector};

/// Fitted geometry of one feature.
#[derive(Debug, Clone)]
pub struct FeatureFit {
    /// Centre (circles) or reference point (faces), mm.
    pub center: Vec3,
    /// Radius (circles), mm.
    pub radius: f64,
    /// Radius held at the certificate.
    pub fixed_radius: bool,
    /// Face: offset, slope along the face, slope along z.
    pub plane: [f64; 3],
    /// Face: uses the z slope (points spread in z).
    pub plane_z: bool,
    /// Kind.
    pub kind: FeatureKind,
    /// Unit normal of a face, unit along-direction.
    pub axes: (Vec3, Vec3),
    /// Points used.
    pub n: usize,
}

/// Artifact fit of a set of points.
#[derive(Debug, Clone)]
pub struct ArtifactFit {
    /// Per feature (index as in the dataset), None when no point.
    pub features: Vec<Option<FeatureFit>>,
    /// Deviation e_i of each point from its feature, mm (radial outward for circles, along
    /// the face normal for faces).
    pub residual: Vec<f64>,
    /// Gradient g_i of e_i with respect to the point.
    pub grad: Vec<Vec3>,
    /// First nuisance column of each feature.
    pub col0: Vec<usize>,
    /// Number of nuisance columns.
    pub n_cols: usize,
}

fn circle_fit(pts: &[Vec3], fixed: Option<f64>) -> Option<(Vec3, f64)> {
    if pts.len() < 3 {
        return None;
    }
    // Algebraic (Kåsa) start, in coordinates relative to the centroid.
    let m = pts.iter().sum::<Vec3>() / pts.len() as f64;
    let mut a = nalgebra::Matrix3::<f64>::zeros();
    let mut b = nalgebra::Vector3::<f64>::zeros();
    for p in pts {
        let (x, y) = (p.x - m.x, p.y - m.y);
        let row = nalgebra::Vector3::new(x, y, 1.0);
        a += row * row.transpose();
        b += row * (x * x + y * y);
    }
    let s = a.lu().solve(&b)?;
    let mut c = nalgebra::Vector2::new(s[0] / 2.0 + m.x, s[1] / 2.0 + m.y);
    let mut r = (s[2] + (s[0] * s[0] + s[1] * s[1]) / 4.0).sqrt();
    if let Some(f) = fixed {
        r = f;
    }
    // Gauss–Newton on the geometric distance.
    for _ in 0..50 {
        let k = if fixed.is_some() { 2 } else { 3 };
        let mut jtj = DMatrix::<f64>::zeros(k, k);
        let mut jtr = DVector::<f64>::zeros(k);
        for p in pts {
            let d = nalgebra::Vector2::new(p.x - c.x, p.y - c.y);
            let rho = d.norm();
            if rho == 0.0 {
                continue;
            }
            let u = d / rho;
            let res = rho - r;
            let j = [-u.x, -u.y, -1.0];
            for i in 0..k {
                jtr[i] += j[i] * res;
                for l in 0..k {
                    jtj[(i, l)] += j[i] * j[l];
                }
            }
        }
        let step = jtj.lu().solve(&(-jtr))?;
        c.x += step[0];
        c.y += step[1];
        if k == 3 {
            r += step[2];
        }
        if step.norm() < 1e-13 * r.max(1.0) {
            break;
        }
    }
    (c.x.is_finite() && r.is_finite()).then(|| (Vec3::new(c.x, c.y, pts[0].z), r))
}

/// Fits every feature to the given points (`surfaces[i]` for `ds.points[i]`, only where
/// `use_point[i]`) and returns deviations and gradients for all points.
pub fn fit_artifacts(ds: &Dataset, surfaces: &[Vec3], use_point: &[bool]) -> ArtifactFit {
    let nf = ds.features.len();
    let mut by_feature: Vec<Vec<usize>> = vec![vec![]; nf];
    for (i, p) in ds.points.iter().enumerate() {
        if use_point[i] {
            by_feature[p.feature].push(i);
        }
    }
    let mut features = vec![];
    let mut col0 = vec![];
    let mut n_cols = 0;
    for (fi, idx) in by_feature.iter().enumerate() {
        let spec = &ds.features[fi].1;
        col0.push(n_cols);
        if idx.is_empty() {
            features.push(None);
            continue;
        }
        let pts: Vec<Vec3> = idx.iter().map(|&i| surfaces[i]).collect();
        match spec.kind {
            FeatureKind::Bore | FeatureKind::Boss => {
                let fixed = spec.certificate_diameter_mm.map(|d| d / 2.0);
                // A ring standing on its edge is fitted in its own plane.
                let tilted = circle_plane(spec.normal);
                let fitted = match tilted {
                    None => circle_fit(&pts, fixed),
                    Some((n, e1, e2)) => {
                        let local: Vec<Vec3> = pts
                            .iter()
                            .map(|p| Vec3::new(p.dot(&e1), p.dot(&e2), p.dot(&n)))
                            .collect();
                        circle_fit(&local, fixed).map(|(c, r)| (e1 * c.x + e2 * c.y + n * c.z, r))
                    }
                };
                let Some((c, r)) = fitted else {
                    features.push(None);
                    continue;
                };
                n_cols += 2 + fixed.is_none() as usize;
                features.push(Some(FeatureFit {
                    center: c,
                    radius: r,
                    fixed_radius: fixed.is_some(),
                    plane: [0.0; 3],
                    plane_z: false,
                    kind: spec.kind,
                    axes: tilted.map_or((Vec3::zeros(), Vec3::zeros()), |(n, e1, _)| (n, e1)),
                    n: pts.len(),
                }));
            }
            FeatureKind::Face => {
                let n = Vec3::from(spec.normal).normalize();
                let along = n.cross(&Vec3::z()).try_normalize(1e-9).unwrap_or(Vec3::x());
                let c = Vec3::from(spec.nominal_center);
                let (zmin, zmax) = pts
                    .iter()
                    .fold((f64::MAX, f64::MIN), |a, p| (a.0.min(p.z), a.1.max(p.z)));
                let use_z = zmax - zmin > 1.0;
                let k = 2 + use_z as usize;
                let mut a = DMatrix::<f64>::zeros(k, k);
                let mut b = DVector::<f64>::zeros(k);
                for p in &pts {
                    let row = [1.0, (p - c).dot(&along), p.z - c.z];
                    let y = (p - c).dot(&n);
                    for i in 0..k {
                        b[i] += row[i] * y;
                        for l in 0..k {
                            a[(i, l)] += row[i] * row[l];
                        }
                    }
                }
                let Some(sol) = a.lu().solve(&b) else {
                    features.push(None);
                    continue;
                };
                n_cols += k;
                features.push(Some(FeatureFit {
                    center: c,
                    radius: 0.0,
                    fixed_radius: true,
                    plane: [sol[0], sol[1], if use_z { sol[2] } else { 0.0 }],
                    plane_z: use_z,
                    kind: FeatureKind::Face,
                    axes: (n, along),
                    n: pts.len(),
                }));
            }
        }
    }
    let mut residual = vec![0.0; ds.points.len()];
    let mut grad = vec![Vec3::zeros(); ds.points.len()];
    for (i, p) in ds.points.iter().enumerate() {
        if let Some(f) = &features[p.feature] {
            let (e, g) = deviation(f, &surfaces[i]);
            residual[i] = e;
            grad[i] = g;
        }
    }
    ArtifactFit {
        features,
        residual,
        grad,
        col0,
        n_cols,
    }
}

/// Deviation of a point from a fitted feature and its gradient.
pub fn deviation(f: &FeatureFit, p: &Vec3) -> (f64, Vec3) {
    match f.kind {
        FeatureKind::Face => {
            let (n, along) = f.axes;
            let d = p - f.center;
            (
                d.dot(&n) - f.plane[0] - f.plane[1] * d.dot(&along) - f.plane[2] * d.z,
                n,
            )
        }
        _ if f.axes.0 != Vec3::zeros() => {
            // In the plane of a ring standing on its edge.
            let n = f.axes.0;
            let d = p - f.center;
            let d = d - n * d.dot(&n);
            let rho = d.norm();
            let u = if rho > 0.0 { d / rho } else { f.axes.1 };
            (rho - f.radius, u)
        }
        _ => {
            let d = Vec3::new(p.x - f.center.x, p.y - f.center.y, 0.0);
            let rho = d.norm();
            let u = if rho > 0.0 { d / rho } else { Vec3::x() };
            (rho - f.radius, u)
        }
    }
}

/// Nuisance (placement) Jacobian entries of point `p` (column, value).
pub fn nuisance_row(fit: &ArtifactFit, p: &LabPoint, surface: &Vec3, out: &mut Vec<(usize, f64)>) {
    out.clear();
    let Some(f) = &fit.features[p.feature] else {
        return;
    };
    let c0 = fit.col0[p.feature];
    match f.kind {
        FeatureKind::Face => {
            let d = surface - f.center;
            out.push((c0, -1.0));
            out.push((c0 + 1, -d.dot(&f.axes.1)));
            if f.plane_z {
                out.push((c0 + 2, -d.z));
            }
        }
        _ => {
            let (_, u) = deviation(f, surface);
            let (e1, e2) = if f.axes.0 != Vec3::zeros() {
                (f.axes.1, f.axes.1.cross(&f.axes.0))
            } else {
                (Vec3::x(), Vec3::y())
            };
            out.push((c0, -u.dot(&e1)));
            out.push((c0 + 1, -u.dot(&e2)));
            if !f.fixed_radius {
                out.push((c0 + 2, -1.0));
            }
        }
    }
}

/// Normal equations of min ‖y + A x‖² accumulated row by row.
#[derive(Debug, Clone)]
pub struct Normal {
    /// AᵀA.
    pub m: DMatrix<f64>,
    /// Aᵀy.
    pub b: DVector<f64>,
    /// yᵀy.
    pub yy: f64,
    /// Rows.
    pub n: usize,
}

/// Solution of a [`Normal`] system.
#[derive(Debug, Clone)]
pub struct Solved {
    /// x minimising ‖y + A x‖².
    pub x: DVector<f64>,
    /// Residual sum of squares at x.
    pub ss: f64,
    /// (AᵀA)⁺ (unscaled covariance).
    pub cov: DMatrix<f64>,
    /// Columns (mostly) in the null space: not identifiable from the data.
    pub unidentifiable: Vec<usize>,
    /// Numerical rank.
    pub rank: usize,
}

impl Normal {
    /// Empty system with `k` columns.
    pub fn new(k: usize) -> Normal {
        Normal {
            m: DMatrix::zeros(k, k),
            b: DVector::zeros(k),
            yy: 0.0,
            n: 0,
        }
    }
    /// Adds a dense part `dense` (columns 0..dense.len()) and sparse part `sparse` of a row.
    #[inline]
    pub fn add(&mut self, dense: &[f64], sparse: &[(usize, f64)], y: f64) {
        let k = dense.len();
        for i in 0..k {
            let di = dense[i];
            if di == 0.0 {
                continue;
            }
            self.b[i] += di * y;
            for (j, dj) in dense[..=i].iter().enumerate() {
                self.m[(i, j)] += di * dj;
            }
            for &(c, v) in sparse {
                self.m[(c + k, i)] += v * di;
            }
        }
        for &(c, v) in sparse {
            self.b[c + k] += v * y;
            for &(c2, v2) in sparse {
                if c2 <= c {
                    self.m[(c + k, c2 + k)] += v * v2;
                }
            }
        }
        self.yy += y * y;
        self.n += 1;
    }
    /// Solves with a rank-revealing pseudo-inverse.
    pub fn solve(&self) -> Solved {
        let k = self.b.len();
        let mut m = self.m.clone();
        for i in 0..k {
            for j in 0..i {
                m[(j, i)] = m[(i, j)];
            }
        }
        let s: Vec<f64> = (0..k)
            .map(|i| {
                if m[(i, i)] > 0.0 {
                    1.0 / m[(i, i)].sqrt()
                } else {
                    0.0
                }
            })
            .collect();
        let mut ms = m.clone();
        for i in 0..k {
            for j in 0..k {
                ms[(i, j)] *= s[i] * s[j];
            }
        }
        let eig = nalgebra::SymmetricEigen::new(ms);
        let lmax = eig.eigenvalues.iter().cloned().fold(0.0, f64::max);
        let tol = lmax * 1e-10;
        let mut pinv = DMatrix::<f64>::zeros(k, k);
        let mut rank = 0;
        let mut null_weight = vec![0.0; k];
        for (l, &lam) in eig.eigenvalues.iter().enumerate() {
            let v = eig.eigenvectors.column(l);
            if lam > tol {
                rank += 1;
                pinv += v * v.transpose() / lam;
            } else {
                for i in 0..k {
                    null_weight[i] += v[i] * v[i];
                }
            }
        }
        let mut cov = pinv;
        for i in 0..k {
            for j in 0..k {
                cov[(i, j)] *= s[i] * s[j];
            }
        }
        let x = -(&cov * &self.b);
        let ss = (self.yy + self.b.dot(&x)).max(0.0);
        let unidentifiable = (0..k)
            .filter(|&i| null_weight[i] > 0.5 || s[i] == 0.0)
            .collect();
        Solved {
            x,
            ss,
            cov,
            unidentifiable,
            rank,
        }
    }
}

/// Maximises `h` on [a, b] by golden-section search.
pub(crate) fn golden_max(h: impl Fn(f64) -> f64, mut a: f64, mut b: f64) -> f64 {
    let r = (5f64.sqrt() - 1.0) / 2.0;
    let mut x1 = b - r * (b - a);
    let mut x2 = a + r * (b - a);
    let (mut h1, mut h2) = (h(x1), h(x2));
    for _ in 0..80 {
        if (b - a) <= 1e-10 * b.abs().max(1e-12) {
            break;
        }
        if h1 >= h2 {
            b = x2;
            x2 = x1;
            h2 = h1;
            x1 = b - r * (b - a);
            h1 = h(x1);
        } else {
            a = x1;
            x1 = x2;
            h1 = h2;
            x2 = a + r * (b - a);
            h2 = h(x2);
        }
    }
    if h1 >= h2 {
        x1
    } else {
        x2
    }
}
