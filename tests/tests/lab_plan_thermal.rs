//! `scancorr lab plan --temp-span-k`: the temperature span in the plan (issue 45, item 3).
//! From a fitted calibration, the plan weighs spans of the room's temperature up to what the
//! user can produce for the thermal effects' σ, writes the span to reach into the program
//! record (`temperature.span_k`) and says why; the simulator runs the record at that span
//! (`sim --program`), and the lab's σ of the scales' expansion coefficients on the bag is
//! within 1.5× of the prediction. The start is the nominal model with the effects a
//! `lab discover` reaches, refitted by `lab fit` on a campaign: the truth only judges.
//! Machine seed 8461, run seeds 84611 and 84612 (no other test uses them).

mod common;
use common::*;
use scancorr_core::effects::{self as fx, EffectConfig};
use scancorr_core::sample::Axis;

fn json(s: &str) -> serde_json::Value {
    assert!(!s.contains("NaN"), "NaN in output: {s}");
    serde_json::from_str(s).unwrap_or_else(|e| panic!("not JSON ({e}): {s}"))
}

/// Not yet met (29 Nov, machine 8461, run 84612): α_x's σ is 1.66× the prediction, α_y 1.14×.
/// The lab composes σ = √(max(σ_stat, σ_scan, fold spread)² + penalty shift²).
///
/// Before (last session): α_x 1.59× (1.22–1.50× with run seeds 84613–84616 on the same plan);
/// σ_stat 1.06–1.12×, σ_scan 0.86–1.14× of the prediction, but the penalties moved α_x by
/// 0.55–1.0 predicted σ in every run, towards its start (7 predicted σ off), α_x 3.8–4.7e-8 above
/// the truth. Confirmed as the lab's relative ridge (`select`: A_jj·(1 + r), r = 1e-3 chosen):
/// the same bag and start refitted with the ridge off gives a penalty shift of 0 and α_x
/// 1.2e-8 lower. A ridge relative to the column's own diagonal is a prior of precision r·V/σ²
/// on a parameter of variance inflation V (140 for α_x): it pulled ≈12 % of the change back.
///
/// Now the ridge is not put on a parameter the data determine (its least-squares change at
/// least 3 of its own σ: `select::Space::determined`). Same plan and start (as fitted before
/// the change; the test's own chain after it gives 1.66×), measured over
/// predicted σ of α_x, before → after, run seeds 84612/84613/84614/84615/84616: penalty shift
/// 0.48/1.0/0.97/0.81/0.55 → 0.06/0.01/0.01/0.03/0.02; σ 1.59/1.46/1.50/1.34/1.22 →
/// 1.70/1.16/1.16/1.15/1.15; α_x − truth 1.50–1.82 → 0.56–1.25 predicted σ (all five still
/// above; the ridge off altogether gives the same).
/// α_y unchanged (1.08–1.11×). Machine 8467 (not used before, after the change was fixed), run
/// 84611/84612: α_x 1.28×, α_y 1.23×.
///
/// What is left on run 84612 is the fold spread, |θ̂₀ − θ̂₁|/2 of the two folds' fits: 1.70× the
/// prediction (1.52× before; 0.19–0.90× on the other four seeds). It is a one-draw estimate of
/// σ (|N(0, σ²)|: above 1.5σ in 13 % of runs) and enters σ through the max, so a single run's
/// σ exceeds 1.5× the design's in about one run in eight by construction. Met when the lab's σ
/// stops taking a one-draw spread at face value (σ_scan already sees correlated residuals with
/// many scans' degrees of freedom) or the plan predicts its distribution. Run with `--ignored`.
#[test]
#[ignore = "α_x's measured σ is 1.66× the prediction on run 84612: the folds' one-draw spread (see the doc)"]
fn the_plan_asks_for_a_temperature_span_and_the_lab_measures_what_it_predicted() {
    let t0 = std::time::Instant::now();
    let d = scratch("lab-plan-thermal");
    let m = ["--machine-seed", "8461"];
    let sim = |args: &[&str]| ok(&d, &[&["sim"][..], args, &m].concat());
    sim(&[
        "--program",
        "campaign",
        "--seed",
        "84611",
        "--out",
        "c.mcap",
        "--datasheet-out",
        "ds.json",
        "--calib-out",
        "sim.json",
    ]);
    // The user's start: nominal, the discovered model's effects at zero, `lab fit`.
    ok(
        &d,
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
    let mut cal = scancorr_core::Calibration::from_json(
        &std::fs::read_to_string(d.join("nominal.json")).unwrap(),
    )
    .unwrap();
    let tips: Vec<u32> = cal.geometry.tips.iter().map(|t| t.id).collect();
    let mut guide = fx::guide_straightness::Config::zeros(Axis::X, 150.0, 900.0, 39, true);
    guide.pitch_about = Some(Axis::Z);
    cal.effects = vec![
        EffectConfig::ProbeForce(fx::probe_force::Config::zeros_per_tip(&tips)),
        EffectConfig::GuideStraightness(guide),
        EffectConfig::AccelDeflection(fx::accel_deflection::Config::zeros(1, false)),
        EffectConfig::ServoPhase(fx::servo_phase::Config::zeros(0)),
        EffectConfig::ScaleThermal(fx::scale_thermal::Config::zeros()),
        EffectConfig::StylusThermal(fx::stylus_thermal::Config::zeros(false)),
    ];
    std::fs::write(d.join("start.json"), cal.to_json()).unwrap();
    ok(
        &d,
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
    // The plan, with the span the user can produce (4 K).
    let planned = json(&ok(
        &d,
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
            "--minutes",
            "8",
            "--candidate",
            "none",
            "--temp-span-k",
            "4",
            "--replicates",
            "0",
            "--out",
            "plan.json",
            "--json",
        ],
    ));
    let th = &planned["thermal"];
    let span = th["span_k"].as_f64().unwrap_or_else(|| panic!("{th}"));
    assert!(span > 0.0 && span <= 4.0, "{th}");
    assert!(th["why"].as_str().unwrap().contains(" K"), "{th}");
    let record: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("plan.json")).unwrap()).unwrap();
    assert_eq!(record["temperature"]["span_k"].as_f64(), Some(span));
    // What the span buys: σ(α_x) at no span against the span chosen.
    let sigma_at = |i: usize, name: &str| {
        th["ladder"][i]["params"]
            .as_array()
            .unwrap()
            .iter()
            .find(|p| p["name"].as_str().unwrap().starts_with(name))
            .and_then(|p| p["sigma"].as_f64())
    };
    let ladder = th["ladder"].as_array().unwrap();
    let chosen = ladder
        .iter()
        .position(|s| s["span_k"].as_f64() == Some(span))
        .unwrap();
    let (s0, s1) = (sigma_at(0, "alpha_x"), sigma_at(chosen, "alpha_x").unwrap());
    assert!(
        s0.is_none_or(|s0| s0 > 1.5 * s1),
        "σ(α_x) {s0:?} at 0 K against {s1:e} at {span} K"
    );
    // The simulator runs the record at its span; the lab fits the bag.
    sim(&[
        "--program",
        "plan.json",
        "--seed",
        "84612",
        "--out",
        "p.mcap",
        "--truth",
        "truth.json",
    ]);
    let truth = json(&std::fs::read_to_string(d.join("truth.json")).unwrap());
    let [lo, hi] = [0, 1].map(|i| truth["temperatures"]["scale_x"][i].as_f64().unwrap());
    assert!(
        (hi - lo - span).abs() < 0.5 * span.max(1.0),
        "the scales spanned {lo:.2}…{hi:.2} °C for a span of {span} K"
    );
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
            "--candidate",
            "none",
            "--replicates",
            "0",
            "--json",
        ],
    ));
    let pred = checked["prediction_at_measured_noise"]["params"]
        .as_array()
        .unwrap();
    let meas = checked["measured"].as_array().unwrap();
    let mut ratios = vec![];
    for (p, q) in pred.iter().zip(meas) {
        let name = p["name"].as_str().unwrap();
        if p["effect"] != "scale_thermal" || name.starts_with("alpha_z") {
            continue;
        }
        let ps = p["sigma"].as_f64().unwrap_or_else(|| panic!("{name}: {p}"));
        let ms = q["sigma"].as_f64().unwrap_or_else(|| {
            panic!("{name}: predicted σ {ps:e}, the lab could not determine it")
        });
        ratios.push((name.to_string(), ms / ps));
    }
    eprintln!(
        "lab_plan_thermal: span {span} K, measured σ / predicted σ {ratios:?} ({:.1} s)",
        t0.elapsed().as_secs_f64()
    );
    assert_eq!(ratios.len(), 2, "{ratios:?}");
    for (n, r) in &ratios {
        assert!(
            (1.0 / 1.5..=1.5).contains(r),
            "{n}: measured/predicted σ {r:.2}"
        );
    }
}
