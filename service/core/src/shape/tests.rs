use super::*;

fn close(a: f64, b: f64, tol: f64) -> bool {
    (a - b).abs() <= tol * (1.0 + b.abs())
}

/// A deterministic pseudo-random sequence in [−1, 1).
fn noise(seed: u64) -> impl FnMut() -> f64 {
    let mut x = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    move || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        (x >> 11) as f64 / (1u64 << 52) as f64 - 1.0
    }
}

fn sphere_points(c: Vec3, r: f64, n: usize, noise_amp: f64) -> Vec<Vec3> {
    let mut rnd = noise(7);
    (0..n)
        .map(|i| {
            // Fibonacci sphere.
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let phi = i as f64 * 2.399_963_229_728_653;
            let rho = (1.0 - z * z).sqrt();
            let dir = Vec3::new(rho * phi.cos(), rho * phi.sin(), z);
            c + dir * (r + noise_amp * rnd())
        })
        .collect()
}

#[test]
fn sphere_exact_and_fixed() {
    let c = Vec3::new(120.5, -40.25, 310.0);
    let pts = sphere_points(c, 12.7, 50, 0.0);
    let f = fit_sphere(&pts).unwrap();
    assert!((f.center - c).norm() < 1e-11, "{:?}", f.center);
    assert!(close(f.radius, 12.7, 1e-13));
    assert!(close(f.diameter, 25.4, 1e-13));
    assert!(f.rms < 1e-11 && f.max_abs_residual() < 1e-11);
    let g = fit_sphere_fixed_radius(&pts, 12.7).unwrap();
    assert!((g.center - c).norm() < 1e-11);
    assert_eq!(g.radius, 12.7);
}

#[test]
fn sphere_cap_with_noise_is_unbiased() {
    // A 60° cap with symmetric noise: the fit stays close to the truth.
    let c = Vec3::new(1.0, 2.0, 3.0);
    let mut rnd = noise(3);
    let pts: Vec<Vec3> = (0..400)
        .map(|i| {
            let z = 1.0 - 0.5 * (i as f64 + 0.5) / 400.0;
            let phi = i as f64 * 2.399_963_229_728_653;
            let rho = (1.0 - z * z).sqrt();
            c + Vec3::new(rho * phi.cos(), rho * phi.sin(), z) * (5.0 + 1e-4 * rnd())
        })
        .collect();
    let f = fit_sphere(&pts).unwrap();
    assert!((f.center - c).norm() < 1e-3, "{:?}", f.center);
    assert!((f.radius - 5.0).abs() < 1e-3);
    assert!(f.rms > 0.0 && f.rms < 1e-4);
    // Residuals are the signed orthogonal distances.
    for (p, e) in pts.iter().zip(&f.residuals) {
        assert!(close((p - f.center).norm() - f.radius, *e, 1e-12));
    }
}

#[test]
fn circle_tilted_exact() {
    let c = Vec3::new(10.0, 20.0, -5.0);
    let n = Vec3::new(1.0, -2.0, 0.5).normalize();
    let a = n.cross(&Vec3::x()).normalize();
    let b = n.cross(&a);
    let pts: Vec<Vec3> = (0..7)
        .map(|i| {
            let t = 0.3 + i as f64 * 0.4;
            c + (a * t.cos() + b * t.sin()) * 25.0
        })
        .collect();
    let f = fit_circle(&pts).unwrap();
    assert!((f.center - c).norm() < 1e-11);
    assert!(close(f.radius, 25.0, 1e-13));
    assert!(f.normal.dot(&n).abs() > 1.0 - 1e-14);
    // Sign convention: largest-magnitude component (−2/…, y) positive.
    assert!(f.normal.y > 0.0);
    assert!(f.plane_rms < 1e-12);
    let g = fit_circle_fixed_radius(&pts, 25.0).unwrap();
    assert!((g.center - c).norm() < 1e-11);
    assert_eq!(g.diameter, 50.0);
}

#[test]
fn circle_three_points_and_signed_residuals() {
    let pts = [
        Vec3::new(1.0, 0.0, 0.0),
        Vec3::new(0.0, 1.0, 0.0),
        Vec3::new(-1.0, 0.0, 0.0),
    ];
    let f = fit_circle(&pts).unwrap();
    assert!(f.center.norm() < 1e-14);
    assert!(close(f.radius, 1.0, 1e-14));
    assert_eq!(f.normal, Vec3::z());
    // Fixed radius larger than the true one, points all round: all fall 0.5 inside.
    let square = [pts[0], pts[1], pts[2], Vec3::new(0.0, -1.0, 0.0)];
    let g = fit_circle_fixed_radius(&square, 1.5).unwrap();
    assert!(g.center.norm() < 1e-14);
    assert!(g.residuals.iter().all(|e| close(*e, -0.5, 1e-14)));
    assert!(close(g.rms, 0.5, 1e-14));
    let h = fit_circle(&square).unwrap();
    assert!(h.residuals.iter().all(|e| e.abs() < 1e-15));
}

#[test]
fn line_fit() {
    let p0 = Vec3::new(1.0, 2.0, 3.0);
    let d = Vec3::new(-0.2, 0.3, -0.9).normalize();
    let off = d.cross(&Vec3::x()).normalize();
    let pts: Vec<Vec3> = (0..11)
        .map(|i| {
            let t = i as f64 - 5.0;
            p0 + d * t + off * if i % 2 == 0 { 0.01 } else { -0.01 }
        })
        .collect();
    let f = fit_line(&pts).unwrap();
    assert!(f.direction.dot(&d).abs() > 1.0 - 1e-6);
    assert!(f.direction.z > 0.0, "largest component positive");
    assert!(close(f.direction.norm(), 1.0, 1e-15));
    assert!(f.residuals.iter().all(|e| *e >= 0.0));
    assert!((f.rms - 0.01).abs() < 1e-4);
    // Two points are enough.
    let two = fit_line(&[Vec3::zeros(), Vec3::new(0.0, 3.0, 4.0)]).unwrap();
    assert!((two.direction - Vec3::new(0.0, 0.6, 0.8)).norm() < 1e-15);
    assert!(two.rms < 1e-15);
}

#[test]
fn plane_fit() {
    let n = Vec3::new(0.1, -0.2, -1.0).normalize();
    let c = Vec3::new(5.0, 6.0, 7.0);
    let a = n.cross(&Vec3::x()).normalize();
    let b = n.cross(&a);
    let pts: Vec<Vec3> = (0..25)
        .map(|i| {
            let (x, y) = ((i % 5) as f64 - 2.0, (i / 5) as f64 - 2.0);
            let h = if (i % 5 + i / 5) % 2 == 0 {
                0.002
            } else {
                -0.002
            };
            c + a * x * 10.0 + b * y * 10.0 + n * h
        })
        .collect();
    let f = fit_plane(&pts).unwrap();
    assert!(f.normal.dot(&n).abs() > 1.0 - 1e-9);
    assert!(f.normal.z > 0.0, "largest component positive");
    assert!((f.centroid - c - n * 0.00008).norm() < 1e-3);
    assert!(f.max_abs_residual() <= 0.0021);
    let sum: f64 = f.residuals.iter().sum();
    assert!(
        sum.abs() < 1e-12,
        "signed residuals sum to 0 about the centroid"
    );
}

#[test]
fn too_few_points() {
    let p = [Vec3::zeros(), Vec3::x(), Vec3::y()];
    assert_eq!(
        fit_sphere(&p).unwrap_err(),
        ShapeError::TooFewPoints {
            kind: ShapeKind::Sphere,
            needed: 4,
            got: 3
        }
    );
    let e = fit_circle(&p[..2]).unwrap_err();
    assert!(e.to_string().contains("at least 3 points, got 2"), "{e}");
    assert!(matches!(
        fit_line(&p[..1]),
        Err(ShapeError::TooFewPoints { needed: 2, .. })
    ));
    assert!(matches!(
        fit_plane(&[]),
        Err(ShapeError::TooFewPoints {
            needed: 3,
            got: 0,
            ..
        })
    ));
}

#[test]
fn degenerate_sets() {
    let line: Vec<Vec3> = (0..6)
        .map(|i| Vec3::new(1.0, 2.0, 3.0) * i as f64)
        .collect();
    let e = fit_circle(&line).unwrap_err();
    assert_eq!(
        e,
        ShapeError::Collinear {
            kind: ShapeKind::Circle
        }
    );
    assert!(e
        .to_string()
        .contains("scan more of the circle's circumference"));
    assert!(matches!(
        fit_plane(&line),
        Err(ShapeError::Collinear { .. })
    ));
    let flat: Vec<Vec3> = (0..8)
        .map(|i| Vec3::new((i as f64).cos(), (i as f64).sin(), 4.0))
        .collect();
    let e = fit_sphere(&flat).unwrap_err();
    assert!(matches!(e, ShapeError::Coplanar { .. }));
    assert!(e.to_string().contains("coplanar"));
    let same = vec![Vec3::new(0.1, 0.2, 0.3); 5];
    for e in [
        fit_circle(&same).unwrap_err(),
        fit_sphere(&same).unwrap_err(),
        fit_line(&same).unwrap_err(),
        fit_plane(&same).unwrap_err(),
    ] {
        assert!(
            matches!(e, ShapeError::AllIdentical { count: 5, .. }),
            "{e}"
        );
    }
    // A nearly straight arc: bulge 1e-9 over a length of 2.
    let arc: Vec<Vec3> = (0..5)
        .map(|i| {
            let x = i as f64 * 0.5 - 1.0;
            Vec3::new(x, 1e-9 * (1.0 - x * x), 0.0)
        })
        .collect();
    assert!(matches!(
        fit_circle(&arc),
        Err(ShapeError::TooFlat { .. } | ShapeError::Collinear { .. })
    ));
    assert!(fit_circle_fixed_radius(&pts_unit_circle(), 0.0).is_err());
    assert!(fit_sphere_fixed_radius(&line, f64::NAN).is_err());
}

fn pts_unit_circle() -> Vec<Vec3> {
    (0..4)
        .map(|i| {
            let t = i as f64;
            Vec3::new(t.cos(), t.sin(), 0.0)
        })
        .collect()
}

#[test]
fn non_finite_points() {
    let mut p = pts_unit_circle();
    p[2].y = f64::NAN;
    let e = fit_circle(&p).unwrap_err();
    assert_eq!(e, ShapeError::NonFinite { index: 2 });
    assert!(e.to_string().starts_with("point 3 "));
    p[2].y = f64::INFINITY;
    assert!(matches!(
        fit_plane(&p),
        Err(ShapeError::NonFinite { index: 2 })
    ));
    assert!(matches!(fit_line(&p), Err(ShapeError::NonFinite { .. })));
    p.push(Vec3::z());
    assert!(matches!(fit_sphere(&p), Err(ShapeError::NonFinite { .. })));
    let huge: Vec<Vec3> = pts_unit_circle().iter().map(|v| v * 1e300).collect();
    assert_eq!(fit_circle(&huge).unwrap_err(), ShapeError::OutOfRange);
}

#[test]
fn parser() {
    let text = "# ring gauge\n3\n1 2 3\n\n4,5,6  # second\n 7 ,\t8, 9\n";
    let p = parse_points(text).unwrap();
    assert_eq!(
        p,
        vec![
            Vec3::new(1.0, 2.0, 3.0),
            Vec3::new(4.0, 5.0, 6.0),
            Vec3::new(7.0, 8.0, 9.0)
        ]
    );
    // No count line.
    assert_eq!(
        parse_points("1e-3 -2 +3.5\r\n").unwrap(),
        vec![Vec3::new(1e-3, -2.0, 3.5)]
    );
    assert!(parse_points("").unwrap().is_empty());
    assert_eq!(
        parse_points("4\n1 2 3\n4 5 6\n").unwrap_err(),
        ShapeError::CountMismatch {
            line: 1,
            declared: 4,
            found: 2
        }
    );
    let e = parse_points("1 2 3\n4 5\n").unwrap_err();
    assert!(matches!(e, ShapeError::Parse { line: 2, .. }), "{e}");
    assert!(
        e.to_string().starts_with("line 2: expected 3 numbers"),
        "{e}"
    );
    let e = parse_points("1 2 3\n4 x 6\n").unwrap_err();
    assert!(e.to_string().contains("line 2: `x` is not a number"), "{e}");
    let e = parse_points("# c\n\n1 2 nan\n").unwrap_err();
    assert!(matches!(e, ShapeError::Parse { line: 3, .. }), "{e}");
    // A count is accepted only on the first data row.
    assert!(matches!(
        parse_points("1 2 3\n5\n"),
        Err(ShapeError::Parse { line: 2, .. })
    ));
    assert!(matches!(
        parse_points("3.5\n1 2 3\n"),
        Err(ShapeError::Parse { line: 1, .. })
    ));
    assert!(parse_points("1 2 3 4\n").is_err());
    // x y rows: a profile in the XY plane; the first row fixes the width.
    assert_eq!(
        parse_points("# profile\n1, 2\n3 4\n").unwrap(),
        vec![Vec3::new(1.0, 2.0, 0.0), Vec3::new(3.0, 4.0, 0.0)]
    );
    let e = parse_points("1 2\n3 4 5\n").unwrap_err();
    assert!(
        e.to_string()
            .starts_with("line 2: expected 2 numbers (x y, as the rows before)"),
        "{e}"
    );
}

#[test]
fn kinds() {
    assert_eq!("Sphere".parse::<ShapeKind>().unwrap(), ShapeKind::Sphere);
    let e = "cone".parse::<ShapeKind>().unwrap_err();
    assert_eq!(
        e.to_string(),
        "unknown shape kind `cone`: expected one of circle, sphere, line, plane"
    );
}

/// A straightedge's scan (points along a nearly straight line with form error) is no circle:
/// refused with the arc it spans, as the Python package refuses it.
#[test]
fn a_straightedge_is_not_a_circle() {
    let pts: Vec<Vec3> = (0..200)
        .map(|i| {
            let x = i as f64 * 2.0;
            Vec3::new(x, 1e-3 * (x / 400.0 * 3.0).sin(), 0.0)
        })
        .collect();
    let e = fit_circle(&pts).unwrap_err();
    assert!(
        matches!(e, ShapeError::ShortArc { .. } | ShapeError::TooFlat { .. }),
        "{e}"
    );
    assert!(e.to_string().contains("straight line"), "{e}");
    // A quarter of a ring still fits.
    let arc: Vec<Vec3> = (0..50)
        .map(|i| {
            let t = i as f64 / 49.0 * std::f64::consts::FRAC_PI_2;
            Vec3::new(25.0 * t.cos(), 25.0 * t.sin(), 0.0)
        })
        .collect();
    assert!((fit_circle(&arc).unwrap().radius - 25.0).abs() < 1e-9);
}
