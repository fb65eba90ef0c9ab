//! The circle fit against the NIST reference results for least-squares circles in 3D
//! (`shared/reference/nist-l2-circle2d`): 30 data sets `cir2dN.ds` (point count, then
//! `x y z` rows; the points lie in a plane parallel to a coordinate plane) with their
//! reference fits `cir2dN.fit` (centre x y z, direction cosines of the plane normal,
//! diameter). Full circles, partial arcs and sets of only 3–5 points.
//!
//! Tolerances: diameter to 1e-10 relative, centre to 1e-10 × diameter, normal parallel to
//! |cos| > 1 − 1e-12 (its sign is a convention). The fixed-radius fit with the reference
//! radius must find the reference centre to the same tolerance. The reference folder must exist: a missing
//! folder fails the test rather than skipping it.

use scancorr_core::shape::{fit_circle, fit_circle_fixed_radius, parse_points};
use scancorr_core::Vec3;
use std::path::PathBuf;

const EXPECTED_SETS: usize = 30;

fn reference_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/reference/nist-l2-circle2d")
}

/// Reads a `.fit` file: 7 numbers (centre, normal direction cosines, diameter).
fn read_fit(path: &std::path::Path) -> (Vec3, Vec3, f64) {
    let text = std::fs::read_to_string(path)
        .unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()));
    let v: Vec<f64> = text
        .split_whitespace()
        .map(|t| {
            t.parse::<f64>()
                .unwrap_or_else(|_| panic!("{}: `{t}` is not a number", path.display()))
        })
        .collect();
    assert_eq!(v.len(), 7, "{}: expected 7 numbers", path.display());
    (
        Vec3::new(v[0], v[1], v[2]),
        Vec3::new(v[3], v[4], v[5]),
        v[6],
    )
}

#[test]
fn nist_circles_match_reference() {
    let dir = reference_dir();
    let entries = std::fs::read_dir(&dir).unwrap_or_else(|e| {
        panic!(
            "the NIST reference folder {} is missing or unreadable ({e}); it is required",
            dir.display()
        )
    });
    let mut sets: Vec<PathBuf> = entries
        .map(|e| e.expect("directory entry").path())
        .filter(|p| p.extension().is_some_and(|x| x == "ds"))
        .collect();
    sets.sort();
    let mut checked = 0;
    let (mut worst_d, mut worst_c, mut worst_n) = (0.0f64, 0.0f64, 0.0f64);
    let mut worst_fixed = 0.0f64;
    let mut failures = Vec::new();
    for ds in &sets {
        let name = ds.file_stem().unwrap().to_string_lossy().into_owned();
        let fit_path = ds.with_extension("fit");
        assert!(
            fit_path.exists(),
            "{name}: no reference {}",
            fit_path.display()
        );
        let text = std::fs::read_to_string(ds)
            .unwrap_or_else(|e| panic!("cannot read {}: {e}", ds.display()));
        let points = parse_points(&text).unwrap_or_else(|e| panic!("{name}: {e}"));
        let (center, normal, diameter) = read_fit(&fit_path);
        let f = fit_circle(&points).unwrap_or_else(|e| panic!("{name}: {e}"));
        let d_err = (f.diameter - diameter).abs() / diameter;
        let c_err = (f.center - center).norm() / diameter;
        let n_err = 1.0 - f.normal.dot(&normal.normalize()).abs();
        println!(
            "{name:>8}: {:>4} points, {:>3} iterations, diameter rel err {d_err:.2e}, \
             centre err/diameter {c_err:.2e}, 1-|cos| {n_err:.1e}",
            points.len(),
            f.iterations
        );
        // With the radius fixed at the reference value the centre is the same point (the
        // free optimum is stationary in the centre for that radius).
        let g = fit_circle_fixed_radius(&points, diameter / 2.0)
            .unwrap_or_else(|e| panic!("{name} (fixed radius): {e}"));
        let g_err = (g.center - center).norm() / diameter;
        if g_err > 1e-10 {
            failures.push(format!(
                "{name}: fixed-radius centre {:?} vs {:?} (err/diameter {g_err:.2e})",
                g.center.as_slice(),
                center.as_slice()
            ));
        }
        worst_fixed = worst_fixed.max(g_err);
        worst_d = worst_d.max(d_err);
        worst_c = worst_c.max(c_err);
        worst_n = worst_n.max(n_err);
        if !(d_err <= 1e-10 && c_err <= 1e-10 && n_err < 1e-12) {
            failures.push(format!(
                "{name}: diameter {} vs {diameter} (rel {d_err:.2e}), centre {:?} vs {:?} \
                 (err/diameter {c_err:.2e}), normal {:?} vs {:?}",
                f.diameter,
                f.center.as_slice(),
                center.as_slice(),
                f.normal.as_slice(),
                normal.as_slice()
            ));
        }
        checked += 1;
    }
    println!(
        "{checked} sets; worst: diameter rel {worst_d:.2e}, centre/diameter {worst_c:.2e}, \
         1-|cos| {worst_n:.1e}, fixed-radius centre/diameter {worst_fixed:.2e}"
    );
    assert!(failures.is_empty(), "mismatches:\n{}", failures.join("\n"));
    assert_eq!(
        checked,
        EXPECTED_SETS,
        "expected {EXPECTED_SETS} NIST data sets in {}",
        dir.display()
    );
}
