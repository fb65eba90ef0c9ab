//! The corrector end to end on synthetic streams: synthesis on a ring, the stream join's
//! handling of bad input, and bit-identical output for any interleaving of the streams.

use proptest::prelude::*;
use scancorr_core::effects::{accel_deflection, stylus_thermal, EffectConfig};
use scancorr_core::*;
use std::f64::consts::PI;

const T_NS: i64 = 1_000_000;

/// A probe scanning the inside of a ring gauge (radius `ring_r`) centred at `c`, starting
/// with a dwell, spinning up and then at constant speed; the scales are the ideal positions
/// (tip centre − stylus offset − deflection). Returns the four streams in time order.
fn ring_streams(n: usize, ring_r: f64, tip_r: f64, defl: f64) -> [Vec<Sample>; 4] {
    let c = Vec3::new(300.0, 200.0, -100.0);
    let offset = Vec3::new(0.0, 0.0, -50.0);
    let path_r = ring_r - tip_r;
    let (mut cmd, mut sc, mut pr, mut tp) = (vec![], vec![], vec![], vec![]);
    for k in 0..n {
        let t = k as f64 * 1e-3;
        // Dwell 50 ms, then speed ramps to 40 mm/s over 100 ms.
        let tt = (t - 0.05).max(0.0);
        let s = if tt < 0.1 {
            200.0 * tt * tt
        } else {
            40.0 * (tt - 0.05)
        };
        let th = s / path_r;
        let dir = Vec3::new(th.cos(), th.sin(), 0.0);
        let tip_center = c + dir * path_r;
        let d_machine = -dir * defl; // the wall pushes the tip towards the centre
                                     // The command pushes past the wall by the deflection.
        let commanded = tip_center - offset + dir * defl;
        let scale = tip_center - offset - d_machine;
        cmd.push(Sample::Command(CommandSample {
            seq: k as u64,
            t_ns: k as i64 * T_NS,
            pos: commanded,
            arc_center: c - offset,
            arc_radius: path_r + defl,
            segment_id: 1,
        }));
        sc.push(Sample::Scale(ScaleSample {
            seq: k as u64,
            t_ns: k as i64 * T_NS,
            pos: scale,
        }));
        pr.push(Sample::Probe(ProbeSample {
            seq: k as u64,
            t_ns: k as i64 * T_NS,
            deflection: d_machine,
            tip_id: 1,
            head_a1_deg: 0.0,
            head_a2_deg: 0.0,
            force_n: None,
        }));
        if k % 100 == 0 {
            tp.push(Sample::Temperature(TemperatureSample {
                seq: (k / 100) as u64,
                t_ns: k as i64 * T_NS - 300 * T_NS,
                sensor: "stylus".into(),
                celsius: 20.5 + 1e-4 * k as f64,
            }));
        }
    }
    [cmd, sc, pr, tp]
}

fn calibration() -> Calibration {
    let mut c = Calibration::example("m1");
    let mut ad = accel_deflection::Config::zeros(1, false);
    ad.p[0] = [[2e-6, 1e-7, 0.0], [0.0, 3e-6, 0.0], [0.0, 0.0, 1e-6]];
    ad.p[1][0][0] = 1e-6;
    c.effects.push(EffectConfig::AccelDeflection(ad));
    c.effects
        .push(EffectConfig::StylusThermal(stylus_thermal::Config {
            alpha_shank_per_k: 11.5e-6,
            ..stylus_thermal::Config::zeros(false)
        }));
    c
}

fn run(cal: &Calibration, samples: impl IntoIterator<Item = Sample>) -> (Output, Stats) {
    let mut corr = Corrector::new(cal).unwrap();
    let mut out = Output::default();
    corr.push_all(samples, &mut out);
    corr.flush(&mut out);
    (out, corr.stats().clone())
}

fn time_ordered(streams: &[Vec<Sample>; 4]) -> Vec<Sample> {
    let mut all: Vec<Sample> = streams.iter().flatten().cloned().collect();
    all.sort_by_key(|s| (s.t_ns(), s.stream()));
    all
}

#[test]
fn ring_points_lie_on_the_ring_without_effects() {
    let streams = ring_streams(1500, 25.0, 1.5, 0.3);
    let cal = Calibration::example("m1");
    let (out, stats) = run(&cal, time_ordered(&streams));
    assert_eq!(stats.points_out, 1500);
    assert_eq!(stats.dropped_total(), 0);
    let c = Vec3::new(300.0, 200.0, -100.0);
    for p in &out.points {
        let r = (p.surface - c).norm();
        assert!((r - 25.0).abs() < 1e-9, "seq {}: r = {r}", p.seq);
        // The normal points from the wall into the ring (towards the centre).
        assert!(p.normal.dot(&(c - p.surface).normalize()) > 0.999999);
        assert!(p.corrections.is_empty());
    }
    // Points are numbered consecutively and name the calibration version.
    assert!(out.points.windows(2).all(|w| w[1].seq == w[0].seq + 1));
    assert!(out.points.iter().all(|p| p.calibration_version == 1));
}

#[test]
fn effects_are_applied_and_reported_per_effect() {
    let streams = ring_streams(1500, 25.0, 1.5, 0.3);
    let cal = calibration();
    let mut corr = Corrector::new(&cal).unwrap();
    corr.record_context(true);
    let mut out = Output::default();
    corr.push_all(time_ordered(&streams), &mut out);
    corr.flush(&mut out);
    assert_eq!(
        corr.effect_ids(),
        vec!["accel_deflection", "stylus_thermal"]
    );
    // Temperatures start 300 ms before the motion; the first point uses the reading at
    // t − 200 ms, so every point is produced.
    assert_eq!(out.points.len(), 1500, "{:?}", corr.stats());
    let mut checked = 0;
    for (p, ctx) in out.points.iter().zip(&out.contexts) {
        let p_mat = nalgebra::Matrix3::new(2e-6, 1e-7, 0.0, 0.0, 3e-6, 0.0, 0.0, 0.0, 1e-6)
            + nalgebra::Matrix3::new(1e-6, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
                * (ctx.scale.x / 500.0);
        let expect = p_mat * ctx.est_acc;
        assert!((p.corrections[0] - expect).norm() < 1e-15);
        let dt = ctx.temps[0] - 20.0;
        assert!((p.corrections[1] - Vec3::new(0.0, 0.0, -50.0 * 11.5e-6 * dt)).norm() < 1e-15);
        let total = p.corrections[0] + p.corrections[1];
        let c = Vec3::new(300.0, 200.0, -100.0);
        let uncorrected = p.surface - total;
        assert!(((uncorrected - c).norm() - 25.0).abs() < 1e-9);
        if ctx.est_acc.norm() > 10.0 {
            checked += 1;
        }
    }
    assert!(checked > 1000);
}

#[test]
fn bad_input_is_counted_never_interpolated_across() {
    let [cmd, sc, pr, tp] = ring_streams(1000, 25.0, 1.5, 0.3);
    let mut samples: Vec<Sample> = vec![];
    // Command gap: samples 400..410 missing → scale points 400..409 dropped (gap of 11 periods).
    let cmd: Vec<Sample> = cmd
        .into_iter()
        .filter(|s| !(400..410).contains(&(s.t_ns() / T_NS)))
        .collect();
    // Probe: one sample with NaN, one duplicate of sample 600.
    let mut pr2 = vec![];
    for s in pr {
        let k = s.t_ns() / T_NS;
        if k == 700 {
            if let Sample::Probe(mut p) = s.clone() {
                p.deflection.x = f64::NAN;
                pr2.push(Sample::Probe(p));
                continue;
            }
        }
        pr2.push(s.clone());
        if k == 600 {
            pr2.push(s);
        }
    }
    // Scale: one sample going back in time.
    let mut sc2 = sc.clone();
    if let Sample::Scale(mut s) = sc[800].clone() {
        s.seq = 5000;
        s.t_ns = 10 * T_NS;
        sc2.insert(801, Sample::Scale(s));
    }
    for s in sc2.iter_mut().skip(802) {
        if let Sample::Scale(x) = s {
            x.seq += 5000;
        }
    }
    samples.extend(cmd);
    samples.extend(sc2);
    samples.extend(pr2);
    samples.extend(tp);
    samples.sort_by_key(|s| (s.t_ns(), s.stream()));
    let (out, st) = run(&Calibration::example("m1"), samples);
    let dropped = |r: DropReason| st.dropped[r as usize];
    assert_eq!(dropped(DropReason::CommandGap), 10, "{st:?}");
    assert_eq!(dropped(DropReason::NonFinite), 1);
    assert_eq!(dropped(DropReason::Duplicate), 1);
    assert_eq!(dropped(DropReason::OutOfOrder), 1);
    assert_eq!(st.seq_gaps[0], 1);
    assert_eq!(st.seq_gaps[1], 1);
    // Probe 700 missing: its neighbours 699 and 701 are 2 periods apart (< 2.5): interpolated.
    assert_eq!(out.points.len(), 990);
    assert!(out
        .points
        .iter()
        .all(|p| !(400..410).contains(&(p.t_ns / T_NS))));
    // After the command gap the estimator restarts: its points are flagged until settled.
    let after: Vec<_> = out.points.iter().filter(|p| p.t_ns / T_NS >= 410).collect();
    assert!(!after[0].estimator_valid);
    assert!(after.last().unwrap().estimator_valid);
    // Every surface point still on the ring (no interpolation across the gap).
    let c = Vec3::new(300.0, 200.0, -100.0);
    assert!(out
        .points
        .iter()
        .all(|p| ((p.surface - c).norm() - 25.0).abs() < 1e-6));
}

#[test]
fn missing_temperature_and_unknown_tip_are_drops() {
    let [cmd, sc, mut pr, _] = ring_streams(300, 25.0, 1.5, 0.3);
    let cal = calibration();
    let all: Vec<Sample> = cmd.iter().chain(&sc).chain(&pr).cloned().collect();
    let (out, st) = run(&cal, all);
    assert_eq!(out.points.len(), 0);
    assert_eq!(st.dropped[DropReason::TemperatureMissing as usize], 300);
    for s in pr.iter_mut() {
        if let Sample::Probe(p) = s {
            p.tip_id = 9;
        }
    }
    let all: Vec<Sample> = cmd.iter().chain(&sc).chain(&pr).cloned().collect();
    let (_, st) = run(&Calibration::example("m1"), all);
    assert_eq!(st.dropped[DropReason::UnknownTip as usize], 300);
}

#[test]
fn calibration_switch_mid_stream_loses_nothing() {
    let streams = ring_streams(1000, 25.0, 1.5, 0.3);
    let samples = time_ordered(&streams);
    let cal1 = Calibration::example("m1");
    let mut cal2 = calibration();
    cal2.version = 2;
    cal2.parent_version = Some(1);
    let mut corr = Corrector::new(&cal1).unwrap();
    let mut out = Output::default();
    let half = samples.len() / 2;
    corr.push_all(samples[..half].iter().cloned(), &mut out);
    let n1 = out.points.len();
    corr.set_model(std::sync::Arc::new(cal2.build().unwrap()));
    corr.push_all(samples[half..].iter().cloned(), &mut out);
    corr.flush(&mut out);
    // Temperatures are needed only from the switch on; the stream has them.
    assert_eq!(out.points.len(), 1000, "{:?}", corr.stats());
    assert!(out.points[..n1].iter().all(|p| p.calibration_version == 1));
    assert!(out.points[n1..]
        .iter()
        .all(|p| p.calibration_version == 2 && p.corrections.len() == 2));
    // Same nominal model: the estimator kept running, points stay valid.
    assert!(out.points[n1..].iter().all(|p| p.estimator_valid));
}

#[test]
fn calibration_switch_to_another_nominal_model_restarts_the_estimator() {
    let streams = ring_streams(1000, 25.0, 1.5, 0.3);
    let samples = time_ordered(&streams);
    let cal1 = calibration();
    let mut cal2 = calibration();
    cal2.version = 2;
    cal2.nominal.axes.x = transfer::TransferFunction::FirstOrder { tau_s: 0.02 };
    let mut corr = Corrector::new(&cal1).unwrap();
    let mut out = Output::default();
    let half = samples.len() / 2;
    corr.push_all(samples[..half].iter().cloned(), &mut out);
    let n1 = out.points.len();
    assert!(
        out.points[n1 - 1].estimator_valid,
        "settled before the switch"
    );
    corr.set_model(std::sync::Arc::new(cal2.build().unwrap()));
    corr.push_all(samples[half..].iter().cloned(), &mut out);
    corr.flush(&mut out);
    assert_eq!(out.points.len(), 1000, "{:?}", corr.stats());
    // Another nominal model: the estimator restarts, its first points flagged while it
    // settles, then valid again.
    assert!(!out.points[n1].estimator_valid);
    assert!(out.points.last().unwrap().estimator_valid);
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

    /// Any interleaving of the four streams gives bit-identical points and alarms.
    #[test]
    fn any_interleaving_gives_identical_output(choices in prop::collection::vec(0u8..4, 4000), n in 200usize..600) {
        let streams = ring_streams(n, 25.0, 1.5, 0.3);
        let cal = calibration();
        let (reference, _) = run(&cal, time_ordered(&streams));
        // Merge the streams in the order the choices say (each stream keeps its own order).
        let mut idx = [0usize; 4];
        let mut merged = vec![];
        let mut ci = choices.iter().cycle();
        while idx.iter().zip(streams.iter()).any(|(i, s)| *i < s.len()) {
            let k = *ci.next().unwrap() as usize;
            let k = (0..4).map(|d| (k + d) % 4).find(|k| idx[*k] < streams[*k].len()).unwrap();
            merged.push(streams[k][idx[k]].clone());
            idx[k] += 1;
        }
        let (out, _) = run(&cal, merged);
        prop_assert_eq!(out.points.len(), reference.points.len());
        for (a, b) in out.points.iter().zip(&reference.points) {
            prop_assert_eq!(a, b);
            prop_assert_eq!(a.surface.x.to_bits(), b.surface.x.to_bits());
        }
        prop_assert_eq!(out.alarms, reference.alarms);
    }
}

#[test]
fn judgement_raises_once_on_a_collision_and_clears() {
    // The scales stop following the command for 30 ms (an obstruction) at 0.6 s.
    let [cmd, mut sc, pr, tp] = ring_streams(1500, 25.0, 1.5, 0.3);
    let mut held = None;
    for s in sc.iter_mut() {
        if let Sample::Scale(x) = s {
            let k = x.t_ns / T_NS;
            if (600..630).contains(&k) {
                let h = *held.get_or_insert(x.pos);
                x.pos = h;
            }
        }
    }
    let all: Vec<Sample> = cmd.into_iter().chain(sc).chain(pr).chain(tp).collect();
    // These synthetic scales follow the command without lag: the nominal model says so too.
    let mut cal = calibration();
    cal.nominal.axes.x = scancorr_core::transfer::TransferFunction::Unity;
    cal.nominal.axes.y = scancorr_core::transfer::TransferFunction::Unity;
    cal.nominal.axes.z = scancorr_core::transfer::TransferFunction::Unity;
    cal.nominal.probes.insert(
        "sp25".into(),
        scancorr_core::transfer::TransferFunction::Unity,
    );
    let (out, st) = run(&cal, all);
    // One episode: raised once on each axis that saw it, cleared once on each.
    let raised: Vec<_> = out.alarms.iter().filter(|a| a.raised).collect();
    let cleared: Vec<_> = out.alarms.iter().filter(|a| !a.raised).collect();
    assert!(!raised.is_empty() && raised.len() <= 3, "{:?}", out.alarms);
    assert_eq!(st.alarms_raised as usize, raised.len());
    for axis in Axis::ALL {
        assert!(raised.iter().filter(|a| a.axis == axis).count() <= 1);
        assert_eq!(
            raised.iter().filter(|a| a.axis == axis).count(),
            cleared.iter().filter(|a| a.axis == axis).count()
        );
    }
    let onset = raised[0].t_ns / T_NS;
    assert!((600..650).contains(&onset), "raised at {onset} ms");
    assert!(cleared.iter().all(|a| a.t_ns > raised[0].t_ns));
    // Points during the episode are flagged.
    assert!(out
        .points
        .iter()
        .any(|p| !p.estimator_valid && p.t_ns / T_NS > 600));
    let _ = PI;
}

#[test]
fn a_host_pending_limit_bounds_buffers_and_counts_what_it_pushes_out() {
    let streams = ring_streams(1000, 25.0, 1.5, 0.3);
    let cal = calibration();
    // Commands and scales arrive, the probe stays silent: everything waits for it.
    let mut corr = Corrector::new(&cal).unwrap();
    corr.limit_pending(Some(64));
    assert_eq!(corr.max_pending(), 64);
    let mut out = Output::default();
    let waiting: Vec<Sample> = streams[0].iter().chain(&streams[1]).cloned().collect();
    corr.push_all(waiting, &mut out);
    assert!(out.points.is_empty());
    let [c, s, _, _] = corr.pending();
    assert_eq!((c, s), (64, 64));
    // 1000 commands and 1000 scales in, 64 of each kept: the rest counted, none lost silently.
    let overflow = corr
        .stats()
        .dropped_by_name()
        .into_iter()
        .find(|(n, _)| *n == "buffer_overflow")
        .map(|(_, v)| v);
    assert_eq!(overflow, Some(2 * (1000 - 64)));
    let bound = std::mem::size_of::<Corrector>()
        + 64 * (std::mem::size_of::<CommandSample>() + std::mem::size_of::<ScaleSample>())
        + 4096;
    assert!(
        corr.state_bytes() <= bound,
        "{} > {bound}",
        corr.state_bytes()
    );
    // Without the host's limit the calibration's bound (20 000) holds everything.
    let mut free = Corrector::new(&cal).unwrap();
    free.push_all(streams[0].iter().cloned(), &mut out);
    assert_eq!(free.pending()[0], 1000);
    assert!(free.state_bytes() > corr.state_bytes());
    // A limit above the calibration's bound does not raise it.
    free.limit_pending(Some(1_000_000));
    assert_eq!(free.max_pending(), cal.join.max_pending);
}

/// The streams of `ring_streams` moved by `dt_ns` in controller time.
fn shifted(streams: &[Vec<Sample>; 4], dt_ns: i64) -> Vec<Sample> {
    time_ordered(streams)
        .into_iter()
        .map(|mut s| {
            match &mut s {
                Sample::Command(c) => c.t_ns += dt_ns,
                Sample::Scale(c) => c.t_ns += dt_ns,
                Sample::Probe(c) => c.t_ns += dt_ns,
                Sample::Temperature(c) => c.t_ns += dt_ns,
            }
            s
        })
        .collect()
}

#[test]
fn a_controller_clock_reset_restarts_the_join_and_loses_no_new_sample() {
    let cal = calibration();
    let before = shifted(&ring_streams(800, 25.0, 1.5, 0.3), 3_600_000_000_000);
    // The controller reboots: its clock and its seq counters start again from zero.
    let after = shifted(&ring_streams(1200, 25.0, 1.5, 0.3), 0);
    let (alone_before, _) = run(&cal, before.clone());
    let (alone_after, _) = run(&cal, after.clone());
    let (both, stats) = run(&cal, before.into_iter().chain(after));
    assert_eq!(stats.clock_resets, 1);
    assert_eq!(
        both.points.len(),
        alone_before.points.len() + alone_after.points.len()
    );
    // Point seq runs on; every point of the new time base equals the one a fresh corrector
    // computes from the new time base alone.
    for (k, p) in both.points.iter().enumerate() {
        assert_eq!(p.seq, k as u64);
    }
    let tail = &both.points[alone_before.points.len()..];
    for (a, b) in tail.iter().zip(&alone_after.points) {
        assert_eq!(
            (
                a.t_ns,
                a.sample_seq,
                a.surface,
                a.tip_center,
                a.estimator_valid
            ),
            (
                b.t_ns,
                b.sample_seq,
                b.surface,
                b.tip_center,
                b.estimator_valid
            )
        );
        assert_eq!(a.corrections, b.corrections);
    }
    assert_eq!(stats.dropped_by_name(), vec![]);
}

#[test]
fn a_few_samples_far_back_are_late_not_a_clock_reset() {
    let cal = calibration();
    let mut samples = time_ordered(&ring_streams(1000, 25.0, 1.5, 0.3));
    // Five scale samples stamped 10 s in the past arrive in the middle.
    let glitch: Vec<Sample> = (0..5)
        .map(|k| {
            Sample::Scale(ScaleSample {
                seq: 5000 + k,
                t_ns: k as i64 * T_NS,
                pos: Vec3::zeros(),
            })
        })
        .collect();
    let at = samples.len() / 2;
    let mut glitched = samples.clone();
    let late_t = samples[at].t_ns() - 10_000_000_000;
    let glitch: Vec<Sample> = glitch
        .into_iter()
        .map(|mut s| {
            if let Sample::Scale(c) = &mut s {
                c.t_ns += late_t;
            }
            s
        })
        .collect();
    glitched.splice(at..at, glitch);
    let (clean, _) = run(&cal, samples.drain(..));
    let (out, stats) = run(&cal, glitched);
    assert_eq!(stats.clock_resets, 0);
    assert_eq!(stats.dropped_by_name(), vec![("out_of_order", 5)]);
    assert_eq!(out.points.len(), clean.points.len());
}

/// The same streams with every sample's seq mapped by `f` (per stream index).
fn reseq(streams: &[Vec<Sample>; 4], f: impl Fn(usize, u64) -> u64) -> [Vec<Sample>; 4] {
    let mut out = streams.clone();
    for (k, st) in out.iter_mut().enumerate() {
        for s in st.iter_mut() {
            match s {
                Sample::Command(c) => c.seq = f(k, c.seq),
                Sample::Scale(c) => c.seq = f(k, c.seq),
                Sample::Probe(c) => c.seq = f(k, c.seq),
                Sample::Temperature(c) => c.seq = f(k, c.seq),
            }
        }
    }
    out
}

/// The same points but for the scale seq each was made from (`sample_seq`); names the first
/// difference.
fn same_points(got: &[CorrectedPoint], want: &[CorrectedPoint]) {
    assert_eq!(got.len(), want.len(), "number of points");
    for (g, w) in got.iter().zip(want) {
        let g = CorrectedPoint {
            sample_seq: w.sample_seq,
            ..g.clone()
        };
        assert!(
            g == *w,
            "first difference at point seq {}: {g:?} vs {w:?}",
            w.seq
        );
    }
}

#[test]
fn a_wrapping_32_bit_counter_restarts_the_sequence_and_loses_nothing() {
    let streams = ring_streams(1500, 25.0, 1.5, 0.3);
    let (want, _) = run(&calibration(), time_ordered(&streams));
    // Command, scale and probe counters are 32-bit and wrap 700 samples in.
    let base = (1u64 << 32) - 700;
    let wrapped = reseq(
        &streams,
        |k, seq| if k < 3 { (base + seq) % (1 << 32) } else { seq },
    );
    let (got, st) = run(&calibration(), time_ordered(&wrapped));
    assert_eq!(st.seq_resets, 3, "{st:?}");
    assert_eq!(st.dropped_total(), 0, "{st:?}");
    same_points(&got.points, &want.points);
}

#[test]
fn one_bogus_seq_jump_is_recovered_from() {
    let streams = ring_streams(1500, 25.0, 1.5, 0.3);
    let (want, _) = run(&calibration(), time_ordered(&streams));
    // One scale sample and one probe sample carry a wild seq; the counters go on as before.
    let jumped = reseq(&streams, |k, seq| match (k, seq) {
        (1, 300) | (2, 900) => 1 << 40,
        _ => seq,
    });
    let (got, st) = run(&calibration(), time_ordered(&jumped));
    assert_eq!(st.seq_resets, 2, "{st:?}");
    assert_eq!(st.dropped_total(), 0, "{st:?}");
    same_points(&got.points, &want.points);
    // True duplicates (same seq, same time) are still duplicates, not a restart.
    let mut dup = time_ordered(&streams);
    let again: Vec<Sample> = dup
        .iter()
        .filter(|s| (500..510).contains(&(s.t_ns() / T_NS)))
        .cloned()
        .collect();
    let at = dup.iter().position(|s| s.t_ns() / T_NS == 510).unwrap();
    dup.splice(at..at, again.clone());
    let (got, st) = run(&calibration(), dup);
    assert_eq!(st.seq_resets, 0);
    assert_eq!(
        st.dropped[DropReason::Duplicate as usize] + st.dropped[DropReason::OutOfOrder as usize],
        again.len() as u64,
        "{st:?}"
    );
    same_points(&got.points, &want.points);
}

#[test]
fn sensors_the_calibration_does_not_use_are_bounded() {
    let streams = ring_streams(1500, 25.0, 1.5, 0.3);
    let (want, _) = run(&calibration(), time_ordered(&streams));
    let mut all = time_ordered(&streams);
    // One burst of 100 000 distinct sensor names (and a few bad names) early in the run.
    let at = all.iter().position(|s| s.t_ns() / T_NS == 20).unwrap();
    let burst: Vec<Sample> = (0..100_000u64)
        .map(|i| {
            Sample::Temperature(TemperatureSample {
                seq: 100 + i,
                t_ns: 10 * T_NS,
                sensor: if i % 10_000 == 7 {
                    format!("bad/name*{i}")
                } else {
                    format!("s{i}")
                },
                celsius: 20.0,
            })
        })
        .collect();
    all.splice(at..at, burst);
    // Later temperatures continue the stylus sensor's sequence above the burst.
    for s in all.iter_mut() {
        if let Sample::Temperature(t) = s {
            if t.sensor == "stylus" && t.t_ns > 10 * T_NS {
                t.seq += 200_000;
            }
        }
    }
    let mut corr = Corrector::new(&calibration()).unwrap();
    let mut out = Output::default();
    corr.push_all(all, &mut out);
    corr.flush(&mut out);
    let st = corr.stats();
    assert_eq!(st.dropped[DropReason::BadName as usize], 10, "{st:?}");
    let unknown = st.dropped[DropReason::UnknownSensor as usize];
    // The stylus sensor is kept with 63 others.
    let kept = MAX_KEPT_SENSORS as u64 - 1;
    assert_eq!(unknown, 100_000 - 10 - kept, "{st:?}");
    assert!(
        corr.state_bytes() < 64 * 1024,
        "{} bytes",
        corr.state_bytes()
    );
    same_points(&out.points, &want.points);
}

#[test]
fn absurd_but_finite_input_never_becomes_a_point() {
    let streams = ring_streams(1500, 25.0, 1.5, 0.3);
    let mut bad = streams.clone();
    if let Sample::Command(c) = &mut bad[0][700] {
        c.pos.x = 1e308;
    }
    if let Sample::Probe(p) = &mut bad[2][900] {
        p.head_a2_deg = 1e308;
    }
    if let Sample::Scale(s) = &mut bad[1][1100] {
        s.pos.y = -1e12;
    }
    if let Sample::Temperature(t) = &mut bad[3][5] {
        t.celsius = 1e300;
    }
    let (out, st) = run(&calibration(), time_ordered(&bad));
    assert_eq!(st.dropped[DropReason::Implausible as usize], 4, "{st:?}");
    let c = Vec3::new(300.0, 200.0, -100.0);
    assert!(out.points.len() > 1400);
    for p in &out.points {
        let uncorrected = p.surface - p.corrections.iter().sum::<Vec3>();
        assert!(
            ((uncorrected - c).norm() - 25.0).abs() < 1e-6,
            "seq {}",
            p.seq
        );
    }
    // A model that predicts a 10-mm correction is broken: no point is published.
    let mut cal = calibration();
    if let EffectConfig::AccelDeflection(ad) = &mut cal.effects[0] {
        ad.p[0] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    }
    let (out, st) = run(&cal, time_ordered(&streams));
    let n = st.dropped[DropReason::ImplausibleOutput as usize];
    assert!(n > 1000, "{st:?}");
    assert!(out
        .points
        .iter()
        .all(|p| p.corrections[0].norm() <= 5.0 * 3f64.sqrt()));
    assert_eq!(out.points.len() as u64 + n, 1500);
}

#[test]
fn an_effect_without_its_signal_is_named_inactive() {
    // servo_phase needs rotation: active on the ring, inactive on a straight scan.
    let mut cal = Calibration::example("m1");
    let mut sp = scancorr_core::effects::servo_phase::Config::zeros(0);
    sp.y[0] = [0.0, 1e-3, 0.0];
    cal.effects.push(EffectConfig::ServoPhase(sp));
    let mut corr = Corrector::new(&cal).unwrap();
    let mut out = Output::default();
    assert!(
        corr.inactive_effects().is_empty(),
        "nothing said before any point"
    );
    corr.push_all(time_ordered(&ring_streams(1500, 25.0, 1.5, 0.3)), &mut out);
    corr.flush(&mut out);
    assert!(corr.inactive_effects().is_empty());
    assert!(corr.stats().effect_points[0] > 1000, "{:?}", corr.stats());

    // A straight scan along x at 20 mm/s, no arc anywhere.
    let mut line: Vec<Sample> = vec![];
    for k in 0..1500u64 {
        let t = k as i64 * T_NS;
        let x = 100.0 + 20.0 * (k as f64 * 1e-3 - 0.05).max(0.0);
        let p = Vec3::new(x, 50.0, -100.0);
        line.push(Sample::Command(CommandSample {
            seq: k,
            t_ns: t,
            pos: p,
            arc_center: Vec3::zeros(),
            arc_radius: 0.0,
            segment_id: 1,
        }));
        line.push(Sample::Scale(ScaleSample {
            seq: k,
            t_ns: t,
            pos: p,
        }));
        line.push(Sample::Probe(ProbeSample {
            seq: k,
            t_ns: t,
            deflection: Vec3::new(0.0, -0.3, 0.0),
            tip_id: 1,
            head_a1_deg: 0.0,
            head_a2_deg: 0.0,
            force_n: None,
        }));
    }
    let mut corr = Corrector::new(&cal).unwrap();
    let mut out = Output::default();
    corr.push_all(line, &mut out);
    corr.flush(&mut out);
    assert!(corr.stats().points_out > 1000);
    assert_eq!(corr.inactive_effects(), vec!["servo_phase".to_string()]);
    // An effect whose parameters are all zero is not reported (it has nothing to say).
    let mut cal0 = Calibration::example("m1");
    cal0.effects.push(EffectConfig::ServoPhase(
        scancorr_core::effects::servo_phase::Config::zeros(0),
    ));
    let (_, st) = run(&cal0, time_ordered(&ring_streams(300, 25.0, 1.5, 0.3)));
    assert_eq!(st.effect_points, vec![0]);
}

#[test]
fn thermal_drift_runs_each_sensors_lag_over_its_readings_and_keeps_it_across_a_swap() {
    use scancorr_core::effects::thermal_drift::{self, Lag};
    // A fast-changing sensor read every 10 ms (the ring's temperatures are every 100 ms).
    let mut streams = ring_streams(1500, 25.0, 1.5, 0.3);
    streams[3].clear();
    let temp_at = |k: usize| 21.0 + 2.0 * (k as f64 * 0.02).sin();
    let times: Vec<i64> = (0..=180)
        .map(|j| j as i64 * 10 * T_NS - 300 * T_NS)
        .collect();
    for (j, &t) in times.iter().enumerate() {
        streams[3].push(Sample::Temperature(TemperatureSample {
            seq: j as u64,
            t_ns: t,
            sensor: "spindle".into(),
            celsius: temp_at(j),
        }));
    }
    let mut cal = Calibration::example("m1");
    let mut td = thermal_drift::Config::zeros(&[
        ("spindle".into(), 0.4, 20.0),
        ("spindle".into(), 0.0, 20.0),
    ]);
    td.set_params(&[1e-3, 0.0, 0.0, 2e-3, -1e-3, 0.0, 0.0, 0.0, 5e-4]);
    cal.effects.push(EffectConfig::ThermalDrift(td));
    let samples = time_ordered(&streams);
    let (out, stats) = run(&cal, samples.clone());
    assert_eq!(out.points.len(), 1500, "{stats:?}");
    // The lag over the readings at or before each point's time less the join's temperature
    // delay.
    let t_s: Vec<f64> = times.iter().map(|&t| t as f64 * 1e-9).collect();
    let u: Vec<f64> = (0..times.len()).map(temp_at).collect();
    let z = Lag { tau_s: 0.4 }.run(&t_s, &u);
    let delay = cal.join.temperature_delay_s;
    for p in &out.points {
        let t = p.t_ns as f64 * 1e-9 - delay;
        let j = t_s.iter().rposition(|&x| x <= t + 1e-12).unwrap();
        let want = Vec3::new(
            1e-3 + 2e-3 * (z[j] - 20.0),
            -1e-3 * (z[j] - 20.0),
            5e-4 * (u[j] - 20.0),
        );
        assert!(
            (p.corrections[0] - want).norm() < 1e-15,
            "seq {}: {:?} vs {want:?}",
            p.seq,
            p.corrections[0]
        );
    }
    // A swap to an equal calibration mid-stream keeps the lag's state: the same points.
    let mut corr = Corrector::new(&cal).unwrap();
    let mut out2 = Output::default();
    let half = samples.len() / 2;
    corr.push_all(samples[..half].iter().cloned(), &mut out2);
    let mut cal2 = cal.clone();
    cal2.version = 2;
    corr.set_model(std::sync::Arc::new(cal2.build().unwrap()));
    corr.push_all(samples[half..].iter().cloned(), &mut out2);
    corr.flush(&mut out2);
    assert_eq!(out2.points.len(), out.points.len());
    for (a, b) in out.points.iter().zip(&out2.points) {
        assert_eq!(a.corrections[0], b.corrections[0], "seq {}", a.seq);
    }
}

/// `streams` with sample `k` of stream `s` (1 scale, 2 probe) changed by `f`.
fn with_sample(
    streams: &[Vec<Sample>; 4],
    s: usize,
    k: usize,
    f: impl Fn(&mut Sample),
) -> [Vec<Sample>; 4] {
    let mut bad = streams.clone();
    f(&mut bad[s][k]);
    bad
}

/// The calibration with the jump gate out of the way (limits no machine reaches).
fn without_gate(mut cal: Calibration) -> Calibration {
    cal.limits.max_speed_mm_s = 1e9;
    cal.limits.max_accel_mm_s2 = 1e12;
    cal.limits.max_head_rate_deg_s = 1e9;
    cal
}

/// The largest distance of a valid point from the point at the same time in `clean`, mm.
fn worst_valid_off(out: &Output, clean: &Output) -> f64 {
    let at: std::collections::HashMap<i64, &CorrectedPoint> =
        clean.points.iter().map(|p| (p.t_ns, p)).collect();
    out.points
        .iter()
        .filter(|p| p.estimator_valid)
        .map(|p| (p.surface - at[&p.t_ns].surface).norm())
        .fold(0.0, f64::max)
}

#[test]
fn an_absurd_sample_inside_the_limits_is_dropped_and_its_neighbours_flagged() {
    let streams = ring_streams(1500, 25.0, 1.5, 0.3);
    let (clean, st) = run(&calibration(), time_ordered(&streams));
    assert_eq!(st.dropped_total(), 0, "{st:?}");
    let valid = clean.points.iter().filter(|p| p.estimator_valid).count();
    // Issue 44's samples: a scale at x = 4 999 mm (the ring is at 300), a deflection of
    // 4.9 mm (the probe's range is 5), the head's A2 at 359° (it stands at 0°); and a tip
    // id that names another stylus of the calibration for one sample.
    type Case = (&'static str, usize, usize, fn(&mut Sample));
    let cases: [Case; 4] = [
        ("scale", 1, 700, |s| {
            if let Sample::Scale(x) = s {
                x.pos.x = 4999.0;
            }
        }),
        ("probe", 2, 900, |s| {
            if let Sample::Probe(p) = s {
                p.deflection.x = 4.9;
            }
        }),
        ("head", 2, 1100, |s| {
            if let Sample::Probe(p) = s {
                p.head_a2_deg = 359.0;
            }
        }),
        ("tip", 2, 1200, |s| {
            if let Sample::Probe(p) = s {
                p.tip_id = 2;
            }
        }),
    ];
    let mut cal = calibration();
    let mut tip2 = cal.geometry.tips[0].clone();
    tip2.id = 2;
    tip2.l1_mm += 30.0;
    cal.geometry.tips.push(tip2);
    for (name, s, k, f) in cases {
        let bad = with_sample(&streams, s, k, f);
        // Without the gate the sample makes a valid point far off the ring.
        let (out, _) = run(&without_gate(cal.clone()), time_ordered(&bad));
        let before = worst_valid_off(&out, &clean);
        let (out, st) = run(&cal, time_ordered(&bad));
        let after = worst_valid_off(&out, &clean);
        eprintln!(
            "{name}: worst valid point {before:.4} mm off without the gate, {after:.2e} with it"
        );
        // (A tip that changes for one sample is a jump whatever the limits.)
        assert!(name == "tip" || before > 0.5, "{name}: {before}");
        assert!(after < 1e-9, "{name}: {after}");
        assert_eq!(
            st.dropped_by_name(),
            vec![("implausible_jump", 1)],
            "{name}: {st:?}"
        );
        assert_eq!(st.stream_jumps, [0; 4], "{name}");
        // The points around it are flagged: for a scale, the next one (the dropped sample
        // makes none); for the probe, the two the join interpolates across it.
        let flagged: Vec<i64> = out
            .points
            .iter()
            .filter(|p| !p.estimator_valid && p.t_ns > 400 * T_NS)
            .map(|p| p.t_ns / T_NS)
            .collect();
        let k = k as i64;
        let want = if s == 1 { vec![k + 1] } else { vec![k, k + 1] };
        assert_eq!(flagged, want, "{name}");
        let valid_now = out.points.iter().filter(|p| p.estimator_valid).count();
        assert_eq!(
            valid_now + want.len() + usize::from(s == 1),
            valid,
            "{name}"
        );
    }
}

#[test]
fn a_jump_the_stream_keeps_is_taken_and_flagged() {
    // The head indexes from 0° to 90° and stays there; the scales leap 2 mm and stay (no
    // machine moves so, but the stream holds it): nothing is lost, the points across each
    // jump are flagged, and each jump is counted.
    let streams = ring_streams(1500, 25.0, 1.5, 0.3);
    let mut bad = streams.clone();
    for s in bad[2].iter_mut().skip(800) {
        if let Sample::Probe(p) = s {
            p.head_a1_deg = 90.0;
        }
    }
    for s in bad[1].iter_mut().skip(1000) {
        if let Sample::Scale(x) = s {
            x.pos.y += 2.0;
        }
    }
    let cal = calibration();
    let (clean, _) = run(&cal, time_ordered(&streams));
    let (out, st) = run(&cal, time_ordered(&bad));
    assert_eq!(out.points.len(), clean.points.len());
    assert_eq!(st.dropped_total(), 0, "{st:?}");
    assert_eq!(st.stream_jumps, [0, 1, 1, 0], "{st:?}");
    let n = cal.limits.jump_confirm_samples as i64;
    let flagged: Vec<i64> = out
        .points
        .iter()
        .filter(|p| !p.estimator_valid && p.t_ns > 400 * T_NS)
        .map(|p| p.t_ns / T_NS)
        .collect();
    let mut want: Vec<i64> = (800..800 + n).chain(1000..1000 + n).collect();
    // The judge sees the scales' leap as an acceleration the estimate does not have.
    want.retain(|k| !flagged.is_empty() && *k >= 800);
    for k in &want {
        assert!(flagged.contains(k), "{k} not flagged: {flagged:?}");
    }
    assert!(!flagged.contains(&(800 + n)) && !flagged.contains(&799));
}

#[test]
fn a_stylus_springs_back_at_any_speed_but_is_pushed_no_faster_than_the_machine() {
    // Contact ends at 800: the deflection drops from 0.3 mm to nothing in a sample (the
    // stylus springs back), and starts again at 1000 the same way (the machine's 2 000 mm/s
    // reach 2 mm in a 1-ms period): both are motion, not jumps.
    let streams = ring_streams(1500, 25.0, 1.5, 0.3);
    let mut bad = streams.clone();
    for s in bad[2].iter_mut().skip(800).take(200) {
        if let Sample::Probe(p) = s {
            p.deflection = Vec3::zeros();
        }
    }
    let (_, st) = run(&Calibration::example("m1"), time_ordered(&bad));
    assert_eq!(st.dropped_total(), 0, "{st:?}");
    assert_eq!(st.stream_jumps, [0; 4], "{st:?}");
    // A machine limited to 100 mm/s cannot push it 1 mm in less than 10 ms: a touch to 1 mm
    // the stream keeps is a jump (taken, flagged, counted), the release at 800 is not.
    for s in bad[2].iter_mut().skip(1000) {
        if let Sample::Probe(p) = s {
            p.deflection *= 1.0 / 0.3;
        }
    }
    let mut cal = Calibration::example("m1");
    cal.limits.max_speed_mm_s = 100.0;
    let (out, st) = run(&cal, time_ordered(&bad));
    assert_eq!(st.dropped_total(), 0, "{st:?}");
    assert_eq!(st.stream_jumps, [0, 0, 1, 0], "{st:?}");
    let flagged = |k: i64| {
        !out.points
            .iter()
            .find(|p| p.t_ns == k * T_NS)
            .unwrap()
            .estimator_valid
    };
    assert!(!flagged(800) && !flagged(999) && flagged(1000) && flagged(1003) && !flagged(1004));
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]

    /// With absurd samples and jumps in the streams, any interleaving still gives
    /// bit-identical points and alarms.
    #[test]
    fn the_jump_gate_keeps_the_output_independent_of_the_interleaving(
        choices in prop::collection::vec(0u8..4, 4000),
        n in 300usize..600,
        at in prop::collection::vec(100usize..300, 4),
    ) {
        let mut streams = ring_streams(n, 25.0, 1.5, 0.3);
        if let Sample::Scale(x) = &mut streams[1][at[0]] {
            x.pos.x = 4999.0;
        }
        if let Sample::Probe(p) = &mut streams[2][at[1]] {
            p.deflection.y = -4.0;
        }
        if let Sample::Probe(p) = &mut streams[2][at[2]] {
            p.head_a1_deg = 180.0;
        }
        for s in streams[1].iter_mut().skip(at[3]) {
            if let Sample::Scale(x) = s {
                x.pos.z -= 1.0;
            }
        }
        let cal = calibration();
        let (reference, st) = run(&cal, time_ordered(&streams));
        prop_assert!(st.dropped[DropReason::ImplausibleJump as usize] >= 2, "{:?}", st);
        let mut idx = [0usize; 4];
        let mut merged = vec![];
        let mut ci = choices.iter().cycle();
        while idx.iter().zip(streams.iter()).any(|(i, s)| *i < s.len()) {
            let k = *ci.next().unwrap() as usize;
            let k = (0..4).map(|d| (k + d) % 4).find(|k| idx[*k] < streams[*k].len()).unwrap();
            merged.push(streams[k][idx[k]].clone());
            idx[k] += 1;
        }
        let (out, st2) = run(&cal, merged);
        prop_assert_eq!(&st2, &st);
        prop_assert_eq!(out.points.len(), reference.points.len());
        for (a, b) in out.points.iter().zip(&reference.points) {
            prop_assert_eq!(a, b);
            prop_assert_eq!(a.surface.x.to_bits(), b.surface.x.to_bits());
        }
        prop_assert_eq!(out.alarms, reference.alarms);
    }
}
