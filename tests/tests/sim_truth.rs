//! The simulator against the corrector: with the true calibration the corrected ring lies on
//! the true surface within the noise; with an effect hidden it does not; the judgement stage
//! is quiet on a nominal run and raises within 50 ms of each fault.

use scancorr_core::{Calibration, Corrector, Output, PointContext, Sample};
use scancorr_sim::program::{FeatureKind, SegmentKind};
use scancorr_sim::{run, Fault, Options, RunResult};

struct Run {
    res: RunResult,
    samples: Vec<Sample>,
}

fn simulate(o: &Options) -> Run {
    let mut samples = vec![];
    let res = run(o, |s| samples.push(s)).expect("simulation runs");
    Run { res, samples }
}

fn correct(r: &Run, cal: &Calibration) -> Output {
    let mut c = Corrector::new(cal).unwrap();
    c.record_context(true);
    let mut out = Output::default();
    c.push_all(r.samples.iter().cloned(), &mut out);
    c.flush(&mut out);
    out
}

/// Deviations (µm) of corrected scan points from the true surface of their feature.
fn deviations(r: &Run, out: &Output) -> Vec<f64> {
    let segs = &r.res.program.segments;
    let feats = &r.res.truth.features;
    let mut d = vec![];
    for (p, _ctx) in out.points.iter().zip(&out.contexts) {
        let Some(seg) = segs.iter().find(|s| s.id == p.segment_id) else {
            continue;
        };
        if seg.kind != SegmentKind::Scan || !p.estimator_valid {
            continue;
        }
        let f = &feats[seg.feature.unwrap() as usize - 1];
        let c = nalgebra::Vector3::from(f.center);
        let dev = match f.kind {
            FeatureKind::Bore | FeatureKind::Boss => {
                let rel = p.surface - c;
                let th = rel.y.atan2(rel.x);
                (rel.x.hypot(rel.y) - (f.radius_mm + f.form_at(th)))
                    * if f.kind == FeatureKind::Bore {
                        1.0
                    } else {
                        -1.0
                    }
            }
            FeatureKind::Face => {
                let n = nalgebra::Vector3::from(f.normal);
                let along = n.cross(&nalgebra::Vector3::z()).normalize();
                (p.surface - c).dot(&n) - f.form_at((p.surface - c).dot(&along))
            }
        };
        d.push(dev * 1e3);
    }
    d
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt()
}

#[test]
fn true_calibration_puts_the_ring_on_its_true_surface() {
    let r = simulate(&Options {
        program: "ring-speeds".into(),
        ..Default::default()
    });
    let out = correct(&r, &r.res.truth.true_calibration);
    let d = deviations(&r, &out);
    let noise = r.res.truth.noise_floor_um;
    let (rms_true, max_true) = (rms(&d), d.iter().fold(0.0f64, |m, x| m.max(x.abs())));
    eprintln!("true calibration: {} points, RMS {rms_true:.3} µm, max {max_true:.3} µm, noise {noise:.3} µm", d.len());
    assert!(d.len() > 50_000);
    assert!(
        rms_true < 3.0 * noise,
        "RMS {rms_true} µm vs 3 × noise {}",
        3.0 * noise
    );
    // Per point: as many within 3σ as pure Gaussian noise would have (99.7 %), less a margin.
    let inside = d.iter().filter(|x| x.abs() <= 3.0 * noise).count() as f64 / d.len() as f64;
    assert!(
        inside > 0.99,
        "only {:.2} % of points within 3 × noise",
        inside * 100.0
    );
    // Nominal model only (everything hidden): far off.
    let mut nominal = r.res.truth.true_calibration.clone();
    nominal.effects.clear();
    let d0 = deviations(&r, &correct(&r, &nominal));
    eprintln!("nominal only: RMS {:.3} µm", rms(&d0));
    assert!(rms(&d0) > 3.0 * noise);
    let _ = PointContext::at_rest;
}

#[test]
fn each_hidden_effect_leaves_the_artifact_off_its_surface() {
    // Rings at several speeds show every effect but the stylus's growth, which moves the tip
    // of a vertical stylus along z only; the campaign's sphere scans with the bent stylus
    // show that one.
    for hide in [
        "accel_deflection",
        "servo_phase",
        "stylus_thermal",
        "scale_thermal",
        "probe_force",
        "guide_straightness",
    ] {
        let program = if hide == "stylus_thermal" {
            "campaign"
        } else {
            "ring-speeds"
        };
        let o = Options {
            program: program.into(),
            hide: vec![hide.into()],
            ..Default::default()
        };
        let r = simulate(&o);
        let mut out = correct(&r, &r.res.start_calibration);
        if hide == "stylus_thermal" {
            // The bent stylus's scans only.
            let keep: Vec<bool> = out.points.iter().map(|p| p.tip_id == 2).collect();
            let mut k = keep.iter();
            out.points.retain(|_| *k.next().unwrap());
            let mut k = keep.iter();
            out.contexts.retain(|_| *k.next().unwrap());
        }
        let d = deviations(&r, &out);
        assert!(d.len() > 5_000);
        let noise = r.res.truth.noise_floor_um;
        eprintln!(
            "{hide} hidden ({program}): RMS {:.3} µm (3 × noise {:.3})",
            rms(&d),
            3.0 * noise
        );
        assert!(
            rms(&d) > 3.0 * noise,
            "{hide} hidden: RMS {} µm is within 3 × noise",
            rms(&d)
        );
    }
}

#[test]
fn judgement_is_quiet_for_ten_minutes_and_catches_each_fault() {
    let o = Options {
        program: "ring-speeds".into(),
        minutes: Some(10.0),
        ..Default::default()
    };
    let r = simulate(&o);
    let out = correct(&r, &r.res.start_calibration);
    let dur = r.samples.iter().map(|s| s.t_ns()).max().unwrap() as f64 * 1e-9;
    eprintln!(
        "nominal run of {dur:.0} s: {} alarm changes",
        out.alarms.len()
    );
    assert!(dur >= 600.0);
    assert!(
        out.alarms.is_empty(),
        "{:?}",
        &out.alarms[..out.alarms.len().min(4)]
    );
    for fault in [Fault::ServoDrift, Fault::Collision, Fault::Stall] {
        let o = Options {
            program: "ring-speeds".into(),
            fault: Some(fault),
            ..Default::default()
        };
        let r = simulate(&o);
        let out = correct(&r, &r.res.start_calibration);
        let onset = r.res.truth.faults[0].onset_t_ns;
        let first = out
            .alarms
            .iter()
            .find(|a| a.raised)
            .unwrap_or_else(|| panic!("{fault:?}: no alarm"));
        let delay_ms = (first.t_ns - onset) as f64 * 1e-6;
        eprintln!(
            "{fault:?}: raised {delay_ms:.1} ms after onset on {:?}",
            first.axis
        );
        assert!((0.0..=50.0).contains(&delay_ms), "{fault:?}: {delay_ms} ms");
    }
}
