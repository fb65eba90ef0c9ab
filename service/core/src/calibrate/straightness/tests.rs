use super::shared::detrend;
use super::*;

/// Small deterministic PRNG (SplitMix64) with Gaussian deviates.
struct Rng(u64);
impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn uniform(&mut self) -> f64 {
        ((self.next_u64() >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    fn gauss(&mut self) -> f64 {
        let (a, b) = (self.uniform(), self.uniform());
        (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
    }
}

const L: f64 = 20.0;
const X0: f64 = 50.0;
const N: usize = 30;
const NOISE: f64 = 5e-6; // 5 nm per averaged reading

/// The straightedge: a set-up offset and tilt, a 3 µm bow and 1.5 µm of waviness, mm.
fn part(x: f64) -> f64 {
    let t = (x - 360.0) / 330.0;
    0.4 + 1e-4 * (x - 300.0)
        + 3e-3 * (1.0 - t * t)
        + 1.5e-3 * (std::f64::consts::TAU * x / 350.0 + 0.4).sin()
}
/// The guide: a line, a 2.5 µm cubic and 0.8 µm of waviness, mm (at the pitch centre).
fn guide(x: f64) -> f64 {
    let t = (x - 350.0) / 300.0;
    3e-5 * x + 2.5e-3 * t * t * t + 0.8e-3 * (std::f64::consts::TAU * x / 260.0).sin()
}
/// The carriage's pitch: 20 µrad constant plus 4 µrad varying, rad.
fn pitch(x: f64) -> f64 {
    2e-5 + 4e-6 * (std::f64::consts::TAU * x / 410.0 + 1.0).sin()
}
fn flat_pitch(_x: f64) -> f64 {
    2e-5
}

fn stations() -> Vec<f64> {
    (0..N).map(|k| X0 + k as f64 * L).collect()
}

/// Probe readings from the geometry: probe j at x + j·l, pitch about probe `centre`.
fn probe_readings(
    probes: usize,
    centre: f64,
    offsets: &[f64],
    sign: f64,
    pitch_of: fn(f64) -> f64,
    noise: f64,
    rng: &mut Rng,
) -> Vec<StationReading> {
    stations()
        .into_iter()
        .map(|x| StationReading {
            x_mm: x,
            readings: (0..probes)
                .map(|j| {
                    let lever = j as f64 * L - centre;
                    let v = sign * part(x + j as f64 * L) - guide(x) - pitch_of(x) * lever
                        + offsets[j]
                        + noise * rng.gauss();
                    Some(Reading {
                        value_mm: v,
                        u_mm: noise.max(1e-7),
                    })
                })
                .collect(),
        })
        .collect()
}

/// Shear-stage readings: stage error e·s, the sensor reporting the true shear.
fn shear_readings(
    shears: &[f64],
    jitter: f64,
    e: f64,
    pitch_of: fn(f64) -> f64,
    rng: &mut Rng,
) -> Vec<ShearReading> {
    let mut out = vec![];
    for x in stations() {
        for &s0 in shears {
            let s = s0 + jitter * (2.0 * rng.uniform() - 1.0);
            let v = part(x + s) - guide(x) - pitch_of(x) * s + e * s + 0.02 + NOISE * rng.gauss();
            out.push(ShearReading {
                x_mm: x,
                shear_mm: s,
                value_mm: v,
                u_mm: NOISE,
            });
        }
    }
    out
}

fn detrended(pos: &[f64], f: impl Fn(f64) -> f64) -> Vec<f64> {
    let mut y: Vec<f64> = pos.iter().map(|&p| f(p)).collect();
    detrend(pos, &mut y);
    y
}
fn centred(pos: &[f64], f: impl Fn(f64) -> f64) -> Vec<f64> {
    let y: Vec<f64> = pos.iter().map(|&p| f(p)).collect();
    let m = y.iter().sum::<f64>() / y.len() as f64;
    y.iter().map(|v| v - m).collect()
}
fn rms(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v.fold((0.0, 0usize), |a, x| (a.0 + x * x, a.1 + 1));
    (s / n as f64).sqrt()
}
fn diff(a: &[f64], b: &[f64]) -> Vec<f64> {
    a.iter().zip(b).map(|(x, y)| x - y).collect()
}

/// RMS error, RMS σ, fraction within 2σ.
fn judge(est: &[f64], sig: &[f64], truth: &[f64]) -> (f64, f64, f64) {
    let e = diff(est, truth);
    let within = e
        .iter()
        .zip(sig)
        .filter(|(a, s)| a.abs() <= 2.0 * **s)
        .count();
    (
        rms(e.iter().copied()),
        rms(sig.iter().copied()),
        within as f64 / e.len() as f64,
    )
}

fn check(label: &str, est: &[f64], sig: &[f64], truth: &[f64]) -> (f64, f64) {
    let (e, s, frac) = judge(est, sig, truth);
    eprintln!("{label}: RMS error {e:.3e}, RMS σ {s:.3e}, within 2σ {frac:.2}");
    assert!(e <= 2.0 * s, "{label}: RMS error {e:e} > 2 × RMS σ {s:e}");
    (e, s)
}

fn truths(sep: &Separation, pitch_of: fn(f64) -> f64) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    (
        detrended(&sep.part_positions_mm, part),
        detrended(&sep.stations_mm, guide),
        centred(&sep.stations_mm, pitch_of),
    )
}

#[test]
fn three_probe_recovers_part_guide_and_pitch() {
    let mut rng = Rng(1);
    let st = probe_readings(3, L, &[0.0; 3], 1.0, pitch, NOISE, &mut rng);
    let sep = three_probe(&ProbeMount { spacing_mm: L }, &st, None).unwrap();
    assert_eq!(sep.part_positions_mm.len(), N + 2);
    let (yp, xg, th) = truths(&sep, pitch);
    check(
        "3p part",
        &sep.part_straightness_mm,
        &sep.part_straightness_mm_u,
        &yp,
    );
    check(
        "3p guide",
        &sep.guide_straightness_mm,
        &sep.guide_straightness_mm_u,
        &xg,
    );
    let (p, pu) = (
        sep.pitch_rad.as_ref().unwrap(),
        sep.pitch_rad_u.as_ref().unwrap(),
    );
    check("3p pitch", p, pu, &th);
    assert_eq!(sep.cannot_see, ["line", "pitch_constant", "parabola"]);
    // The sequential method's σ grow along the travel.
    let u = &sep.part_straightness_mm_u;
    let min = u.iter().copied().fold(f64::MAX, f64::min);
    let max = u.iter().copied().fold(0.0, f64::max);
    assert!(max > 2.0 * min, "σ {min:e} … {max:e}");
    let json = serde_json::to_value(&sep).unwrap();
    for k in [
        "stations_mm",
        "guide_straightness_mm",
        "guide_straightness_mm_u",
        "part_straightness_mm",
        "part_straightness_mm_u",
        "pitch_rad",
        "pitch_rad_u",
        "cannot_see",
        "notes",
    ] {
        assert!(json.get(k).is_some(), "{k}");
    }
}

#[test]
fn offsets_give_the_predicted_parabola_unless_reversed() {
    let offsets = [0.8e-3, 1.3e-3, 1.5e-3];
    let delta = offsets[0] - 2.0 * offsets[1] + offsets[2];
    let mount = ProbeMount { spacing_mm: L };
    let mut rng = Rng(2);
    let st = probe_readings(3, L, &offsets, 1.0, pitch, 0.0, &mut rng);
    let sep = three_probe(&mount, &st, None).unwrap();
    let (yp, xg, th) = truths(&sep, pitch);
    let c2 = delta / (2.0 * L * L);
    let bow = |x: f64| c2 * (x - X0).powi(2);
    let want_g: Vec<f64> = xg
        .iter()
        .zip(detrended(&sep.stations_mm, bow))
        .map(|(a, b)| a + b)
        .collect();
    let want_p: Vec<f64> = yp
        .iter()
        .zip(detrended(&sep.part_positions_mm, bow))
        .map(|(a, b)| a + b)
        .collect();
    let eg = rms(diff(&sep.guide_straightness_mm, &want_g).into_iter());
    let ep = rms(diff(&sep.part_straightness_mm, &want_p).into_iter());
    let size = rms(detrended(&sep.stations_mm, bow).into_iter());
    eprintln!("parabola: RMS {size:e} mm, guide off it by {eg:e}, part by {ep:e}");
    assert!(size > 1e-3 && eg < 1e-10 && ep < 1e-10);
    // The pitch carries the parabola's slope 2·c2·(x − x_0) (about its mean).
    let want_t: Vec<f64> = th
        .iter()
        .zip(centred(&sep.stations_mm, |x| 2.0 * c2 * (x - X0)))
        .map(|(a, b)| a + b)
        .collect();
    let ept = rms(diff(sep.pitch_rad.as_ref().unwrap(), &want_t).into_iter());
    assert!(ept < 1e-12, "{ept:e}");
    // With the reversal the parabola is gone and δ measured.
    let rev = probe_readings(3, L, &offsets, -1.0, flat_pitch, 0.0, &mut rng);
    let sep = three_probe(&mount, &st, Some(&rev)).unwrap();
    assert_eq!(sep.cannot_see, ["line", "pitch_constant"]);
    let eg = rms(diff(&sep.guide_straightness_mm, &xg).into_iter());
    let ep = rms(diff(&sep.part_straightness_mm, &yp).into_iter());
    assert!(eg < 1e-10 && ep < 1e-10, "{eg:e} {ep:e}");
    assert!((sep.params[0].value - delta).abs() < 1e-12);
}

#[test]
fn reversal_with_noise_within_bounds() {
    let offsets = [0.8e-3, 1.3e-3, 1.5e-3];
    let mut rng = Rng(3);
    let st = probe_readings(3, L, &offsets, 1.0, pitch, NOISE, &mut rng);
    let rev = probe_readings(3, L, &offsets, -1.0, flat_pitch, NOISE, &mut rng);
    let sep = three_probe(&ProbeMount { spacing_mm: L }, &st, Some(&rev)).unwrap();
    let (yp, xg, th) = truths(&sep, pitch);
    check(
        "3p+rev part",
        &sep.part_straightness_mm,
        &sep.part_straightness_mm_u,
        &yp,
    );
    check(
        "3p+rev guide",
        &sep.guide_straightness_mm,
        &sep.guide_straightness_mm_u,
        &xg,
    );
    check(
        "3p+rev pitch",
        sep.pitch_rad.as_ref().unwrap(),
        sep.pitch_rad_u.as_ref().unwrap(),
        &th,
    );
    let p = &sep.params[0];
    let delta = offsets[0] - 2.0 * offsets[1] + offsets[2];
    assert!((p.value - delta).abs() < 3.0 * p.sigma, "{p:?}");
}

#[test]
fn two_probe_recovers_without_pitch_and_shows_the_pitch_it_cannot_see() {
    let mount = ProbeMount { spacing_mm: L };
    let mut rng = Rng(4);
    let st = probe_readings(2, 0.0, &[0.01, -0.02], 1.0, flat_pitch, NOISE, &mut rng);
    let sep = two_probe(&mount, &st).unwrap();
    assert_eq!(sep.part_positions_mm.len(), N + 1);
    assert_eq!(sep.cannot_see, ["line", "pitch"]);
    assert!(sep.pitch_rad.is_none());
    let (yp, xg, _) = truths(&sep, flat_pitch);
    check(
        "2p part",
        &sep.part_straightness_mm,
        &sep.part_straightness_mm_u,
        &yp,
    );
    check(
        "2p guide",
        &sep.guide_straightness_mm,
        &sep.guide_straightness_mm_u,
        &xg,
    );
    // A varying pitch leaks as −l·Σθ, as the note says.
    let st = probe_readings(2, 0.0, &[0.0; 2], 1.0, pitch, 0.0, &mut rng);
    let sep = two_probe(&mount, &st).unwrap();
    let mut cum = vec![0.0];
    for x in stations() {
        let last = *cum.last().unwrap();
        cum.push(last - L * pitch(x));
    }
    let mut leak = cum.clone();
    detrend(&sep.part_positions_mm, &mut leak);
    let want: Vec<f64> = yp.iter().zip(&leak).map(|(a, b)| a + b).collect();
    assert!(rms(diff(&sep.part_straightness_mm, &want).into_iter()) < 1e-10);
}

#[test]
fn shear_two_point_is_sequential_and_removes_the_stage_error() {
    let mut rng = Rng(5);
    let r0 = shear_readings(&[0.0, L], 0.0, 0.0, flat_pitch, &mut rng);
    let mut rng = Rng(5);
    let r1 = shear_readings(&[0.0, L], 0.0, 5e-4, flat_pitch, &mut rng);
    let a = shear_stage(&r0, &ShearOptions::default()).unwrap();
    let b = shear_stage(&r1, &ShearOptions::default()).unwrap();
    assert!(a.method.contains("two-point"), "{}", a.method);
    let (yp, xg, _) = truths(&a, flat_pitch);
    check(
        "shear 2pt part",
        &b.part_straightness_mm,
        &b.part_straightness_mm_u,
        &yp,
    );
    check(
        "shear 2pt guide",
        &b.guide_straightness_mm,
        &b.guide_straightness_mm_u,
        &xg,
    );
    let d = rms(diff(&a.guide_straightness_mm, &b.guide_straightness_mm).into_iter())
        + rms(diff(&a.part_straightness_mm, &b.part_straightness_mm).into_iter());
    assert!(d < 1e-11, "stage error left {d:e}");
    // Against the step: shears {−l, 0}, the same separation by least squares.
    let mut rng = Rng(5);
    let r2 = shear_readings(&[-L, 0.0], 0.0, 5e-4, flat_pitch, &mut rng);
    let c = shear_stage(&r2, &ShearOptions::default()).unwrap();
    assert!(c.method.contains("no pitch"), "{}", c.method);
    assert_eq!(c.cannot_see, ["line", "pitch"]);
    let (yp, xg, _) = truths(&c, flat_pitch);
    check(
        "shear −l part",
        &c.part_straightness_mm,
        &c.part_straightness_mm_u,
        &yp,
    );
    check(
        "shear −l guide",
        &c.guide_straightness_mm,
        &c.guide_straightness_mm_u,
        &xg,
    );
}

#[test]
fn shear_three_point_exact_recovers_and_removes_the_stage_error() {
    let mut rng = Rng(6);
    let r0 = shear_readings(&[-L, 0.0, L], 0.0, 0.0, pitch, &mut rng);
    let mut rng = Rng(6);
    let r1 = shear_readings(&[-L, 0.0, L], 0.0, 3e-4, pitch, &mut rng);
    let a = shear_stage(&r0, &ShearOptions::default()).unwrap();
    let b = shear_stage(&r1, &ShearOptions::default()).unwrap();
    assert!(b.method.contains("on the grid nodes"), "{}", b.method);
    // A curved stage path would be a parabola no reading shows: said.
    assert_eq!(b.cannot_see, ["line", "pitch_constant", "parabola"]);
    assert_eq!(b.part_positions_mm.len(), N + 2);
    assert!((b.part_positions_mm[0] - (X0 - L)).abs() < 1e-9);
    let (yp, xg, th) = truths(&b, pitch);
    check(
        "shear 3pt part",
        &b.part_straightness_mm,
        &b.part_straightness_mm_u,
        &yp,
    );
    check(
        "shear 3pt guide",
        &b.guide_straightness_mm,
        &b.guide_straightness_mm_u,
        &xg,
    );
    check(
        "shear 3pt pitch",
        b.pitch_rad.as_ref().unwrap(),
        b.pitch_rad_u.as_ref().unwrap(),
        &th,
    );
    let d = rms(diff(&a.guide_straightness_mm, &b.guide_straightness_mm).into_iter())
        + rms(diff(&a.part_straightness_mm, &b.part_straightness_mm).into_iter());
    let dp = rms(diff(a.pitch_rad.as_ref().unwrap(), b.pitch_rad.as_ref().unwrap()).into_iter());
    eprintln!("stage error 0.3 mrad: profiles change by {d:e} mm, pitch by {dp:e} rad");
    assert!(d < 1e-10 && dp < 1e-12);
}

#[test]
fn shear_scanning_with_interpolation_recovers() {
    let mut rng = Rng(7);
    // Shears not equal to the step, on a half-step grid, one between nodes, and the
    // stage's sensor reporting a few µm of jitter.
    let r = shear_readings(&[0.0, 10.0, 25.0, 30.0, 40.0], 0.004, 2e-4, pitch, &mut rng);
    let sep = shear_stage(
        &r,
        &ShearOptions {
            grid_mm: Some(10.0),
        },
    )
    .unwrap();
    assert!(sep.method.contains("interpolation"), "{}", sep.method);
    let (yp, xg, th) = truths(&sep, pitch);
    check(
        "shear scan part",
        &sep.part_straightness_mm,
        &sep.part_straightness_mm_u,
        &yp,
    );
    check(
        "shear scan guide",
        &sep.guide_straightness_mm,
        &sep.guide_straightness_mm_u,
        &xg,
    );
    check(
        "shear scan pitch",
        sep.pitch_rad.as_ref().unwrap(),
        sep.pitch_rad_u.as_ref().unwrap(),
        &th,
    );
    eprintln!("shear scan χ² {:?}", sep.chi2_reduced);
}

#[test]
fn recursion_equals_least_squares() {
    let mut rng = Rng(8);
    let st = probe_readings(3, L, &[0.0; 3], 1.0, pitch, NOISE, &mut rng);
    let a = three_probe(&ProbeMount { spacing_mm: L }, &st, None).unwrap();
    let shear: Vec<ShearReading> = st
        .iter()
        .flat_map(|s| {
            s.readings.iter().enumerate().map(move |(j, r)| {
                let r = r.unwrap();
                ShearReading {
                    x_mm: s.x_mm,
                    shear_mm: j as f64 * L,
                    value_mm: r.value_mm,
                    u_mm: r.u_mm,
                }
            })
        })
        .collect();
    let b = shear_stage(&shear, &ShearOptions::default()).unwrap();
    let (pa, pb) = (a.pitch_rad.as_ref().unwrap(), b.pitch_rad.as_ref().unwrap());
    assert!(rms(diff(&a.part_straightness_mm, &b.part_straightness_mm).into_iter()) < 1e-10);
    assert!(rms(diff(pa, pb).into_iter()) < 1e-12);
    // The stage's guide is at A (zero shear), the three-probe's at B: X_A = X_B − θ·l.
    let mut moved: Vec<f64> = a
        .guide_straightness_mm
        .iter()
        .zip(pa)
        .map(|(x, t)| x - t * L)
        .collect();
    detrend(&a.stations_mm, &mut moved);
    assert!(rms(diff(&moved, &b.guide_straightness_mm).into_iter()) < 1e-10);
    let su = diff(&a.part_straightness_mm_u, &b.part_straightness_mm_u);
    assert!(rms(su.into_iter()) < 1e-10);
}

#[test]
fn three_methods_agree_on_the_guide() {
    let mut rng = Rng(9);
    let mount = ProbeMount { spacing_mm: L };
    let s3 = three_probe(
        &mount,
        &probe_readings(3, L, &[0.0; 3], 1.0, flat_pitch, NOISE, &mut rng),
        None,
    )
    .unwrap();
    let s2 = two_probe(
        &mount,
        &probe_readings(2, 0.0, &[0.0; 2], 1.0, flat_pitch, NOISE, &mut rng),
    )
    .unwrap();
    let ss = shear_stage(
        &shear_readings(&[-L, 0.0, L], 0.0, 1e-4, flat_pitch, &mut rng),
        &ShearOptions::default(),
    )
    .unwrap();
    for (name, a, b) in [
        ("3p/2p", &s3, &s2),
        ("3p/shear", &s3, &ss),
        ("2p/shear", &s2, &ss),
    ] {
        let z: Vec<f64> = a
            .guide_straightness_mm
            .iter()
            .zip(&b.guide_straightness_mm)
            .zip(
                a.guide_straightness_mm_u
                    .iter()
                    .zip(&b.guide_straightness_mm_u),
            )
            .map(|((x, y), (u, v))| (x - y) / (u * u + v * v).sqrt())
            .collect();
        let within = z.iter().filter(|v| v.abs() <= 2.0).count() as f64 / z.len() as f64;
        let r = rms(z.iter().copied());
        eprintln!("{name}: RMS normalised difference {r:.2}, within 2σ {within:.2}");
        assert!(r < 2.0 && within >= 0.75, "{name}");
    }
}

/// Monte Carlo: the propagated σ is the scatter of the estimates.
fn monte_carlo(label: &str, runs: usize, f: impl Fn(&mut Rng) -> Separation) {
    let mut z2 = [0.0; 3];
    let (mut inside, mut count) = ([0usize; 3], [0usize; 3]);
    for seed in 0..runs {
        let mut rng = Rng(1000 + seed as u64);
        let sep = f(&mut rng);
        let (yp, xg, th) = truths(&sep, pitch);
        let sets = [
            (&sep.part_straightness_mm, &sep.part_straightness_mm_u, yp),
            (&sep.guide_straightness_mm, &sep.guide_straightness_mm_u, xg),
        ];
        for (i, (e, u, t)) in sets.into_iter().enumerate() {
            for ((a, s), b) in e.iter().zip(u).zip(&t) {
                let z = (a - b) / s;
                z2[i] += z * z;
                inside[i] += (z.abs() <= 2.0) as usize;
                count[i] += 1;
            }
        }
        if let (Some(p), Some(u)) = (&sep.pitch_rad, &sep.pitch_rad_u) {
            for ((a, s), b) in p.iter().zip(u).zip(&th) {
                let z = (a - b) / s;
                z2[2] += z * z;
                inside[2] += (z.abs() <= 2.0) as usize;
                count[2] += 1;
            }
        }
    }
    for (i, what) in ["part", "guide", "pitch"].iter().enumerate() {
        if count[i] == 0 {
            continue;
        }
        let r = (z2[i] / count[i] as f64).sqrt();
        let frac = inside[i] as f64 / count[i] as f64;
        eprintln!("{label} {what}: RMS(error/σ) {r:.2}, within 2σ {frac:.3}");
        assert!((0.8..1.25).contains(&r) && frac > 0.9, "{label} {what}");
    }
}

#[test]
fn propagated_sigma_is_the_scatter() {
    let mount = ProbeMount { spacing_mm: L };
    monte_carlo("3p", 40, |rng| {
        three_probe(
            &mount,
            &probe_readings(3, L, &[0.0; 3], 1.0, pitch, NOISE, rng),
            None,
        )
        .unwrap()
    });
    monte_carlo("2p", 40, |rng| {
        two_probe(
            &mount,
            &probe_readings(2, 0.0, &[0.0; 2], 1.0, flat_pitch, NOISE, rng),
        )
        .unwrap()
    });
    monte_carlo("shear", 30, |rng| {
        shear_stage(
            &shear_readings(&[0.0, 10.0, 20.0, 30.0, 40.0], 0.0, 1e-4, pitch, rng),
            &ShearOptions {
                grid_mm: Some(10.0),
            },
        )
        .unwrap()
    });
}

fn err_text(r: Result<Separation, ProcedureError>) -> String {
    match r {
        Ok(_) => panic!("expected an error"),
        Err(e) => e.to_string(),
    }
}

#[test]
fn bad_input_is_refused_with_a_clear_message() {
    let mount = ProbeMount { spacing_mm: L };
    let mut rng = Rng(10);
    let good = probe_readings(3, L, &[0.0; 3], 1.0, pitch, NOISE, &mut rng);
    // Too few stations.
    let e = err_text(three_probe(&mount, &good[..2], None));
    assert!(
        e.contains("at least 3 stations") && e.contains("has 2"),
        "{e}"
    );
    // Unequal spacing.
    let mut bad = good.clone();
    bad[5].x_mm += 1.0;
    let e = err_text(three_probe(&mount, &bad, None));
    assert!(
        e.contains("step by the probe spacing") && e.contains("station 5"),
        "{e}"
    );
    // A probe missing.
    let mut bad = good.clone();
    bad[7].readings[1] = None;
    let e = err_text(three_probe(&mount, &bad, None));
    assert!(
        e.contains("station 7") && e.contains("probe B has no reading"),
        "{e}"
    );
    // Non-finite readings.
    let mut bad = good.clone();
    bad[3].readings[2] = Some(Reading {
        value_mm: f64::NAN,
        u_mm: 1e-5,
    });
    let e = err_text(three_probe(&mount, &bad, None));
    assert!(
        e.contains("station 3") && e.contains("probe C") && e.contains("not finite"),
        "{e}"
    );
    let mut bad = good.clone();
    bad[3].readings[0] = Some(Reading {
        value_mm: 0.1,
        u_mm: 0.0,
    });
    let e = err_text(three_probe(&mount, &bad, None));
    assert!(e.contains("must be positive"), "{e}");
    // Wrong probe count, bad spacing, short reversal.
    let e = err_text(two_probe(&mount, &good));
    assert!(
        e.contains("has 3 probe readings") && e.contains("needs 2"),
        "{e}"
    );
    let e = err_text(three_probe(
        &ProbeMount {
            spacing_mm: f64::NAN,
        },
        &good,
        None,
    ));
    assert!(e.contains("probe spacing"), "{e}");
    let e = err_text(three_probe(&mount, &good, Some(&good[..10])));
    assert!(e.contains("reversal has 10 stations"), "{e}");
    // Shear stage: non-finite, too few stations, one shear, undetermined layout.
    let mut r = shear_readings(&[0.0, L, 2.0 * L], 0.0, 0.0, pitch, &mut rng);
    let keep = r.clone();
    r[4].value_mm = f64::INFINITY;
    let e = err_text(shear_stage(&r, &ShearOptions::default()));
    assert!(
        e.contains("shear reading 4") && e.contains("not finite"),
        "{e}"
    );
    let e = err_text(shear_stage(&keep[..6], &ShearOptions::default()));
    assert!(
        e.contains("at least 3 carriage stations") && e.contains("have 2"),
        "{e}"
    );
    let one: Vec<ShearReading> = keep
        .iter()
        .filter(|r| r.shear_mm != L || r.x_mm != X0 + L)
        .copied()
        .collect();
    let one: Vec<ShearReading> = one
        .into_iter()
        .filter(|r| r.x_mm != X0 + L || r.shear_mm == 0.0)
        .collect();
    let e = err_text(shear_stage(&one, &ShearOptions::default()));
    assert!(
        e.contains("single shear") && e.contains("x = 70.0000"),
        "{e}"
    );
    let r = shear_readings(&[0.0, L, 3.0 * L], 0.0, 0.0, pitch, &mut rng);
    let e = err_text(shear_stage(&r, &ShearOptions::default()));
    assert!(
        e.contains("undetermined") && e.contains("add a shear"),
        "{e}"
    );
    let e = err_text(shear_stage(
        &keep,
        &ShearOptions {
            grid_mm: Some(-1.0),
        },
    ));
    assert!(e.contains("grid pitch"), "{e}");
}

#[test]
fn averaging_is_robust() {
    let mut rng = Rng(11);
    let mut s: Vec<f64> = (0..200).map(|_| 1.0 + 1e-4 * rng.gauss()).collect();
    s[17] = 5.0;
    s[40] = f64::NAN;
    let a = average_samples(&s).unwrap();
    assert_eq!((a.used, a.rejected), (198, 2));
    assert!((a.reading.value_mm - 1.0).abs() < 3.0 * a.reading.u_mm);
    assert!(
        (a.reading.u_mm / (1e-4 / 198f64.sqrt()) - 1.0).abs() < 0.35,
        "{a:?}"
    );
    // A slow drift (correlated samples) inflates the standard error.
    let d: Vec<f64> = (0..200)
        .map(|i| (i as f64 * 0.05).sin() * 1e-4 + 1e-6 * rng.gauss())
        .collect();
    let b = average_samples(&d).unwrap();
    let plain = {
        let m = d.iter().sum::<f64>() / 200.0;
        (d.iter().map(|v| (v - m).powi(2)).sum::<f64>() / 199.0 / 200.0).sqrt()
    };
    assert!(b.reading.u_mm > 3.0 * plain);
    let e = average_samples(&[1.0, f64::NAN]).unwrap_err().to_string();
    assert!(e.contains("at least 2"), "{e}");
}

/// LS coefficient of i² of (i, y_i), i = 0, 1, … (independently of `three.rs`: the normal
/// equations of [1, t, t²], t = i − the mean index).
fn quadratic_coefficient(y: &[f64]) -> f64 {
    let mut m = nalgebra::Matrix3::<f64>::zeros();
    let mut b = nalgebra::Vector3::<f64>::zeros();
    // Centred (the same i² coefficient; the normal matrix better conditioned).
    let c = (y.len() as f64 - 1.0) / 2.0;
    let ym = y.iter().sum::<f64>() / y.len() as f64;
    for (i, v) in y.iter().map(|v| v - ym).enumerate() {
        let t = i as f64 - c;
        let r = nalgebra::Vector3::new(1.0, t, t * t);
        m += r * r.transpose();
        b += r * v;
    }
    (m.try_inverse().unwrap() * b)[2]
}

#[test]
fn without_a_reversal_the_stated_bow_fixes_the_offsets_parabola() {
    let offsets = [0.8e-3, 1.3e-3, 1.5e-3];
    let delta = offsets[0] - 2.0 * offsets[1] + offsets[2];
    let mount = ProbeMount { spacing_mm: L };
    let mut rng = Rng(11);
    // Noise-free: δ̂ = δ + 2q, q the true part's least-squares parabola (in the point index).
    let st = probe_readings(3, L, &offsets, 1.0, pitch, 0.0, &mut rng);
    let bound = 4e-3;
    let opts = ThreeProbeOptions {
        straightedge_bow_mm: Some(bound),
        probe_zero_mm: None,
    };
    let sep = three_probe_with(&mount, &st, None, &opts).unwrap();
    let y: Vec<f64> = sep.part_positions_mm.iter().map(|&x| part(x)).collect();
    let q = quadratic_coefficient(&y);
    let d = &sep.params[0];
    assert_eq!(d.name, "probe_offsets.second_difference_mm");
    assert!(
        (d.value - (delta + 2.0 * q)).abs() < 1e-12,
        "{} vs {}",
        d.value,
        delta + 2.0 * q
    );
    assert_eq!(sep.params[1].name, "probe_offsets.beta_rad");
    assert!((sep.params[1].value - d.value / L).abs() < 1e-15);
    assert!(
        !sep.cannot_see.iter().any(|c| c == "parabola"),
        "{:?}",
        sep.cannot_see
    );
    // σ: the stated bound's, 2·(B/√3)/((N+1)/2)² with N + 2 part points.
    let half = (N + 1) as f64 / 2.0;
    let sp = 2.0 * bound / 3f64.sqrt() / (half * half);
    // (plus the 0.1 µm floor of these noise-free readings' u through the recursion).
    assert!(
        d.sigma >= sp && d.sigma < 1.001 * sp,
        "σ {} vs {sp}",
        d.sigma
    );
    // What is left: the part's own parabola, on the guide with its sign changed; honest.
    let (yp, xg, _) = truths(&sep, pitch);
    let eg = diff(&sep.guide_straightness_mm, &xg);
    let ep = diff(&sep.part_straightness_mm, &yp);
    let (rg, rp) = (rms(eg.iter().copied()), rms(ep.iter().copied()));
    let ug = rms(sep.guide_straightness_mm_u.iter().copied());
    eprintln!("stated bow: guide off by {rg:e} mm RMS (σ {ug:e}), part {rp:e}");
    assert!(rg <= 2.0 * ug && rg > 0.0, "{rg} vs σ {ug}");
    // Without the bound the parabola is δ's; with it, q's: smaller here (δ ≫ 2q).
    let plain = three_probe(&mount, &st, None).unwrap();
    let rg0 = rms(diff(&plain.guide_straightness_mm, &xg).into_iter());
    assert!(rg < 0.2 * rg0, "{rg} vs {rg0} without the bound");
    // With the zeroing's bound too: a weighted mean, between 0 and the bow's estimate.
    let both = three_probe_with(
        &mount,
        &st,
        None,
        &ThreeProbeOptions {
            straightedge_bow_mm: Some(bound),
            probe_zero_mm: Some(2e-3),
        },
    )
    .unwrap();
    let v = both.params[0].value;
    assert!(
        v.abs() < d.value.abs() && v * d.value > 0.0,
        "{v} vs {}",
        d.value
    );
    assert!(both.params[0].sigma < d.sigma);
    // Noisy readings: the σ include the noise.
    let st = probe_readings(3, L, &offsets, 1.0, pitch, NOISE, &mut rng);
    let noisy = three_probe_with(&mount, &st, None, &opts).unwrap();
    assert!(noisy.params[0].sigma > d.sigma);
    let (yp, xg, _) = truths(&noisy, pitch);
    check(
        "3p+bow part",
        &noisy.part_straightness_mm,
        &noisy.part_straightness_mm_u,
        &yp,
    );
    check(
        "3p+bow guide",
        &noisy.guide_straightness_mm,
        &noisy.guide_straightness_mm_u,
        &xg,
    );
}

#[test]
fn the_stated_bounds_are_checked() {
    let offsets = [0.0; 3];
    let mount = ProbeMount { spacing_mm: L };
    let mut rng = Rng(12);
    let st = probe_readings(3, L, &offsets, 1.0, pitch, NOISE, &mut rng);
    let rev = probe_readings(3, L, &offsets, -1.0, flat_pitch, NOISE, &mut rng);
    let o = |b: Option<f64>, z: Option<f64>| ThreeProbeOptions {
        straightedge_bow_mm: b,
        probe_zero_mm: z,
    };
    let e = err_text(three_probe_with(
        &mount,
        &st,
        Some(&rev),
        &o(Some(1e-3), None),
    ));
    assert!(e.contains("either the reversal"), "{e}");
    let e = err_text(three_probe_with(&mount, &st, None, &o(None, Some(1e-3))));
    assert!(e.contains("bow bound too"), "{e}");
    for bad in [0.0, -1e-3, f64::NAN] {
        let e = err_text(three_probe_with(&mount, &st, None, &o(Some(bad), None)));
        assert!(e.contains("bow bound must be a positive length"), "{e}");
        assert!(!e.contains("NaN"), "{e}");
    }
}

/// Readings of one probe on the stage, carriage stepping by `step` from X0 over `n` stations,
/// shears `shears` at each and `start` more at the first; a stage path c·s².
fn unequal_readings(
    step: f64,
    n: usize,
    shears: &[f64],
    start: &[f64],
    path_c: f64,
    noise: f64,
    rng: &mut Rng,
) -> Vec<ShearReading> {
    let mut out = vec![];
    for k in 0..n {
        let x = X0 + k as f64 * step;
        let extra: &[f64] = if k == 0 { start } else { &[] };
        for &s in shears.iter().chain(extra) {
            let v = part(x + s) - guide(x) - pitch(x) * s
                + 3e-4 * s
                + path_c * s * s
                + 0.02
                + noise * rng.gauss();
            out.push(ShearReading {
                x_mm: x,
                shear_mm: s,
                value_mm: v,
                u_mm: noise.max(1e-7),
            });
        }
    }
    out
}

/// Two unequal shears (0, 20, 30 mm at a 10 mm step; the NUDT form): refused without the
/// start station, with the station to add named; exact with it (noise-free to 1e-9 mm),
/// within the propagated σ with noise; a curved stage path flagged as the parabola it makes,
/// its stated size the profiles' actual change.
#[test]
fn two_unequal_shears_are_exact_from_a_start_station() {
    let (h, n) = (10.0, 50);
    let mut rng = Rng(31);
    let bare = unequal_readings(h, n, &[0.0, 20.0, 30.0], &[], 0.0, 0.0, &mut rng);
    let e = err_text(shear_stage(&bare, &ShearOptions::default()));
    assert!(
        e.contains("undetermined") && e.contains("start values") && e.contains("10.000"),
        "{e}"
    );
    let exact = unequal_readings(h, n, &[0.0, 20.0, 30.0], &[10.0], 0.0, 0.0, &mut rng);
    let sep = shear_stage(&exact, &ShearOptions::default()).unwrap();
    assert!(sep.method.contains("on the grid nodes"), "{}", sep.method);
    assert!(sep.notes[1].contains("exact"), "{}", sep.notes[1]);
    let (yp, xg, th) = truths(&sep, pitch);
    let err = rms(diff(&sep.part_straightness_mm, &yp).into_iter())
        + rms(diff(&sep.guide_straightness_mm, &xg).into_iter());
    let errp = rms(diff(sep.pitch_rad.as_ref().unwrap(), &th).into_iter());
    assert!(
        err < 1e-9 && errp < 1e-12,
        "noise-free: {err:e} mm, {errp:e} rad"
    );
    // With noise: within the σ.
    let noisy = unequal_readings(h, n, &[0.0, 20.0, 30.0], &[10.0], 0.0, NOISE, &mut rng);
    let sep = shear_stage(&noisy, &ShearOptions::default()).unwrap();
    check(
        "unequal part",
        &sep.part_straightness_mm,
        &sep.part_straightness_mm_u,
        &yp,
    );
    check(
        "unequal guide",
        &sep.guide_straightness_mm,
        &sep.guide_straightness_mm_u,
        &xg,
    );
    check(
        "unequal pitch",
        sep.pitch_rad.as_ref().unwrap(),
        sep.pitch_rad_u.as_ref().unwrap(),
        &th,
    );
    // A stage path with 10 nm of sagitta over the shears 0 … 30 mm: c = 4·b/30².
    let c = 4.0 * 1e-5 / 900.0;
    let bent = unequal_readings(h, n, &[0.0, 20.0, 30.0], &[10.0], c, 0.0, &mut rng);
    let sb = shear_stage(&bent, &ShearOptions::default()).unwrap();
    assert!(sb.cannot_see.iter().any(|c| c == "parabola"));
    let d = diff(&sb.part_straightness_mm, &yp);
    let pv =
        d.iter().copied().fold(f64::MIN, f64::max) - d.iter().copied().fold(f64::MAX, f64::min);
    let note = sb
        .notes
        .iter()
        .find(|t| t.contains("sagitta"))
        .expect("the path's note");
    let quoted = format!("{:.3} µm peak-to-valley on the part", pv * 1e3);
    assert!(note.contains(&quoted), "{quoted}: {note}");
    assert!(pv > 0.5e-3, "10 nm of sagitta is a large parabola: {pv}");
}
