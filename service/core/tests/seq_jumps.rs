//! Issue 44: a bogus seq (1.8·10¹⁹) was reported as 1.8·10¹⁹ samples missing. A seq jump
//! longer than the stream could have made since its previous sample loses nothing: it is a
//! gap, its return a seq reset; real losses are still counted exactly.

use scancorr_core::*;

const T_NS: i64 = 1_000_000;

/// A probe standing deflected against a face: command, scale and probe at 1 kHz.
fn streams(n: u64) -> [Vec<Sample>; 3] {
    let (mut cmd, mut sc, mut pr) = (vec![], vec![], vec![]);
    for k in 0..n {
        let t_ns = k as i64 * T_NS;
        let pos = Vec3::new(300.0, 200.0, -100.0);
        cmd.push(Sample::Command(CommandSample {
            seq: k,
            t_ns,
            pos,
            arc_center: pos,
            arc_radius: 0.0,
            segment_id: 1,
        }));
        sc.push(Sample::Scale(ScaleSample { seq: k, t_ns, pos }));
        pr.push(Sample::Probe(ProbeSample {
            seq: k,
            t_ns,
            deflection: Vec3::new(0.0, 0.0, 0.3),
            tip_id: 1,
            head_a1_deg: 0.0,
            head_a2_deg: 0.0,
            force_n: None,
        }));
    }
    [cmd, sc, pr]
}

fn run(s: &[Vec<Sample>; 3]) -> (Vec<CorrectedPoint>, Stats) {
    let mut all: Vec<Sample> = s.iter().flatten().cloned().collect();
    all.sort_by_key(|s| (s.t_ns(), s.stream()));
    let mut c = Corrector::new(&Calibration::example("m1")).unwrap();
    let mut out = Output::default();
    c.push_all(all, &mut out);
    c.flush(&mut out);
    (out.points, c.stats().clone())
}

fn set_seq(s: &mut Sample, seq: u64) {
    match s {
        Sample::Command(c) => c.seq = seq,
        Sample::Scale(c) => c.seq = seq,
        Sample::Probe(c) => c.seq = seq,
        Sample::Temperature(c) => c.seq = seq,
    }
}

#[test]
fn a_bogus_seq_is_not_counted_as_missing_samples() {
    let clean = streams(1500);
    let (want, st) = run(&clean);
    assert_eq!(st.samples_missing, [0; 4]);
    // One command, one scale and one probe sample carry wild seqs (u64::MAX: the largest
    // possible jump), the counters go on as before.
    let mut bogus = clean.clone();
    set_seq(&mut bogus[0][300], u64::MAX);
    set_seq(&mut bogus[1][600], u64::MAX - 5);
    set_seq(&mut bogus[2][900], 1 << 40);
    let (got, st) = run(&bogus);
    assert_eq!(st.samples_missing, [0; 4], "{st:?}");
    // The jumps are counted as gaps (not the one to u64::MAX's neighbour — nothing is above
    // it), each return as a seq reset; nothing is lost.
    assert_eq!(&st.seq_gaps[..3], &[1, 1, 1], "{st:?}");
    assert_eq!(st.seq_resets, 3, "{st:?}");
    assert_eq!(st.dropped_total(), 0, "{st:?}");
    assert_eq!(got.len(), want.len());
    // Summed over many correctors (the service's totals) nothing wraps either.
    let mut total = Stats::default();
    for _ in 0..4 {
        total.add(&st);
    }
    assert_eq!(total.samples_missing, [0; 4]);
}

#[test]
fn real_losses_are_still_counted_exactly() {
    let mut s = streams(3000);
    // 100 scale samples lost (a link dropped for 0.1 s), 1200 probe samples (a router down for
    // 1.2 s: longer than the 1024 slack, within the time bound).
    s[1].drain(500..600);
    s[2].drain(1000..2200);
    let (_, st) = run(&s);
    assert_eq!(st.samples_missing, [0, 100, 1200, 0], "{st:?}");
    assert_eq!(st.seq_gaps, [0, 1, 1, 0], "{st:?}");
    assert_eq!(st.seq_resets, 0, "{st:?}");
    // A jump of 5000 in 2 ms cannot be samples lost.
    let mut s = streams(3000);
    for x in s[1][1000..].iter_mut() {
        let seq = match x {
            Sample::Scale(c) => c.seq,
            _ => unreachable!(),
        };
        set_seq(x, seq + 5000);
    }
    let (_, st) = run(&s);
    assert_eq!(st.samples_missing, [0; 4], "{st:?}");
    assert_eq!(st.seq_gaps, [0, 1, 0, 0], "{st:?}");
}
