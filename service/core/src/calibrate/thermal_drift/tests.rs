use super::*;

/// Small deterministic noise (xorshift), uniform in ±a.
fn noise(n: usize, a: f64, seed: u64) -> Vec<f64> {
    let mut s = seed;
    (0..n)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            a * (2.0 * (s >> 11) as f64 / (1u64 << 53) as f64 - 1.0)
        })
        .collect()
}

/// A machine whose drift follows one sensor through a 2400 s lag and a heat source
/// through a 1200 s lag; another sensor is a copy of the first (confounded), a third is
/// unrelated. The procedure finds the lagged groups, names the copy, and predicts a
/// later period it never saw.
#[test]
fn finds_the_lagged_drift_and_predicts_a_later_period() {
    let n = 4000;
    let t: Vec<f64> = (0..n).map(|k| 15.0 * k as f64).collect();
    let rpm: Vec<f64> = t
        .iter()
        .map(|&x| {
            if ((x / 7200.0) as usize) % 2 == 1 {
                3000.0
            } else {
                0.0
            }
        })
        .collect();
    let t_a: Vec<f64> = t
        .iter()
        .zip(noise(n, 0.01, 3))
        .map(|(&x, e)| 22.0 + 2.0 * (x / 20000.0).sin() + e)
        .collect();
    let t_b: Vec<f64> = t_a.iter().map(|v| 0.5 * v + 3.0).collect();
    let t_c: Vec<f64> = noise(n, 0.3, 9).iter().map(|e| 21.0 + e).collect();
    let la = Lag { tau_s: 2400.0 }.run(&t, &t_a.iter().map(|v| v - t_a[0]).collect::<Vec<_>>());
    let lr = Lag { tau_s: 1200.0 }.run(&t, &rpm);
    let y: Vec<f64> = (0..n)
        .zip(noise(n, 0.2e-3, 17))
        .map(|(k, e)| 1e-3 * (5.0 * la[k] + 0.004 * lr[k]) + e)
        .collect();
    let rec = Recording {
        t_s: t,
        sources: vec![
            Source {
                name: "a".into(),
                kind: SourceKind::Temperature,
                values: t_a,
            },
            Source {
                name: "b".into(),
                kind: SourceKind::Temperature,
                values: t_b,
            },
            Source {
                name: "c".into(),
                kind: SourceKind::Temperature,
                values: t_c,
            },
            Source {
                name: "rpm".into(),
                kind: SourceKind::HeatSource,
                values: rpm,
            },
        ],
        channels: vec![Channel {
            name: "z".into(),
            mm: y,
        }],
    };
    let opt = Options {
        heldout_from: 3000,
        ..Options::default()
    };
    let f = fit(&rec, &opt).unwrap();
    assert_eq!(f.confounded.len(), 1);
    assert_eq!(
        (
            f.confounded[0].kept.as_str(),
            f.confounded[0].dropped.as_str()
        ),
        ("a", "b")
    );
    let ch = &f.channels[0];
    let added: Vec<&str> = ch.steps.iter().map(|s| s.added.as_str()).collect();
    assert!(added.contains(&Group::Lagged.name()), "{added:?}");
    assert!(added.contains(&Group::Heat.name()), "{added:?}");
    // The drift spans ~ ±12 µm; the model predicts the held-out hours within half a µm
    // (the noise is uniform ±0.2 µm, MAE 0.1 µm; the heat source's 1200 s lag is not in
    // the basis and is made of its neighbours, 600 and 2400 s).
    assert!(ch.nominal_heldout.mae_um > 3.0, "{:?}", ch.nominal_heldout);
    assert!(ch.heldout.mae_um < 0.5, "{:?} {:?}", ch.heldout, ch.steps);
    assert!(ch
        .terms
        .iter()
        .all(|t| t.k.is_finite() && t.sigma.is_finite() && t.sigma >= 0.0));
    // The strongest term is a lagged `a` or the heat source.
    assert!(
        ["a", "rpm"].contains(&ch.terms[0].source.as_str()),
        "{:?}",
        ch.terms[0]
    );
}

/// A drift through a lag of 1500 s, between the basis's 600 and 2400 s, with noise: the
/// compact model refines its lag off the basis to the truth within its stated σ (and the
/// σ is not vanishing: between 0.1 % and 20 % of τ), and predicts the held-out rows
/// better than the basis lag did.
#[test]
fn the_compact_model_refines_a_lag_off_the_basis_within_its_sigma() {
    let n = 6000;
    let t: Vec<f64> = (0..n).map(|k| 15.0 * k as f64).collect();
    let a: Vec<f64> = t
        .iter()
        .map(|&x| 20.0 + 2.0 * (x / 5000.0).sin() + 1.5 * (x / 1700.0).cos())
        .collect();
    let da: Vec<f64> = a.iter().map(|v| v - a[0]).collect();
    let la = Lag { tau_s: 1500.0 }.run(&t, &da);
    let y: Vec<f64> = (0..n)
        .zip(noise(n, 0.3e-3, 5))
        .map(|(k, e)| 1e-3 * 6.0 * la[k] + e)
        .collect();
    let rec = Recording {
        t_s: t,
        sources: vec![Source {
            name: "a".into(),
            kind: SourceKind::Temperature,
            values: a,
        }],
        channels: vec![Channel {
            name: "z".into(),
            mm: y,
        }],
    };
    let opt = Options {
        heldout_from: 4500,
        ..Options::default()
    };
    let m = compact(&rec, &opt, 0, 2).unwrap();
    assert!(m.refined, "{m:?}");
    let lag = m
        .terms
        .iter()
        .find(|t| t.tau_s > 0.0)
        .expect("a lagged term");
    let u = lag.tau_sigma_s.expect("a refined lag has its σ");
    assert!(
        (lag.tau_s - 1500.0).abs() < 3.0 * u && u > 1.5 && u < 300.0,
        "τ = {} ± {u} s against 1500 s",
        lag.tau_s
    );
    assert!(
        (lag.k - 6.0).abs() < 3.0 * lag.sigma + 0.05,
        "k = {} ± {}",
        lag.k,
        lag.sigma
    );
    assert!(m.heldout.mae_um < 0.2, "{:?}", m.heldout);
    let cfg = effect(&[(&m, 2)]).unwrap();
    assert!(cfg.terms.iter().any(|t| t.tau_s_u == Some(u)));
}

#[test]
fn refuses_a_recording_it_cannot_fit() {
    let rec = Recording {
        t_s: vec![0.0, 1.0, 1.0],
        sources: vec![Source {
            name: "a".into(),
            kind: SourceKind::Temperature,
            values: vec![20.0; 3],
        }],
        channels: vec![Channel {
            name: "x".into(),
            mm: vec![0.0; 3],
        }],
    };
    let e = fit(
        &rec,
        &Options {
            heldout_from: 2,
            ..Options::default()
        },
    )
    .unwrap_err();
    assert!(
        e.to_string().contains("time does not increase at row 2"),
        "{e}"
    );
}

/// The effect written from a compact model corrects as the model predicts: its terms
/// through the corrector's lag over the recorded readings give the model's prediction.
#[test]
fn the_effect_applies_what_the_compact_model_predicts() {
    let n = 3000;
    let t: Vec<f64> = (0..n).map(|k| 15.0 * k as f64).collect();
    let a: Vec<f64> = t.iter().map(|&x| 21.0 + 3.0 * (x / 9000.0).sin()).collect();
    let b: Vec<f64> = t.iter().map(|&x| 24.0 + 1.0 * (x / 3000.0).cos()).collect();
    let la = Lag { tau_s: 2400.0 }.run(&t, &a);
    let y: Vec<f64> = (0..n)
        .map(|k| 1e-3 * (4.0 * (la[k] - 21.0) - 2.0 * (b[k] - b[0])))
        .collect();
    let rec = Recording {
        t_s: t.clone(),
        sources: vec![
            Source {
                name: "a".into(),
                kind: SourceKind::Temperature,
                values: a.clone(),
            },
            Source {
                name: "b".into(),
                kind: SourceKind::Temperature,
                values: b.clone(),
            },
        ],
        channels: vec![Channel {
            name: "z".into(),
            mm: y,
        }],
    };
    let opt = Options {
        heldout_from: 2400,
        ..Options::default()
    };
    let m = compact(&rec, &opt, 0, 4).unwrap();
    assert!(m.heldout.mae_um < 0.05, "{m:?}");
    let cfg = effect(&[(&m, 2)]).unwrap();
    assert!(!cfg.terms.is_empty() && cfg.terms.len() <= 4);
    // Evaluate the effect as the corrector would: each term's lagged reading.
    let mut sensors = crate::effects::SensorTable::default();
    let built = cfg.build(&mut sensors).unwrap();
    let lagged: Vec<Vec<f64>> = (0..sensors.names().len())
        .map(|slot| {
            let src = if sensors.names()[slot] == "a" { &a } else { &b };
            Lag {
                tau_s: sensors.tau(slot),
            }
            .run(&t, src)
        })
        .collect();
    for k in (0..n).step_by(97) {
        let mut ctx = crate::sample::PointContext::at_rest(crate::sample::Vec3::zeros());
        for (slot, v) in lagged.iter().enumerate() {
            ctx.temps[slot] = v[k];
        }
        ctx.temps_valid = (1 << lagged.len()) - 1;
        let d = crate::effects::Effect::correction(&built, &ctx);
        assert!(d.x == 0.0 && d.y == 0.0);
        assert!(
            (d.z - rec.channels[0].mm[k]).abs() < 1e-4,
            "row {k}: {} vs {}",
            d.z,
            rec.channels[0].mm[k]
        );
    }
}
