//! `scancorr lab plan`: a campaign planned from a fitted calibration before it is measured,
//! run by the simulator (`sim --program plan.json`), and the lab's fit on its bag set beside
//! the prediction: σ within 1.5× of predicted for the deflection matrix P, the servo gain and
//! the rigid-body terms the design determines (those confounded with others, over 99.9 % of
//! their column following theirs, are named and claim no σ); and on the campaign's bag with the plan's, `accel_deflection` (the
//! simulator's physics) chosen over `servo_gain`. The start is the nominal model with the
//! effects a `lab discover` reaches, refitted by `lab fit` on the campaign: the truth only
//! judges. Machine seed 113, run seeds 41 and 42 (no other test uses them).

mod common;
use common::*;
use scancorr_core::effects::{self as fx, EffectConfig};
use scancorr_core::sample::Axis;

fn json(s: &str) -> serde_json::Value {
    assert!(!s.contains("NaN"), "NaN in output: {s}");
    serde_json::from_str(s).unwrap_or_else(|e| panic!("not JSON ({e}): {s}"))
}

/// The effects `lab discover` ends with on the default campaign (README), at zero.
fn discovered_effects(tips: &[u32]) -> Vec<EffectConfig> {
    let mut guide = fx::guide_straightness::Config::zeros(Axis::X, 150.0, 900.0, 39, true);
    guide.pitch_about = Some(Axis::Z);
    vec![
        EffectConfig::ProbeForce(fx::probe_force::Config::zeros_per_tip(tips)),
        EffectConfig::GuideStraightness(guide),
        EffectConfig::AccelDeflection(fx::accel_deflection::Config::zeros(1, false)),
        EffectConfig::ServoPhase(fx::servo_phase::Config::zeros(0)),
        EffectConfig::ScaleThermal(fx::scale_thermal::Config::zeros()),
        EffectConfig::StylusThermal(fx::stylus_thermal::Config::zeros(false)),
    ]
}

#[test]
fn a_planned_campaign_measures_what_it_predicted() {
    let t0 = std::time::Instant::now();
    let d = scratch("lab-plan");
    let seed = ["--machine-seed", "113"];
    ok(
        &d,
        &[
            &[
                "sim",
                "--program",
                "campaign",
                "--seed",
                "41",
                "--out",
                "c.mcap",
            ][..],
            &seed,
            &["--datasheet-out", "ds.json", "--calib-out", "sim.json"],
        ]
        .concat(),
    );
    fitted_from_nominal(&d);
    // The plan, from the fitted calibration, the data sheet's travel and the artifacts owned.
    let planned = plan_owned(&d, "8", &[]);
    let minutes = planned["minutes"].as_f64().unwrap();
    assert!(minutes > 4.0 && minutes <= 8.0, "{minutes} min");
    // The simulator runs the record.
    ok(
        &d,
        &[
            &[
                "sim",
                "--program",
                "plan.json",
                "--seed",
                "42",
                "--out",
                "p.mcap",
            ][..],
            &seed,
            &["--truth", "truth.json"],
        ]
        .concat(),
    );
    // The lab fits the plan's bag; its σ beside the prediction.
    let checked = json(&ok(
        &d,
        &[
            "lab",
            "plan",
            "--calib",
            "fitted.json",
            "--program",
            "plan.json",
            "--bag",
            "p.mcap",
            "--json",
        ],
    ));
    // The lab's σ counts the residual's lag-1 correlation ρ (of the start's residual on the
    // new bag, which no design can know): compare with the design's prediction at the noise
    // and ρ the bag showed; the first prediction (ρ = 0) is that one scaled.
    let rho = checked["measured_rho"].as_f64().unwrap();
    assert!((0.0..1.0).contains(&rho), "{rho}");
    let pred = checked["prediction_at_measured_noise"]["params"]
        .as_array()
        .unwrap();
    let meas = checked["measured"].as_array().unwrap();
    assert_eq!(pred.len(), meas.len());
    let mut ratios = std::collections::BTreeMap::<String, Vec<(f64, String)>>::new();
    for (p, m) in pred.iter().zip(meas) {
        let effect = p["effect"].as_str().unwrap();
        let group = match effect {
            "accel_deflection" => "P",
            e if e.starts_with("servo_gain") => "servo gain",
            e if e.starts_with("rigid_body") => "rigid body",
            _ => continue,
        };
        // What the design determines, the lab determines.
        let Some(ps) = p["sigma"].as_f64() else {
            continue;
        };
        // A parameter confounded with others (99.9 % of its column follows theirs) has its σ
        // from the lab's ridge and the data's model error: the plan names it, claims no σ.
        let vif = p["vif"].as_f64().unwrap_or(f64::INFINITY);
        if vif > scancorr_core::lab::plan::JOINT_VIF {
            continue;
        }
        let ms = m["sigma"].as_f64().unwrap_or_else(|| {
            panic!(
                "{effect}: {}: predicted σ {ps:e}, the lab could not determine it",
                p["name"]
            )
        });
        ratios
            .entry(group.to_string())
            .or_default()
            .push((ms / ps, p["name"].as_str().unwrap().to_string()));
    }
    eprintln!("lab_plan: measured σ / predicted σ {ratios:?}");
    // Every parameter the design determines: the lab's σ within 1.5× of the prediction (the
    // lab's own fit on simulated measurements of the design, at the noise and ρ the bag
    // showed).
    for g in ["P", "servo gain", "rigid body"] {
        let r = ratios.get(g).cloned().unwrap_or_default();
        assert!(r.len() >= 2, "too few {g} terms determined: {ratios:?}");
        for (x, name) in &r {
            assert!(
                (1.0 / 1.5..=1.5).contains(x),
                "{g}: {name}: measured σ / predicted σ {x:.2} ({r:?})"
            );
        }
    }
    let compared: Vec<(String, usize)> = ratios.iter().map(|(k, v)| (k.clone(), v.len())).collect();
    // Item 5: on the campaign with the plan, without accel_deflection in the model, the lab
    // ranks the simulator's physics (compliance under acceleration) above the servo gain.
    let mut noacc = scancorr_core::Calibration::from_json(
        &std::fs::read_to_string(d.join("fitted.json")).unwrap(),
    )
    .unwrap();
    noacc.effects.retain(|e| e.kind() != "accel_deflection");
    std::fs::write(d.join("noacc.json"), noacc.to_json()).unwrap();
    let diag = json(&ok(
        &d,
        &[
            "lab",
            "diagnose",
            "--bag",
            "c.mcap",
            "--bag",
            "p.mcap",
            "--calib",
            "noacc.json",
            "--stride",
            "8",
            "--json",
        ],
    ));
    let cands = diag["candidates"].as_array().unwrap();
    let rank = |kind: &str| {
        cands
            .iter()
            .position(|c| c["effect"].as_str().unwrap().starts_with(kind))
            .unwrap_or(usize::MAX)
    };
    assert_eq!(rank("accel_deflection"), 0, "{cands:?}");
    let cv = |kind: &str| cands[rank(kind)]["cv_rms_after_um"].as_f64().unwrap();
    assert!(
        cv("servo_gain") > 2.0 * cv("accel_deflection"),
        "servo_gain {} µm against accel_deflection {} µm",
        cv("servo_gain"),
        cv("accel_deflection")
    );
    eprintln!(
        "lab_plan: {compared:?} in {:.1} s",
        t0.elapsed().as_secs_f64()
    );
}

/// Item 5, the plan's half: the machine has the simulator's 21 wavy rigid-body errors
/// (`--with rigid_body`), which the default campaign's three ring positions cannot determine.
/// From the nominal model with the discovered effects fitted by `lab fit` on the campaign,
/// `lab plan --candidate rigid_body` places the ring one place at a time where it most reduces
/// the predicted variance of the rigid-body terms, and its prediction (from the design alone)
/// determines every rigid-body term any place of the pool could: the others are reported
/// beyond reach (with horizontal rings, an error of z alone that moves every stylus alike shifts
/// each ring's centre, which the fit takes as its own; the guide table in the model carries the x axis' straightness and
/// yaw). Measured: 25 of 33 terms within reach, all determined by the plan (24 of 33 while
/// each place was scanned both ways; 16 before the places along z were scanned with every
/// stylus: the z axis' straightness and rotations are seen only between styli). With one turn
/// per place (`greedy::ONE_WAY`) the first plan left `AZX c1` (the x axis' yaw varying along
/// x) undetermined (neither a turn the other way nor a second speed at its places
/// determined it; every stylus along x does): the plan is made again with every stylus along x.
/// Machine seed 131, run seed 4311 (no other test uses them). 12 s (25 s under heavy load:
/// the two simulations and `lab fit`; the plan 2.4 s, twice when it is made again).
#[test]
fn the_plan_determines_every_rigid_body_term_within_reach() {
    let t0 = std::time::Instant::now();
    let d = scratch("lab-plan-reach");
    let planned = rigid_plan(&d);
    let beyond: Vec<&str> = planned["prediction"]["beyond_reach"]
        .as_array()
        .map(|v| v.iter().filter_map(|x| x.as_str()).collect())
        .unwrap_or_default();
    let rb: Vec<(String, bool)> = planned["prediction"]["params"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|p| p["effect"].as_str().unwrap().starts_with("rigid_body"))
        .map(|p| {
            (
                format!(
                    "{}: {}",
                    p["effect"].as_str().unwrap(),
                    p["name"].as_str().unwrap()
                ),
                p["sigma"].is_number(),
            )
        })
        .collect();
    let (within, out): (Vec<_>, Vec<_>) =
        rb.iter().partition(|(n, _)| !beyond.contains(&n.as_str()));
    let missed: Vec<&String> = within.iter().filter(|(_, s)| !s).map(|(n, _)| n).collect();
    eprintln!(
        "lab_plan reach: {} of {} rigid-body terms within reach, {} determined; beyond: {beyond:?} ({:.1} s)",
        within.len(),
        rb.len(),
        within.len() - missed.len(),
        t0.elapsed().as_secs_f64()
    );
    assert!(
        !within.is_empty() && !out.is_empty(),
        "{} of {} terms beyond reach: {beyond:?}",
        out.len(),
        rb.len()
    );
    // With rings in the horizontal plane, the z axis' positioning (EZZ, a function of z that
    // moves every stylus alike along z) is beyond reach, whatever the places; its rotation
    // about z (AZZ) turns each stylus's horizontal offset its own way: seen between styli at
    // the places along z the plan scans with every stylus, and determined.
    for (n, s) in &rb {
        let term = n.split(": ").nth(1).unwrap_or("");
        assert!(
            !term.starts_with("EZZ") || beyond.contains(&n.as_str()),
            "{n} predicted determined from horizontal rings"
        );
        assert!(
            !term.starts_with("AZZ") || (*s && !beyond.contains(&n.as_str())),
            "{n} not determined by the styli along z"
        );
    }
    assert!(
        missed.is_empty(),
        "within reach but not determined: {missed:?}"
    );
    // Nothing beyond reach is predicted determined (the pool holds the plan's places).
    assert!(out.iter().all(|(_, s)| !s), "{out:?}");
}

/// The acceptance's last clause: on the campaign with the plan's bag (above), `lab add
/// rigid_body` brings a held-out ring at another position within 1.2× the noise floor. Run
/// seeds 4312–4313.
///
/// Measured 29 Nov: 0.405 → 0.106 µm against a 0.103 µm floor (1.03×; 1.05× while each place
/// was scanned both ways, 1.10× before the plan scanned its places along z with every
/// stylus). It stood at 1.52×
/// while the lab's fit left every translation table of the rigid body out (`select`: a column
/// was "weak" beside its effect's strongest, and a rotation's column is its Abbe lever,
/// hundreds of mm, times a translation's): the rotations times their levers stood in for the
/// translations at the data's z levels, not between them. Columns are now compared within
/// their own unit.
#[test]
fn the_plan_determines_the_rigid_body_hidden_from_a_nominal_start() {
    let t0 = std::time::Instant::now();
    let d = scratch("lab-plan-rigid");
    rigid_plan(&d);
    ok(
        &d,
        &[
            "sim",
            "--program",
            "plan.json",
            "--seed",
            "4312",
            "--out",
            "p.mcap",
            "--machine-seed",
            "131",
            "--with",
            "rigid_body",
        ],
    );
    let added = json(&ok(
        &d,
        &[
            "lab",
            "add",
            "rigid_body",
            "--bag",
            "c.mcap",
            "--bag",
            "p.mcap",
            "--calib",
            "fitted.json",
            "--validate",
            "v.mcap",
            "--out",
            "rb.json",
            "--json",
        ],
    ));
    let (before, after, floor) = (
        added["heldout_rms_before_um"].as_f64().unwrap(),
        added["heldout_rms_after_um"].as_f64().unwrap(),
        added["noise_floor_um"].as_f64().unwrap(),
    );
    eprintln!(
        "lab_plan rigid: held-out {before:.3} → {after:.3} µm, floor {floor:.3} µm ({:.2}×) in {:.1} s",
        after / floor,
        t0.elapsed().as_secs_f64()
    );
    assert!(
        floor > 0.0 && after <= 1.2 * floor,
        "held-out ring {after:.3} µm against a floor of {floor:.3} µm (from {before:.3} µm)"
    );
}

/// Machine 131 with the wavy rigid body: the campaign (`c.mcap`, run seed 4311), a held-out
/// ring-speeds run at (550, 300, −250) (`v.mcap`, 4313), the user's fitted start
/// (`fitted.json`) and the 16-minute plan for the rigid body (`plan.json`): its JSON, after
/// checking the plan placed the ring for the rigid body.
fn rigid_plan(d: &std::path::Path) -> serde_json::Value {
    let m = ["--machine-seed", "131", "--with", "rigid_body"];
    let sim = |program: &str, seed: &str, out: &str, extra: &[&str]| {
        ok(
            d,
            &[
                &["sim", "--program", program, "--seed", seed, "--out", out][..],
                &m,
                extra,
            ]
            .concat(),
        );
    };
    sim(
        "campaign",
        "4311",
        "c.mcap",
        &["--datasheet-out", "ds.json", "--calib-out", "sim.json"],
    );
    sim(
        "ring-speeds",
        "4313",
        "v.mcap",
        &["--position", "550,300,-250"],
    );
    fitted_from_nominal(d);
    let planned = plan_owned(d, "16", &["--candidate", "rigid_body"]);
    let groups = planned["groups"].as_array().unwrap();
    assert!(
        groups.iter().any(|g| g["what"]
            .as_str()
            .unwrap()
            .contains("chosen one by one for the rigid body")),
        "{groups:?}"
    );
    planned
}

/// `calib nominal` from the data sheet (styli as qualified), the discovered model's effects at
/// zero, refitted on the campaign `c.mcap` by `lab fit`: `fitted.json`, what a user starts from.
/// `lab plan` from the fitted calibration, the data sheet's travel and the artifacts owned (a
/// ring, a sphere, a 400 mm straightedge), within `minutes`, to `plan.json`: its JSON.
fn plan_owned(d: &std::path::Path, minutes: &str, extra: &[&str]) -> serde_json::Value {
    let args = [
        &[
            "lab",
            "plan",
            "--calib",
            "fitted.json",
            "--datasheet",
            "ds.json",
            "--artifact",
            "ring:d=50.0012",
            "--artifact",
            "sphere:d=25.0004",
            "--artifact",
            "straightedge:l=400",
            "--minutes",
            minutes,
        ][..],
        extra,
        &["--replicates", "0", "--out", "plan.json", "--json"],
    ]
    .concat();
    json(&ok(d, &args))
}

fn fitted_from_nominal(d: &std::path::Path) {
    ok(
        d,
        &[
            "calib",
            "nominal",
            "--datasheet",
            "ds.json",
            "--tips-from",
            "sim.json",
            "--out",
            "nominal.json",
        ],
    );
    let nominal = std::fs::read_to_string(d.join("nominal.json")).unwrap();
    let mut cal = scancorr_core::Calibration::from_json(&nominal).unwrap();
    let tips: Vec<u32> = cal.geometry.tips.iter().map(|t| t.id).collect();
    cal.effects = discovered_effects(&tips);
    std::fs::write(d.join("start.json"), cal.to_json()).unwrap();
    ok(
        d,
        &[
            "lab",
            "fit",
            "--bag",
            "c.mcap",
            "--calib",
            "start.json",
            "--out",
            "fitted.json",
        ],
    );
}
