//! `scancorr export`: a corrected bag's points as CSV (every point, the per-effect breakdown)
//! and as `x y z` rows; the rows re-read by `scancorr shape fit` give the diameter the lab
//! reports for the same scan; `shape fit` reads `x y` rows from standard input and prints the
//! roundness; a bag without corrected points, a segment that is not there and an output over
//! the input are refused with a message and nothing written.

mod common;
use common::*;
use std::io::Write;
use std::process::{Command, Stdio};

fn json(s: &str) -> serde_json::Value {
    serde_json::from_str(s).unwrap_or_else(|e| panic!("not JSON ({e}): {s}"))
}

#[test]
fn exported_points_refit_to_the_labs_diameter() {
    let dir = scratch("cli-export");
    ok(
        &dir,
        &[
            "sim",
            "--program",
            "campaign",
            "--seed",
            "3",
            "--out",
            "c.mcap",
            "--calib-out",
            "cal.json",
        ],
    );
    ok(
        &dir,
        &[
            "correct", "--bag", "c.mcap", "--calib", "cal.json", "--out", "o.mcap",
        ],
    );
    // The lab's traces: the slow counter-clockwise scan of the first ring, its segment and
    // the diameter of the least-squares circle through its points.
    let cmp = json(&ok(
        &dir,
        &[
            "lab", "compare", "--bag", "c.mcap", "--calib", "cal.json", "--json",
        ],
    ));
    let trace = cmp["traces"]
        .as_array()
        .unwrap()
        .iter()
        .find(|t| {
            t["artifact"] == "ring"
                && t["direction"] == 1
                && t["segments"].as_array().unwrap().len() == 1
        })
        .expect("a ring scanned in one segment");
    let seg = trace["segments"][0].as_u64().unwrap().to_string();
    let lab_d = trace["diameter_fit_mm"].as_f64().unwrap();

    // x y z rows of that segment, re-read by shape fit.
    ok(
        &dir,
        &[
            "export",
            "--bag",
            "o.mcap",
            "--format",
            "xyz",
            "--segment",
            &seg,
            "--out",
            "s.xyz",
        ],
    );
    let xyz = std::fs::read_to_string(dir.join("s.xyz")).unwrap();
    assert!(xyz.starts_with("# scancorr export"), "{}", &xyz[..200]);
    let fit = json(&ok(
        &dir,
        &[
            "shape", "fit", "--kind", "circle", "--points", "s.xyz", "--json",
        ],
    ));
    let d = fit["diameter"].as_f64().unwrap();
    eprintln!("segment {seg}: exported and refitted Ø{d:.6} mm, the lab's trace Ø{lab_d:.6} mm");
    assert!((d - lab_d).abs() < 0.05e-3, "{d} vs {lab_d}");
    assert!(fit["roundness"].as_f64().unwrap() > 0.0);

    // The same rows as x y on standard input: the same diameter, and the roundness printed.
    let xy: String = xyz
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| {
            let v: Vec<&str> = l.split_whitespace().collect();
            format!("{} {}\n", v[0], v[1])
        })
        .collect();
    let mut child = Command::new(scancorr())
        .current_dir(&dir)
        .args(["shape", "fit", "--kind", "circle", "--points", "-"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    child
        .stdin
        .take()
        .unwrap()
        .write_all(xy.as_bytes())
        .unwrap();
    let out = child.wait_with_output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        text.contains("standard input") && text.contains("roundness"),
        "{text}"
    );
    let d2: f64 = text
        .lines()
        .find(|l| l.trim_start().starts_with("diameter"))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("{text}"));
    assert!((d2 - d).abs() < 1e-5, "{d2} vs {d}");

    // CSV: a row per corrected point of the segment, the per-effect breakdown in columns.
    ok(
        &dir,
        &[
            "export",
            "--bag",
            "o.mcap",
            "--segment",
            &seg,
            "--out",
            "s.csv",
        ],
    );
    let csv = std::fs::read_to_string(dir.join("s.csv")).unwrap();
    let mut lines = csv.lines();
    let head: Vec<&str> = lines.next().unwrap().split(',').collect();
    let cal = json(&std::fs::read_to_string(dir.join("cal.json")).unwrap());
    for e in cal["effects"].as_array().unwrap() {
        let name = e["id"].as_str().or(e["kind"].as_str()).unwrap();
        assert!(
            head.contains(&format!("{name}_dx_mm").as_str()),
            "{name}: {head:?}"
        );
    }
    let col = |n: &str| head.iter().position(|h| *h == n).unwrap();
    let want: Vec<_> = points(&dir.join("o.mcap"))
        .into_iter()
        .filter(|p| p.segment_id.to_string() == seg)
        .collect();
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), want.len());
    for (r, p) in rows.iter().zip(&want) {
        assert_eq!(r.len(), head.len());
        assert_eq!(r[col("seq")], p.seq.to_string());
        let s = p.surface.as_ref().unwrap();
        let x: f64 = r[col("surface_x_mm")].parse().unwrap();
        assert_eq!(x, s.x, "the value, to the last bit");
        assert_eq!(r[col("calibration_version")], "1");
    }

    // Refusals: nothing written, the input intact.
    let before = std::fs::read(dir.join("o.mcap")).unwrap();
    fails(
        &dir,
        &["export", "--bag", "c.mcap", "--out", "raw.csv"],
        &["no corrected points", "scancorr correct"],
    );
    fails(
        &dir,
        &[
            "export",
            "--bag",
            "o.mcap",
            "--segment",
            "9999",
            "--out",
            "x.csv",
        ],
        &["--segment 9999", "segments: 1–"],
    );
    fails(
        &dir,
        &["export", "--bag", "o.mcap", "--out", "o.mcap"],
        &["same file"],
    );
    fails(
        &dir,
        &[
            "export", "--bag", "o.mcap", "--format", "tsv", "--out", "x.csv",
        ],
        &["--format `tsv`"],
    );
    assert_eq!(std::fs::read(dir.join("o.mcap")).unwrap(), before);
    for f in ["raw.csv", "x.csv"] {
        assert!(!dir.join(f).exists(), "{f} written");
    }
}
