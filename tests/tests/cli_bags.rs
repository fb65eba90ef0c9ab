//! `scancorr sim` and `scancorr correct` as a user runs them, including bad input.

mod common;
use common::*;
use scancorr_bag::Stream;
use std::path::Path;
use std::process::{Command, Stdio};

fn json(s: &str) -> serde_json::Value {
    serde_json::from_str(s).unwrap_or_else(|e| panic!("not JSON ({e}): {s}"))
}

#[test]
fn campaign_simulates_and_corrects() {
    let d = scratch("campaign");
    let sim = json(&ok(
        &d,
        &[
            "sim",
            "--program",
            "campaign",
            "--seed",
            "1",
            "--out",
            "c.mcap",
            "--truth",
            "t.json",
            "--calib-out",
            "start.json",
            "--json",
        ],
    ));
    let n_scale = sim["samples"]["scale"].as_u64().unwrap();
    assert!(n_scale > 200_000, "{sim}");
    let out = json(&ok(
        &d,
        &[
            "correct",
            "--bag",
            "c.mcap",
            "--calib",
            "start.json",
            "--out",
            "o.mcap",
            "--json",
        ],
    ));
    let total: u64 = ["command", "scale", "probe", "temperature"]
        .iter()
        .map(|k| sim["samples"][k].as_u64().unwrap())
        .sum();
    assert_eq!(out["samples"].as_u64(), Some(total), "{out}");
    let points = out["points"].as_u64().unwrap();
    let dropped: u64 = out["dropped"]
        .as_object()
        .unwrap()
        .values()
        .map(|v| v.as_u64().unwrap())
        .sum();
    // One point per scale sample, or a counted drop.
    assert_eq!(points + dropped, n_scale, "{out}");
    assert!(points as f64 > 0.99 * n_scale as f64, "{out}");
    assert_eq!(
        out["alarms"].as_u64(),
        Some(0),
        "a nominal campaign raises no alarm: {out}"
    );
    let truth = json(&std::fs::read_to_string(d.join("t.json")).unwrap());
    // One effect per library effect the simulated machine has.
    assert_eq!(
        truth["true_calibration"]["effects"]
            .as_array()
            .unwrap()
            .len(),
        scancorr_sim::LIBRARY_EFFECTS.len()
    );
    assert!(truth["features"].as_array().unwrap().len() >= 5);
    // Same seed, same bytes.
    ok(
        &d,
        &[
            "sim",
            "--program",
            "campaign",
            "--seed",
            "1",
            "--out",
            "c2.mcap",
        ],
    );
    assert!(std::fs::read(d.join("c.mcap")).unwrap() == std::fs::read(d.join("c2.mcap")).unwrap());
    // The output bag holds the points.
    let r = scancorr_bag::BagReader::open(d.join("o.mcap")).unwrap();
    let ch = r.channel("m1", Stream::Points).expect("points channel");
    assert_eq!(ch.sample_count, Some(points));
    assert_points_are_the_cores(&d.join("c.mcap"), &d.join("start.json"), &d.join("o.mcap"));
}

/// The corrected bag holds exactly the points the core makes of the input bag, in order, in
/// messages of at most 100 points (the writer thread loses, reorders or repeats none).
fn assert_points_are_the_cores(input: &Path, cal: &Path, out: &Path) {
    use scancorr_core::{wire, Calibration, Corrector, Output};
    let cal = Calibration::from_json(&std::fs::read_to_string(cal).unwrap()).unwrap();
    let mut corr = Corrector::new(&cal).unwrap();
    let (mut output, mut samples, mut want) = (Output::default(), vec![], vec![]);
    for m in scancorr_bag::BagReader::open(input)
        .unwrap()
        .messages()
        .unwrap()
    {
        let m = m.unwrap();
        let Some(stream) = wire::stream_id(m.stream) else {
            continue;
        };
        samples.clear();
        wire::decode_machine(stream, &m.data, "m1", &mut samples).unwrap();
        for x in samples.drain(..) {
            corr.push(x, &mut output);
        }
        want.extend(wire::points(&output.points, "m1", &corr));
        output.clear();
    }
    corr.flush(&mut output);
    want.extend(wire::points(&output.points, "m1", &corr));
    let got = points(out);
    assert_eq!(got.len(), want.len());
    assert!(
        got == want,
        "the corrected bag's points differ from the core's"
    );
    let r = scancorr_bag::BagReader::open(out).unwrap();
    for m in r.messages().unwrap() {
        let m = m.unwrap();
        if m.stream == Stream::Points {
            let n = scancorr_bag::peek(m.stream, &m.data).unwrap().samples;
            assert!((1..=100).contains(&n), "a points message of {n} points");
        }
    }
}

#[test]
fn bad_bags_and_calibrations_are_clear_errors() {
    let d = scratch("bad");
    ok(
        &d,
        &[
            "sim",
            "--program",
            "ring",
            "--out",
            "r.mcap",
            "--calib-out",
            "start.json",
            "--truth",
            "t.json",
        ],
    );
    let full = json(&ok(
        &d,
        &[
            "correct",
            "--bag",
            "r.mcap",
            "--calib",
            "start.json",
            "--json",
        ],
    ));

    // Not a bag.
    std::fs::write(
        d.join("garbage.mcap"),
        b"this is not a bag at all, just text",
    )
    .unwrap();
    fails(
        &d,
        &["correct", "--bag", "garbage.mcap", "--calib", "start.json"],
        &["garbage.mcap"],
    );
    fails(
        &d,
        &["correct", "--bag", "missing.mcap", "--calib", "start.json"],
        &["missing.mcap"],
    );

    // Truncated (cut short mid-write): readable up to the last complete chunk, with a warning.
    let bytes = std::fs::read(d.join("r.mcap")).unwrap();
    std::fs::write(d.join("cut.mcap"), &bytes[..bytes.len() * 6 / 10]).unwrap();
    let o = run(
        &d,
        &[
            "correct",
            "--bag",
            "cut.mcap",
            "--calib",
            "start.json",
            "--json",
        ],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stderr).contains("cut short"));
    let cut = json(&String::from_utf8_lossy(&o.stdout));
    let (pc, pf) = (
        cut["points"].as_u64().unwrap(),
        full["points"].as_u64().unwrap(),
    );
    assert!(pc > 0 && pc < pf, "{pc} of {pf}");
    // Cut inside the header: a clear error.
    std::fs::write(d.join("stub.mcap"), &bytes[..10]).unwrap();
    fails(
        &d,
        &["correct", "--bag", "stub.mcap", "--calib", "start.json"],
        &["stub.mcap"],
    );

    // Calibration for another machine.
    let cal = std::fs::read_to_string(d.join("start.json")).unwrap();
    std::fs::write(
        d.join("m2.json"),
        cal.replace("\"machine_id\": \"m1\"", "\"machine_id\": \"m2\""),
    )
    .unwrap();
    fails(
        &d,
        &["correct", "--bag", "r.mcap", "--calib", "m2.json"],
        &["m2", "m1"],
    );
    // Invalid calibration: names the field.
    std::fs::write(
        d.join("bad.json"),
        cal.replace("\"sample_period_s\": 0.001", "\"sample_period_s\": -1"),
    )
    .unwrap();
    fails(
        &d,
        &["correct", "--bag", "r.mcap", "--calib", "bad.json"],
        &["sample_period_s"],
    );
    std::fs::write(
        d.join("typo.json"),
        cal.replacen("\"note\"", "\"note_typo\"", 1),
    )
    .unwrap();
    fails(
        &d,
        &["correct", "--bag", "r.mcap", "--calib", "typo.json"],
        &["note_typo"],
    );

    // A bag missing the probe channel, with an unknown channel.
    copy_bag(&d.join("r.mcap"), &d.join("noprobe.mcap"), |s| {
        s != Stream::Probe
    });
    fails(
        &d,
        &["correct", "--bag", "noprobe.mcap", "--calib", "start.json"],
        &["cmm/m1/raw/probe"],
    );
}

#[test]
fn a_bag_cut_short_by_a_killed_simulator_is_still_readable() {
    let d = scratch("killed");
    sim_ring(&d, "start.json");
    let mut child = Command::new(scancorr())
        .args([
            "sim",
            "--program",
            "ring-speeds",
            "--minutes",
            "30",
            "--out",
            "long.mcap",
        ])
        .current_dir(&d)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    // Wait until several chunks are on disk, then kill it mid-write.
    let t0 = std::time::Instant::now();
    while std::fs::metadata(d.join("long.mcap"))
        .map(|m| m.len())
        .unwrap_or(0)
        < 4_000_000
    {
        assert!(
            t0.elapsed().as_secs() < 120,
            "the simulator wrote too little"
        );
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    let o = run(
        &d,
        &[
            "correct",
            "--bag",
            "long.mcap",
            "--calib",
            "start.json",
            "--json",
        ],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let s = json(&String::from_utf8_lossy(&o.stdout));
    assert!(s["points"].as_u64().unwrap() > 10_000, "{s}");
}

#[test]
fn correct_names_an_effect_that_never_acts() {
    let d = scratch("inactive-effect");
    sim_ring(&d, "c.json");
    // A custom effect whose signal never occurs in this run (speeds above 5 m/s).
    let mut cal = json(&std::fs::read_to_string(d.join("c.json")).unwrap());
    cal["effects"]
        .as_array_mut()
        .unwrap()
        .push(serde_json::json!({
            "kind": "custom", "id": "overspeed",
            "terms": [{"axis": "x", "expr": "max(0, speed - 5000)"}],
            "coefficients": [1e-3]
        }));
    std::fs::write(d.join("c2.json"), cal.to_string()).unwrap();
    let o = run(
        &d,
        &["correct", "--bag", "r.mcap", "--calib", "c2.json", "--json"],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let s = json(&String::from_utf8_lossy(&o.stdout));
    assert_eq!(
        s["inactive_effects"],
        serde_json::json!(["overspeed"]),
        "{s}"
    );
    assert_eq!(s["effect_points"]["overspeed"], 0, "{s}");
    assert!(s["points"].as_u64().unwrap() > 1000);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("effect `overspeed`") && err.contains("inactive"),
        "{err}"
    );
}
