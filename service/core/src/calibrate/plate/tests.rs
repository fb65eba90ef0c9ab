use super::*;

/// splitmix64 → uniform and normal deviates (a fixed seed: the tests are repeatable).
struct Rng(u64);

impl Rng {
    fn uniform(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        (z >> 11) as f64 / (1u64 << 53) as f64
    }
    fn normal(&mut self) -> f64 {
        let u = self.uniform().max(1e-300);
        let v = self.uniform();
        (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
    }
}

/// The truth of a synthetic plate.
#[derive(Clone, Copy)]
struct Truth {
    offset_um: [f64; 2],
    rotation_urad: f64,
    scale_ppm: f64,
    q_ppm: f64,
    phi_deg: f64,
    /// X error ∝ (y/R)³ at the edge, µm.
    dx_y3_um: f64,
    noise_um: f64,
}

const R: f64 = 300.0;

fn plate(t: Truth, n: usize, seed: u64) -> Vec<Feature> {
    let mut rng = Rng(seed);
    let th = t.rotation_urad * 1e-6;
    let s = 1.0 + t.scale_ppm * 1e-6;
    let (q, p2) = (t.q_ppm * 1e-6, 2.0 * t.phi_deg.to_radians());
    let qm = [[q * p2.cos(), q * p2.sin()], [q * p2.sin(), -q * p2.cos()]];
    (0..n)
        .map(|k| {
            let (r, a) = (
                R * rng.uniform().sqrt(),
                2.0 * std::f64::consts::PI * rng.uniform(),
            );
            let (x, y) = (r * a.cos(), r * a.sin());
            // s·R(θ)·n, then (I + Q).
            let rx = s * (th.cos() * x - th.sin() * y);
            let ry = s * (th.sin() * x + th.cos() * y);
            let mx = rx + qm[0][0] * rx + qm[0][1] * ry;
            let my = ry + qm[1][0] * rx + qm[1][1] * ry;
            let cubic = t.dx_y3_um * 1e-3 * (y / R).powi(3);
            Feature {
                id: format!("{}", k + 1),
                nominal_mm: [x, y],
                measured_mm: [
                    mx + t.offset_um[0] * 1e-3 + cubic + t.noise_um * 1e-3 * rng.normal(),
                    my + t.offset_um[1] * 1e-3 + t.noise_um * 1e-3 * rng.normal(),
                ],
                nominal_d_mm: Some(2.167),
                measured_d_mm: Some(2.170),
            }
        })
        .collect()
}

fn within(p: &Param, truth: f64, k: f64) {
    assert!(
        p.sigma > 0.0 && p.sigma.is_finite(),
        "{}: σ {} not positive",
        p.name,
        p.sigma
    );
    assert!(
        (p.value - truth).abs() <= k * p.sigma,
        "{}: {} ± {} vs truth {truth}",
        p.name,
        p.value,
        p.sigma
    );
}

const BASE: Truth = Truth {
    offset_um: [40.0, -25.0],
    rotation_urad: 150.0,
    scale_ppm: 12.0,
    q_ppm: 0.0,
    phi_deg: 0.0,
    dx_y3_um: 0.0,
    noise_um: 2.0,
};

#[test]
fn plate_similarity_and_shear_recovered_within_sigma() {
    let t = Truth {
        q_ppm: 20.0,
        phi_deg: 30.0,
        ..BASE
    };
    let f = plate(t, 200, 7);
    let o = run(&f, &Options::default()).unwrap();
    let a = o.affine.as_ref().expect("determined");
    within(&a.offset_x_um, t.offset_um[0], 4.0);
    within(&a.offset_y_um, t.offset_um[1], 4.0);
    within(&a.rotation_urad, t.rotation_urad, 4.0);
    within(&a.scale_ppm, t.scale_ppm, 4.0);
    within(&a.quadrupole_ppm, t.q_ppm, 4.0);
    within(
        a.quadrupole_angle_deg.as_ref().expect("q significant"),
        t.phi_deg,
        4.0,
    );
    // The CMM engineer's terms of the same map: e_x − e_y = 2q·cos 2φ, squareness
    // −2q·sin 2φ (to first order), mean scale the similarity's.
    let p2 = 2.0 * t.phi_deg.to_radians();
    within(&a.scale_x_ppm, t.scale_ppm + t.q_ppm * p2.cos(), 4.0);
    within(&a.scale_y_ppm, t.scale_ppm - t.q_ppm * p2.cos(), 4.0);
    within(&a.squareness_urad, -2.0 * t.q_ppm * p2.sin(), 4.0);
    // σ honest: the residual is the noise (2 µm per coordinate: 2.83 radial).
    assert!((a.residual.rms_radial_um - 2.0 * 2f64.sqrt()).abs() < 0.3);
    // The similarity misses it, and the procedure names it.
    assert!(o.similarity.residual.rms_radial_um > 1.5 * a.residual.rms_radial_um);
    assert_eq!(
        o.selection.kept.first().map(String::as_str),
        Some("quadrupole")
    );
    let m = o.missing_effect.as_deref().unwrap();
    assert!(m.contains("anisotropic scale/shear (quadrupole)"), "{m}");
    assert!(!serde_json::to_string(&o).unwrap().contains("NaN"));
}

#[test]
fn plate_similarity_recovered_and_nothing_named_without_shear() {
    let f = plate(BASE, 150, 11);
    let o = run(&f, &Options::default()).unwrap();
    let s = &o.similarity;
    within(&s.offset_x_um, BASE.offset_um[0], 4.0);
    within(&s.offset_y_um, BASE.offset_um[1], 4.0);
    within(&s.rotation_urad, BASE.rotation_urad, 4.0);
    within(&s.scale_ppm, BASE.scale_ppm, 4.0);
    within(
        &s.rotation_deg,
        (BASE.rotation_urad * 1e-6).to_degrees(),
        4.0,
    );
    within(&s.scale, 1.0 + BASE.scale_ppm * 1e-6, 4.0);
    within(&o.affine.as_ref().unwrap().quadrupole_ppm, 0.0, 4.0);
    assert!(o.missing_effect.is_none(), "{:?}", o.missing_effect);
    assert!(o.selection.kept.is_empty());
    // Every candidate was judged, with its CV figure.
    let round2 = &o.selection.rounds[1];
    assert_eq!(round2.candidates.len(), 14);
    assert!(round2.candidates.iter().all(|c| c.cv_rms_um.is_some()));
}

#[test]
fn plate_cubic_distortion_found_beyond_the_linear_map() {
    let t = Truth {
        q_ppm: 15.0,
        phi_deg: -50.0,
        dx_y3_um: 12.0,
        noise_um: 1.0,
        ..BASE
    };
    let f = plate(t, 300, 3);
    let o = run(&f, &Options::default()).unwrap();
    assert_eq!(o.selection.kept[0], "quadrupole");
    assert!(
        o.selection.kept.iter().any(|k| k == "dx_y3"),
        "{:?}",
        o.selection.kept
    );
    let c = o
        .selection
        .terms
        .iter()
        .find(|p| p.name == "dx_y3_um")
        .unwrap();
    within(c, t.dx_y3_um, 4.0);
    within(o.selection.quadrupole_ppm.as_ref().unwrap(), t.q_ppm, 4.0);
    assert!(!o.beyond.is_empty());
    assert!(o.selection.residual.cv_rms_um.unwrap() < 1.7);
}

#[test]
fn plate_collinear_holes_leave_the_shear_undetermined_without_nan() {
    let f: Vec<Feature> = (0..12)
        .map(|k| {
            let u = -200.0 + 40.0 * k as f64;
            Feature {
                id: format!("h{k}"),
                nominal_mm: [u, 0.5 * u],
                measured_mm: [u + 0.01 + 1e-4 * (k as f64).sin(), 0.5 * u - 0.02],
                nominal_d_mm: None,
                measured_d_mm: None,
            }
        })
        .collect();
    let o = run(&f, &Options::default()).unwrap();
    assert!(o.affine.is_none());
    assert!(
        o.undetermined.iter().any(|u| u.contains("collinear")),
        "{:?}",
        o.undetermined
    );
    let q = &o.selection.rounds[0].candidates[0];
    assert!(q.undetermined.is_some() && q.cv_rms_um.is_none());
    assert!(o.original_tool.as_ref().unwrap().qp_magnitude.is_none());
    let js = serde_json::to_string(&o).unwrap();
    assert!(!js.contains("NaN") && !js.contains("inf"), "{js}");
}

#[test]
fn plate_too_few_holes_is_named() {
    let f = plate(BASE, 2, 1);
    let e = run(&f, &Options::default()).unwrap_err().to_string();
    assert!(e.contains("at least 3 holes"), "{e}");
}

/// The port of lmdif against scipy.optimize.leastsq (scipy 1.17) on a synthetic plate:
/// the same coefficients and the same number of function evaluations.
#[test]
fn plate_original_tool_fit_matches_scipy_leastsq() {
    let n = 40;
    let f: Vec<Feature> = (0..n)
        .map(|k| {
            let kf = k as f64;
            let (r, a) = (250.0 * ((kf + 1.0) / n as f64).sqrt(), 2.4 * kf);
            let (x, y) = (r * a.cos(), r * a.sin());
            let qf = 1.0 + 2e-5 * (2.0 * (a - 25f64.to_radians())).cos();
            let (th, s) = (3e-4f64, 1.0 + 1e-5);
            Feature {
                id: format!("{k}"),
                nominal_mm: [x, y],
                measured_mm: [
                    0.05 + s * (th.cos() * x - th.sin() * y) * qf + 0.004 * (7.3 * kf).sin(),
                    -0.03 + s * (th.sin() * x + th.cos() * y) * qf + 0.004 * (5.1 * kf).cos(),
                ],
                nominal_d_mm: None,
                measured_d_mm: None,
            }
        })
        .collect();
    let o = original_tool(&f).unwrap();
    let c = [
        0.05019614720893729,
        -0.029709894346109617,
        0.00030063133891997497,
        1.0000092364059185,
    ];
    // Not bit for bit: the path of lmdif's finite differences on Σ r⁴ is sensitive to
    // the last bits of every function value (numpy's dot, its trigonometry), so the
    // stopping point agrees to ~1e-8 mm and the quadrupole to ~1e-4 of itself.
    assert!((o.fit_offset_mm[0] - c[0]).abs() < 1e-7, "{o:?}");
    assert!((o.fit_offset_mm[1] - c[1]).abs() < 1e-7, "{o:?}");
    assert!((o.fit_scale - c[2].hypot(c[3])).abs() < 1e-9);
    assert!((o.fit_rot_angle_deg - c[2].atan2(c[3]).to_degrees()).abs() < 1e-6);
    assert_eq!(o.lmdif[0].1, 2, "stopped by the step-size test, as scipy's");
    let q = [0.01851502901483146, 0.3749059927358013];
    assert!((o.qp_magnitude.unwrap() / (q[0] * 1e-3) - 1.0).abs() < 1e-3);
    assert!((o.qp_angle_deg.unwrap() - q[1].to_degrees()).abs() < 0.01);
    assert_eq!(o.lmdif[1].1, 1, "stopped by the reduction test, as scipy's");
    // And it is the tool's stopping point, not the least-squares optimum.
    let l2 = run(
        &f,
        &Options {
            original_tool: false,
            ..Options::default()
        },
    )
    .unwrap();
    let d = (l2.similarity.offset_x_um.value * 1e-3 - c[0]).abs();
    assert!(d > 1e-6, "least squares {d} mm from scipy's stopping point");
}
