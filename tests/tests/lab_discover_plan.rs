//! `lab discover` closes the confounding itself (issue 45, item 5): when the loop stops with a
//! confounded pair or parameters the campaign cannot determine, it writes the plan that
//! separates them (`--out-dir/plan.json`, made by the lab's planner as `lab plan` makes it);
//! the simulator runs it (`sim --program plan.json`), and `lab discover --bag campaign --bag
//! plan` takes the simulator's physics, `accel_deflection`, not the `servo_gain` it does not
//! have, and no longer names the pair confounded once their scores separate them.
//!
//! The start is a calibration the lab fitted (`lab fit` on the campaign, every parameter from
//! zero) with every library effect but `accel_deflection`; the truth only judges. Machine
//! seed 137, run seeds 1 and 2 (no other test uses them). Every 64th point of a scan, the
//! first loop stopped after its diagnosis (`--max-steps 0`: it only has to write the plan) and
//! the second limited to one move keep it short.

mod common;
use common::*;

fn json(s: &str) -> serde_json::Value {
    assert!(!s.contains("NaN"), "NaN in output: {s}");
    serde_json::from_str(s).unwrap_or_else(|e| panic!("not JSON ({e}): {s}"))
}

const STRIDE: &str = "64";

fn discover(dir: &std::path::Path, bags: &[&str], out: &str, steps: &str) -> serde_json::Value {
    let mut a = vec!["lab", "discover"];
    for b in bags {
        a.extend(["--bag", b]);
    }
    a.extend([
        "--calib",
        "fitted.json",
        "--out-dir",
        out,
        "--stride",
        STRIDE,
        "--max-steps",
        steps,
        "--plan-minutes",
        "5",
        "--json",
    ]);
    json(&ok(dir, &a))
}

fn kinds(d: &serde_json::Value) -> Vec<String> {
    d["final"]["kinds"]
        .as_array()
        .unwrap()
        .iter()
        .map(|k| k.as_str().unwrap().to_string())
        .collect()
}

/// Whether `a` and `b` (kinds) are named in one of `d[key]`'s pairs.
fn paired(d: &serde_json::Value, key: &str, a: &str, b: &str) -> bool {
    d[key].as_array().is_some_and(|v| {
        v.iter().any(|c| {
            let k: Vec<&str> = c["effects"]
                .as_array()
                .unwrap()
                .iter()
                .map(|e| e.as_str().unwrap().split(':').next().unwrap())
                .collect();
            k.contains(&a) && k.contains(&b)
        })
    })
}

#[test]
fn discover_writes_the_plan_that_separates_and_chooses_on_its_bag() {
    let t0 = std::time::Instant::now();
    let d = scratch("discover-plan");
    let mut a = vec![
        "sim",
        "--program",
        "campaign",
        "--machine-seed",
        "137",
        "--seed",
        "1",
        "--hide",
        "accel_deflection",
        "--out",
        "c.mcap",
        "--calib-out",
        "listed.json",
        "--truth",
        "truth.json",
    ];
    a.extend(BUYERS_DOCUMENTS);
    ok(&d, &a);
    // The user's start: the other library effects (kinds only), fitted by the lab.
    fitted_start(&d, "listed.json", "datasheet.json", "c.mcap", "fitted.json");
    let truth = json(&std::fs::read_to_string(d.join("truth.json")).unwrap());
    assert!(truth["effects"]["accel_deflection"].as_f64().unwrap() > 0.0);
    assert!(
        truth["effects"]
            .get("servo_gain")
            .and_then(|v| v.as_f64())
            .unwrap_or(0.0)
            == 0.0,
        "the simulator has no servo gain: {}",
        truth["effects"]
    );
    // The campaign alone: the loop stops (here at its step limit) with parameters not
    // determined and writes the plan.
    let d1 = discover(&d, &["c.mcap"], "s1", "0");
    let plan = &d1["plan"];
    assert!(
        !plan["left"].as_array().unwrap().is_empty(),
        "what the plan is for: {plan:#}"
    );
    let file = plan["file"].as_str().unwrap_or_else(|| panic!("{plan:#}"));
    assert!(file.ends_with("plan.json"), "{file}");
    let candidates: Vec<&str> = plan["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c.as_str().unwrap())
        .collect();
    assert!(
        candidates.iter().any(|c| c.starts_with("servo_gain")),
        "the plan makes servo_gain identifiable: {candidates:?}"
    );
    let m = plan["minutes"].as_f64().unwrap();
    assert!(m > 0.0 && m <= 5.0, "{m} min");
    assert_eq!(
        plan["undetermined_before"].as_u64(),
        Some(d1["unidentifiable"].as_array().unwrap().len() as u64)
    );
    // The simulator runs the plan the loop wrote.
    ok(
        &d,
        &[
            "sim",
            "--program",
            "s1/plan.json",
            "--machine-seed",
            "137",
            "--seed",
            "2",
            "--out",
            "p.mcap",
        ],
    );
    // The campaign with the plan's bag: the simulator's physics is taken, not servo_gain, and
    // the pair is not named confounded when the scores separate them.
    let d2 = discover(&d, &["c.mcap", "p.mcap"], "s2", "1");
    let k2 = kinds(&d2);
    // Parameters not determined, for the record (at stride 64: 11 → 16 at machine 137, the
    // second model having the deflection matrix; the plan's design does not determine every
    // table value the campaign leaves).
    let (u1, u2) = (
        d1["unidentifiable"].as_array().unwrap().len(),
        d2["unidentifiable"].as_array().unwrap().len(),
    );
    eprintln!(
        "campaign alone: {:?}, confounded {}, separated {}; with the plan: {k2:?}, confounded {}, separated {}; not determined {u1} → {u2}",
        kinds(&d1),
        d1["confounded"],
        d1["separated"],
        d2["confounded"],
        d2["separated"]
    );
    assert!(k2.iter().any(|k| k == "accel_deflection"), "{d2:#}");
    assert!(!k2.iter().any(|k| k == "servo_gain"), "{d2:#}");
    let first = d2["steps"][1]["effect"].as_str().unwrap_or("");
    assert!(first.starts_with("accel_deflection"), "{d2:#}");
    if paired(&d2, "confounded", "accel_deflection", "servo_gain") {
        // Still confounded: only if their scores are alike (the separation is then not the
        // data's) — never with one scoring far better.
        assert!(!paired(&d2, "separated", "accel_deflection", "servo_gain"));
    } else {
        assert!(
            paired(&d2, "separated", "accel_deflection", "servo_gain"),
            "the pair is either confounded or separated by scores: {d2:#}"
        );
        let s = d2["separated"]
            .as_array()
            .unwrap()
            .iter()
            .find(|c| c["effects"][0].as_str().unwrap().starts_with("accel"))
            .unwrap();
        let cv: Vec<f64> = s["cv_rms_um"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        assert!(cv[0] < cv[1], "accel_deflection scores better: {s:#}");
    }
    eprintln!(
        "lab_discover_plan: held-out {:.3} µm (floor {:.3}) with the plan in {:.1} s",
        d2["final"]["heldout_rms_um"].as_f64().unwrap(),
        d2["final"]["noise_floor_um"].as_f64().unwrap(),
        t0.elapsed().as_secs_f64()
    );
}
