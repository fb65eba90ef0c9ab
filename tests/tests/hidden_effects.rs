//! The hidden-effect suite: for each effect, simulate the calibration campaign with that
//! effect hidden from the starting calibration, let the lab diagnose it, add it, and check the
//! error on held-out data (a `ring-speeds` run of the same machine at a position the campaign
//! did not use, another seed) falls.

mod common;
use common::*;
use std::path::Path;

fn json(s: &str) -> serde_json::Value {
    serde_json::from_str(s).unwrap_or_else(|e| panic!("not JSON ({e}): {s}"))
}

struct Case {
    /// Removed when the test passes (kept when it fails).
    dir: Scratch,
}

impl Case {
    /// Campaign with `hide` hidden (or extra effects switched on), held-out ring-speeds run.
    fn new(name: &str, hide: &[&str], with: &[&str]) -> Case {
        let dir = scratch(&format!("hidden-{name}"));
        let mut args: Vec<String> = [
            "sim",
            "--program",
            "campaign",
            "--seed",
            "1",
            "--out",
            "c.mcap",
            "--calib-out",
            "sim.json",
            "--datasheet-out",
            "ds.json",
            "--truth",
            "t.json",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        let mut extra = vec![];
        for h in hide {
            extra.extend(["--hide".to_string(), h.to_string()]);
        }
        for w in with {
            extra.extend(["--with".to_string(), w.to_string()]);
        }
        args.extend(extra.iter().cloned());
        ok(&dir, &args.iter().map(|s| s.as_str()).collect::<Vec<_>>());
        let mut v: Vec<String> = [
            "sim",
            "--program",
            "ring-speeds",
            "--seed",
            "2",
            "--position",
            "550,300,-250",
            "--out",
            "v.mcap",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        for w in with {
            v.extend(["--with".to_string(), w.to_string()]);
        }
        ok(&dir, &v.iter().map(|s| s.as_str()).collect::<Vec<_>>());
        // The user's start: nominal with the other effects' list, fitted on the campaign.
        fitted_start(&dir, "sim.json", "ds.json", "c.mcap", "start.json");
        Case { dir }
    }
    fn lab(&self, args: &[&str]) -> serde_json::Value {
        let mut a = vec!["lab"];
        a.extend_from_slice(args);
        a.extend_from_slice(&["--bag", "c.mcap", "--validate", "v.mcap", "--json"]);
        json(&ok(&self.dir, &a))
    }
    fn noise(&self) -> f64 {
        let t = json(&std::fs::read_to_string(self.dir.join("t.json")).unwrap());
        t["noise_floor_um"].as_f64().unwrap()
    }
    fn path(&self, f: &str) -> String {
        self.dir.join(f).display().to_string()
    }
}

fn kind(effect: &str) -> &str {
    effect.split(':').next().unwrap()
}

/// The lab finds `hidden` (first, or confounded with another), adding it takes ≥ 80 % of what it
/// adds above the noise floor (in quadrature) off the held-out error, to within 1.5 × the
/// floor; adding a wrong effect does not.
fn library_case(hidden: &str, wrong: &str) {
    let c = Case::new(hidden, &[hidden], &[]);
    let d = c.lab(&["diagnose", "--calib", "start.json"]);
    let cands = d["candidates"].as_array().unwrap();
    let first = cands[0]["effect"].as_str().unwrap();
    let confounded: Vec<(String, String)> = d["confounded"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| {
            (
                x["effects"][0].as_str().unwrap().to_string(),
                x["effects"][1].as_str().unwrap().to_string(),
            )
        })
        .collect();
    eprintln!("{hidden}: first {first}, confounded {confounded:?}");
    let found = kind(first) == hidden
        || confounded
            .iter()
            .any(|(a, b)| kind(a) == hidden || kind(b) == hidden);
    assert!(found, "{hidden} hidden, diagnosis: {d:#}");
    assert!(cands[0]["significant"].as_bool().unwrap(), "{d:#}");
    for x in d["confounded"].as_array().unwrap() {
        assert!(!x["separate_by"].as_array().unwrap().is_empty());
    }
    let noise = c.noise();
    let add = c.lab(&[
        "add",
        hidden,
        "--calib",
        "start.json",
        "--out",
        &c.path("next.json"),
    ]);
    let (before, after) = (
        add["heldout_rms_before_um"].as_f64().unwrap(),
        add["heldout_rms_after_um"].as_f64().unwrap(),
    );
    eprintln!("{hidden}: held-out {before:.3} → {after:.3} µm (noise floor {noise:.3})");
    // What the hidden effect adds above the noise (in quadrature) falls by ≥ 80 %.
    let excess = |rms: f64| (rms * rms - noise * noise).max(0.0).sqrt();
    assert!(
        excess(after) <= 0.2 * excess(before),
        "{hidden}: {before} → {after} (noise {noise})"
    );
    assert!(
        after <= 1.5 * noise,
        "{hidden}: {after} µm vs noise floor {noise}"
    );
    // The new version names its parent.
    let next = json(&std::fs::read_to_string(c.dir.join("next.json")).unwrap());
    let from = json(&std::fs::read_to_string(c.dir.join("start.json")).unwrap())["version"]
        .as_u64()
        .unwrap();
    assert_eq!(next["parent_version"], from);
    assert_eq!(next["version"], from + 1);
    // A wrong effect does not pass the held-out check.
    let mut start = json(&std::fs::read_to_string(c.dir.join("start.json")).unwrap());
    // (remove the wrong effect from the start so it can be added)
    let effects = start["effects"].as_array_mut().unwrap();
    effects.retain(|e| e["kind"] != kind(wrong));
    std::fs::write(c.dir.join("start_wrong.json"), start.to_string()).unwrap();
    let w = c.lab(&[
        "add",
        wrong,
        "--calib",
        "start_wrong.json",
        "--out",
        &c.path("wrong.json"),
        // The wrong effect alone: refitting the others would let them absorb the hidden one.
        "--only-new",
    ]);
    let wa = w["heldout_rms_after_um"].as_f64().unwrap();
    eprintln!("{hidden}: wrong effect {wrong}: held-out → {wa:.3} µm");
    assert!(
        !(excess(wa) <= 0.2 * excess(before) && wa <= 1.5 * noise),
        "adding {wrong} for hidden {hidden} passed the held-out check"
    );
}

#[test]
fn hidden_accel_deflection() {
    library_case("accel_deflection", "probe_force");
}
#[test]
fn hidden_servo_phase() {
    library_case("servo_phase", "scale_thermal");
}
/// The simulated machine has no arc gain of its own: what its arcs show is a compliance (the
/// structure's and the probe mount's), so there is nothing to hide as `servo_gain`, and the
/// simulator says where that physics is.
#[test]
fn the_arc_gain_is_a_compliance_not_an_effect_to_hide() {
    let dir = scratch("no-gain");
    for flag in ["--hide", "--effect"] {
        let arg = if flag == "--hide" {
            "servo_gain"
        } else {
            "servo_gain=2"
        };
        fails(
            &dir,
            &["sim", "--program", "ring", "--out", "r.mcap", flag, arg],
            &["no arc gain of its own", "accel_deflection"],
        );
        assert!(!dir.join("r.mcap").exists(), "nothing written on refusal");
    }
}
#[test]
fn hidden_stylus_thermal() {
    library_case("stylus_thermal", "servo_phase");
}
#[test]
fn hidden_scale_thermal() {
    library_case("scale_thermal", "servo_phase");
}
#[test]
fn hidden_probe_force() {
    library_case("probe_force", "servo_phase");
}
#[test]
fn hidden_guide_straightness() {
    library_case("guide_straightness", "probe_force");
}

#[test]
fn nothing_hidden_reports_no_significant_candidate() {
    let c = Case::new("none", &[], &[]);
    // Everything is in the model: candidates are other variants only when refitting; diagnose
    // a model without two effects' *structure* mismatch — here, the full true model.
    let d = c.lab(&["diagnose", "--calib", "start.json"]);
    let sig: Vec<&serde_json::Value> = d["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|x| x["significant"].as_bool().unwrap())
        .collect();
    assert!(sig.is_empty(), "{sig:#?}");
    assert!(d["unexplained"].as_array().unwrap().is_empty(), "{d:#}");
}

/// Outside the library: the lab reports the structure, a custom effect from it fixes it.
fn outside_case(effect: &str, check: impl Fn(&serde_json::Value) -> bool) {
    let c = Case::new(effect, &[], &[effect]);
    let d = c.lab(&["diagnose", "--calib", "start.json"]);
    let un = d["unexplained"].as_array().unwrap();
    assert!(
        !un.is_empty(),
        "{effect}: no unexplained structure reported: {d:#}"
    );
    eprintln!("{effect}: unexplained {:#}", un[0]);
    assert!(check(&un[0]), "{effect}: {:#}", un[0]);
    // The command `lab diagnose` prints for it runs as printed.
    let text = ok(
        &c.dir,
        &[
            "lab",
            "diagnose",
            "--calib",
            "start.json",
            "--bag",
            "c.mcap",
            "--validate",
            "v.mcap",
        ],
    );
    let line = text
        .lines()
        .map(str::trim)
        .find(|l| l.starts_with("scancorr lab add custom"))
        .unwrap_or_else(|| panic!("{effect}: no command offered:\n{text}"));
    let cmd = format!(
        "{}{} --json",
        common::scancorr().display(),
        line.strip_prefix("scancorr").unwrap()
    );
    let out = std::process::Command::new("sh")
        .args(["-c", &cmd])
        .current_dir(&c.dir)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{cmd}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let a = json(&String::from_utf8_lossy(&out.stdout));
    let (before, after) = (
        a["heldout_rms_before_um"].as_f64().unwrap(),
        a["heldout_rms_after_um"].as_f64().unwrap(),
    );
    let noise = c.noise();
    eprintln!("{effect}: custom effect: held-out {before:.3} → {after:.3} µm (noise {noise:.3})");
    assert!(
        after <= 0.2 * before && after <= 1.5 * noise,
        "{effect}: {before} → {after}"
    );
    let _ = Path::new("");
}

/// The structure's profile (what the report plots: the residual against the axis with the
/// fitted period over it) has the period's shape: 12 bins a period, and the binned residual
/// within half the fitted swing of the fitted curve.
fn profile_follows_the_fit(s: &serde_json::Value) -> bool {
    let p = &s["profile"];
    let v = |k: &str| -> Vec<f64> {
        p[k].as_array()
            .map(|a| a.iter().filter_map(|x| x.as_f64()).collect())
            .unwrap_or_default()
    };
    let (x, m, f) = (v("x_mm"), v("measured_um"), v("fitted_um"));
    if p["coordinate"] != "x, mm" || x.len() < 24 || m.len() != x.len() || f.len() != x.len() {
        eprintln!("profile: {p:#}");
        return false;
    }
    let rms = |a: &mut dyn Iterator<Item = f64>| {
        let (s, n) = a.fold((0.0, 0usize), |(s, n), v| (s + v * v, n + 1));
        (s / n as f64).sqrt()
    };
    let off = rms(&mut m.iter().zip(&f).map(|(a, b)| a - b));
    let swing = rms(&mut f.iter().copied());
    let per_bin = s["period_mm"].as_f64().unwrap() / (x[1] - x[0]);
    eprintln!("profile: {} bins, {per_bin:.1} a period, fitted {swing:.3} µm rms, residual off it {off:.3} µm rms", x.len());
    (per_bin - 12.0).abs() < 1.0 && off < 0.5 * swing
}

#[test]
fn outside_cyclic_error() {
    outside_case("cyclic_error", |s| {
        s["kind"] == "period"
            && s["axis"] == "x"
            && (s["period_mm"].as_f64().unwrap() - 4.0).abs() < 0.04
            && profile_follows_the_fit(s)
    });
}

#[test]
fn outside_backlash() {
    outside_case("backlash", |s| s["kind"] == "reversal" && s["axis"] == "x");
}

/// On rings alone, acceleration deflection and servo gain describe one physics: the lab says
/// they are confounded and which measurement would separate them.
#[test]
fn rings_alone_confound_accel_deflection_and_servo_gain() {
    let dir = scratch("confound");
    ok(
        &dir,
        &[
            "sim",
            "--program",
            "ring-speeds",
            "--hide",
            "accel_deflection",
            "--out",
            "r.mcap",
            "--calib-out",
            "sim.json",
            "--datasheet-out",
            "ds.json",
        ],
    );
    fitted_start(&dir, "sim.json", "ds.json", "r.mcap", "s.json");
    let d: serde_json::Value = serde_json::from_str(&ok(
        &dir,
        &[
            "lab", "diagnose", "--bag", "r.mcap", "--calib", "s.json", "--json",
        ],
    ))
    .unwrap();
    let conf = d["confounded"].as_array().unwrap();
    let pair = conf
        .iter()
        .find(|c| {
            let k: Vec<&str> = c["effects"]
                .as_array()
                .unwrap()
                .iter()
                .map(|e| kind(e.as_str().unwrap()))
                .collect();
            k.contains(&"accel_deflection") && k.contains(&"servo_gain")
        })
        .unwrap_or_else(|| panic!("not reported as confounded: {d:#}"));
    let how: Vec<&str> = pair["separate_by"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s.as_str().unwrap())
        .collect();
    // Only measurements that act along the measured direction and that these rings lack:
    // another diameter (frequency v/2πr vs acceleration v²/r: it separates the gain's f¹
    // term only, and says so), or a face accelerated along its normal — not "more spin-up".
    assert!(
        how.iter()
            .any(|s| s.contains("another diameter") && s.contains("in f²")),
        "{how:?}"
    );
    assert!(how.iter().any(|s| s.contains("face")), "{how:?}");
    assert!(!how.iter().any(|s| s.contains("spin-up")), "{how:?}");
}
