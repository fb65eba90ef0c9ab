//! `scancorr shape fit` against the NIST least-squares circle reference pairs.

mod common;
use common::*;

fn nums(text: &str) -> Vec<f64> {
    text.split_whitespace()
        .map(|t| t.parse::<f64>().unwrap())
        .collect()
}

#[test]
fn circle_fits_match_nist_reference_results() {
    let dir = root()
        .parent()
        .unwrap()
        .join("shared/reference/nist-l2-circle2d");
    assert!(dir.is_dir(), "reference data missing: {}", dir.display());
    let mut n = 0;
    for k in 1..=30 {
        let ds = dir.join(format!("cir2d{k}.ds"));
        let fit = nums(&std::fs::read_to_string(dir.join(format!("cir2d{k}.fit"))).unwrap());
        let out = ok(
            &root(),
            &[
                "shape",
                "fit",
                "--kind",
                "circle",
                "--points",
                ds.to_str().unwrap(),
                "--json",
            ],
        );
        let v: serde_json::Value = serde_json::from_str(&out).unwrap();
        let d = v["diameter"].as_f64().unwrap();
        let c: Vec<f64> = v["center"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect();
        let nrm: Vec<f64> = v["normal"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect();
        assert!(
            ((d - fit[6]) / fit[6]).abs() < 1e-10,
            "cir2d{k}: diameter {d} vs {}",
            fit[6]
        );
        for i in 0..3 {
            assert!(
                (c[i] - fit[i]).abs() < 1e-10 * fit[6],
                "cir2d{k}: centre {c:?} vs {:?}",
                &fit[..3]
            );
        }
        let dot: f64 = (0..3).map(|i| nrm[i] * fit[3 + i]).sum();
        assert!(dot.abs() > 1.0 - 1e-12, "cir2d{k}: normal {nrm:?}");
        n += 1;
    }
    assert_eq!(n, 30);
    // Bad input is a clear error.
    let d = scratch("shape");
    std::fs::write(d.join("two.txt"), "2\n0 0 0\n1 0 0\n").unwrap();
    fails(
        &d,
        &["shape", "fit", "--kind", "circle", "--points", "two.txt"],
        &["3"],
    );
    std::fs::write(d.join("line.txt"), "0 0 0\n1 0 0\n2 0 0\n3 0 0\n").unwrap();
    fails(
        &d,
        &["shape", "fit", "--kind", "circle", "--points", "line.txt"],
        &["collinear"],
    );
    fails(
        &d,
        &["shape", "fit", "--kind", "cube", "--points", "line.txt"],
        &["circle"],
    );
    let pl = json_ok(
        &d,
        &[
            "shape", "fit", "--kind", "line", "--points", "line.txt", "--json",
        ],
    );
    assert!((pl["normal"][0].as_f64().unwrap().abs() - 1.0).abs() < 1e-12);
}

fn json_ok(d: &std::path::Path, a: &[&str]) -> serde_json::Value {
    serde_json::from_str(&ok(d, a)).unwrap()
}
