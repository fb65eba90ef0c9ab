//! Straightness error-separation measurements: distance probes on the X carriage facing a
//! straightedge that lies along X, stepped along the travel.
//!
//! The physics, modelled here and nowhere in the corrector:
//! * The carriage runs on the machine's own X guide ([`TrueMachine::guide_y`] sideways
//!   towards y, [`TrueMachine::guide_pitch`] its yaw about z): at carriage position x the
//!   ram axis is displaced by g(x) towards +y and the carriage turned by θ(x), so a point of
//!   the mount at lever s along x from the ram axis moves by g(x) + θ(x)·s towards +y.
//! * The straightedge (its face at y_f, normal −y) has a form of its own, not below the
//!   noise: a bow (a few µm of sag) and waviness (0.3–1 µm at 60–250 mm), and it is set up
//!   with a small tilt and offset.
//! * A probe at lever s reads the gap from its tip to the face along +y: the face's form
//!   at x + s less the mount's displacement, plus its zero offset (what zeroing on an optical
//!   flat leaves: ±0.2 µm), plus noise, quantised.
//! * The shear micro-stage carries one probe along x by a commanded shear; it reaches it
//!   with a scale error of its own and travels at a small angle φ to the x axis (its
//!   perpendicular zero-adjustment error: the probe moves φ·s towards +y); its displacement
//!   sensor reads the real shear with a few nm of noise.
//!
//! At each station the carriage moves, settles and dwells while every probe (and, for the
//! stage, every shear in turn) is read at the sample rate; the scales stream throughout.

use crate::machine::{profile, TrueMachine, Wave};
use crate::rng::Rng;
use serde::{Deserialize, Serialize};

/// The separation programs.
pub const PROGRAMS: [&str; 4] = [
    "straightness-three-probe",
    "straightness-two-probe",
    "straightness-shear-stage",
    "straightness-shear-unequal",
];

/// What the mount carries and how the carriage steps.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Setup {
    /// Program name.
    pub program: String,
    /// Levers of the fixed probes along x from the ram axis, mm (ids 1, 2, …).
    pub probe_levers_mm: Vec<f64>,
    /// Shears the stage takes at every station, mm (empty: no stage); the stage carries
    /// probe 1 at lever 0.
    pub shears_mm: Vec<f64>,
    /// Shears the stage takes at the first station besides `shears_mm`, mm (two unequal
    /// shears: the recursion's start values).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub start_shears_mm: Vec<f64>,
    /// Carriage step between stations, mm.
    pub step_mm: f64,
    /// Carriage positions of the stations, mm.
    pub stations_mm: Vec<f64>,
}

impl Setup {
    /// The setup of `program`.
    pub fn of(program: &str) -> Result<Setup, String> {
        let stations = |lo: f64, hi: f64, step: f64| -> Vec<f64> {
            let n = ((hi - lo) / step).round() as usize;
            (0..=n).map(|k| lo + step * k as f64).collect()
        };
        Ok(match program {
            "straightness-three-probe" => Setup {
                program: program.into(),
                probe_levers_mm: vec![-25.0, 0.0, 25.0],
                shears_mm: vec![],
                start_shears_mm: vec![],
                step_mm: 25.0,
                stations_mm: stations(175.0, 825.0, 25.0),
            },
            "straightness-two-probe" => Setup {
                program: program.into(),
                probe_levers_mm: vec![0.0, 25.0],
                shears_mm: vec![],
                start_shears_mm: vec![],
                step_mm: 25.0,
                stations_mm: stations(150.0, 825.0, 25.0),
            },
            "straightness-shear-stage" => Setup {
                program: program.into(),
                probe_levers_mm: vec![0.0],
                // The step (the two-point method), and twice the step (with it, the exact
                // three-point reconstruction).
                shears_mm: vec![0.0, 20.0, 40.0],
                start_shears_mm: vec![],
                step_mm: 20.0,
                stations_mm: stations(150.0, 810.0, 20.0),
            },
            "straightness-shear-unequal" => Setup {
                program: program.into(),
                probe_levers_mm: vec![0.0],
                // Two unequal shears, 2 and 3 carriage steps (NUDT's single-probe form), and
                // at the first station the step too: the recursion's start values.
                shears_mm: vec![0.0, 20.0, 30.0],
                start_shears_mm: vec![10.0],
                step_mm: 10.0,
                stations_mm: stations(150.0, 800.0, 10.0),
            },
            _ => {
                return Err(format!(
                    "unknown separation program `{program}` (known: {})",
                    PROGRAMS.join(", ")
                ))
            }
        })
    }
}

/// The straightedge: where it lies and its form.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Straightedge {
    /// Face position along y at x = 500 mm, mm.
    pub face_y_mm: f64,
    /// Set-up tilt of the face, rad (a line: no method sees it).
    pub tilt_rad: f64,
    /// Sag of the bow over its span, mm (positive: the middle stands further from the
    /// mount, the gap is larger there).
    pub bow_mm: f64,
    /// The bow's ends, mm.
    pub span_mm: [f64; 2],
    /// Waviness.
    pub waves: Vec<Wave>,
    /// Across the face (z), for a surface measured in lines: the face's bow along z (its
    /// sag over ±50 mm of the middle line, zero on it), mm.
    #[serde(default)]
    pub bow_z_mm: f64,
    /// Twist: the height at (x − 500 mm = 400 mm, z − z_middle = 50 mm), mm.
    #[serde(default)]
    pub twist_mm: f64,
}

impl Straightedge {
    fn from_seed(seed: u64) -> Straightedge {
        let mut r = Rng::new(seed, "straightedge");
        let sign = |r: &mut Rng| if r.uniform() < 0.5 { -1.0 } else { 1.0 };
        let bow_mm = sign(&mut r) * r.range(2.0e-3, 4.0e-3);
        let waves = (0..3)
            .map(|_| Wave {
                amplitude: sign(&mut r) * r.range(0.3e-3, 1.0e-3),
                wavelength_mm: r.range(60.0, 250.0),
                phase: r.range(0.0, std::f64::consts::TAU),
            })
            .collect();
        // Across the face: its own stream, so the straightedge along its length is as before.
        let mut rz = Rng::new(seed, "straightedge-across");
        Straightedge {
            face_y_mm: 700.0 + r.range(-0.5, 0.5),
            tilt_rad: r.range(-40e-6, 40e-6),
            bow_mm,
            span_mm: [100.0, 900.0],
            waves,
            bow_z_mm: sign(&mut rz) * rz.range(0.5e-3, 1.5e-3),
            twist_mm: sign(&mut rz) * rz.range(0.5e-3, 1.5e-3),
        }
    }
    /// The face's form at (x, dz), dz from the middle line, mm: the flatness a surface
    /// measured in lines shows (about its plane).
    pub fn surface_mm(&self, x: f64, dz: f64) -> f64 {
        let v = dz / 50.0;
        self.form_mm(x) + self.bow_z_mm * v * v + self.twist_mm * (x - 500.0) / 400.0 * v
    }
    /// The face's form (bow and waviness) at x, mm: the part straightness the methods
    /// recover (up to the line none can see).
    pub fn form_mm(&self, x: f64) -> f64 {
        let [a, b] = self.span_mm;
        let u = 2.0 * (x - a) / (b - a) - 1.0;
        self.bow_mm * (1.0 - u * u) + profile(&self.waves, x)
    }
    /// The face's position along y at x, mm.
    pub fn face_y(&self, x: f64) -> f64 {
        self.face_y_mm + self.tilt_rad * (x - 500.0) + self.form_mm(x)
    }
}

/// Probes and stage as built.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Instruments {
    /// Zero offset of each probe left after zeroing, mm.
    pub probe_offsets_mm: Vec<f64>,
    /// Noise of one probe reading (1σ), mm.
    pub probe_noise_mm: f64,
    /// Resolution of a probe reading, mm.
    pub probe_resolution_mm: f64,
    /// Scale error of the stage (relative), so a commanded shear is not the real one.
    pub stage_scale_error: f64,
    /// Angle of the stage's travel to the x axis, rad: the probe moves φ·s towards +y.
    pub stage_perpendicular_rad: f64,
    /// Noise of the stage's displacement sensor (1σ), mm.
    pub stage_sensor_noise_mm: f64,
}

impl Instruments {
    fn from_seed(seed: u64, probes: usize) -> Instruments {
        let mut r = Rng::new(seed, "separation-instruments");
        Instruments {
            probe_offsets_mm: (0..probes).map(|_| r.range(-0.2e-3, 0.2e-3)).collect(),
            probe_noise_mm: 0.05e-3,
            probe_resolution_mm: 1e-6,
            stage_scale_error: r.range(-2e-3, 2e-3),
            stage_perpendicular_rad: r.range(30e-6, 80e-6)
                * if r.uniform() < 0.5 { -1.0 } else { 1.0 },
            stage_sensor_noise_mm: 2e-6,
        }
    }
}

/// One sample of the measurement, in time order.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Reading {
    /// The carriage's scales, mm.
    Scale {
        /// Sequence number of the stream.
        seq: u64,
        /// Time, ns.
        t_ns: i64,
        /// Scale readings x, y, z, mm.
        pos: [f64; 3],
    },
    /// One distance probe.
    Distance {
        /// Sequence number of the stream.
        seq: u64,
        /// Time, ns.
        t_ns: i64,
        /// Probe id (1, 2, …).
        probe_id: u32,
        /// The reading, mm.
        distance_mm: f64,
        /// The probe's lever along x from the mount's reference (the ram axis), as
        /// mounted, mm (for the stage's probe: its lever at zero shear).
        spacing_mm: f64,
    },
    /// The micro-stage.
    Stage {
        /// Sequence number of the stream.
        seq: u64,
        /// Time, ns.
        t_ns: i64,
        /// The probe it carries.
        probe_id: u32,
        /// Where the stage was told to go, mm.
        commanded_mm: f64,
        /// What its own displacement sensor reads, mm.
        sensor_mm: f64,
    },
}

/// The truth of a separation run, under the names `scancorr calibrate straightness` prints.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SeparationTruth {
    /// The program and its setup.
    pub setup: Setup,
    /// Carriage positions of the stations, mm.
    pub stations_mm: Vec<f64>,
    /// The guide's straightness towards +y at the stations (the ram axis's displacement), mm.
    pub guide_straightness_mm: Vec<f64>,
    /// The carriage's yaw about z at the stations, rad.
    pub pitch_rad: Vec<f64>,
    /// Where the probes touched the straightedge, mm (every station's x plus each lever
    /// and shear), sorted.
    pub part_positions_mm: Vec<f64>,
    /// The straightedge's form at `part_positions_mm`, mm (the bow and waviness; no set-up
    /// line): what the methods recover as the part's straightness.
    pub part_straightness_mm: Vec<f64>,
    /// True for the reversal measurement (the form read with the opposite sign).
    pub reversal: bool,
    /// With lines stepped across: each line's z (mm) and the face's form at
    /// `part_positions_mm` on it (mm).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub lines: Vec<(f64, Vec<f64>)>,
    /// Noise of one probe reading (1σ), mm.
    pub probe_noise_mm: f64,
    /// Readings averaged per probe (and shear) at each station.
    pub samples_per_reading: usize,
    /// The straightedge.
    pub straightedge: Straightedge,
    /// Probes and stage.
    pub instruments: Instruments,
}

/// Options of a separation run.
#[derive(Debug, Clone, PartialEq)]
pub struct SeparationOptions {
    /// Program (one of [`PROGRAMS`]).
    pub program: String,
    /// Machine seed: the guide.
    pub machine_seed: u64,
    /// Run seed: the straightedge, the instruments, the noise.
    pub seed: u64,
    /// Sample rate, Hz.
    pub rate_hz: f64,
    /// Scale of the guide's errors (the simulator's `guide_straightness` factor).
    pub guide_factor: f64,
    /// The reversal measurement: the straightedge turned over about its length (its form
    /// seen with the opposite sign), the same stations, probes and offsets.
    pub reversal: bool,
    /// Lines stepped across the face along z, 25 mm apart about the middle one (1: one
    /// line, the straightedge's): a surface for its flatness.
    pub lines: usize,
}

/// Runs the measurement, handing every reading (in time order) to `sink`.
pub fn run(
    o: &SeparationOptions,
    mut sink: impl FnMut(Reading),
) -> Result<SeparationTruth, String> {
    if !(o.rate_hz.is_finite() && (10.0..=100_000.0).contains(&o.rate_hz)) {
        return Err("--rate must be between 10 and 100000 Hz".into());
    }
    if !(o.guide_factor.is_finite() && o.guide_factor >= 0.0) {
        return Err("the guide's effect scale must be a finite number ≥ 0".into());
    }
    let setup = Setup::of(&o.program)?;
    if o.reversal && setup.probe_levers_mm.len() != 3 {
        return Err(format!(
            "--reversal: only the three-probe method uses a reversal (it separates the \
             probes' zero offsets); `{}` has none",
            o.program
        ));
    }
    let flip = if o.reversal { -1.0 } else { 1.0 };
    if !(1..=21).contains(&o.lines) {
        return Err(format!("--lines {}: 1 to 21", o.lines));
    }
    if o.lines > 1 && o.reversal {
        return Err("--lines with --reversal: the reversal is of the first line only".into());
    }
    let dz_of = |j: usize| (j as f64 - (o.lines - 1) as f64 / 2.0) * 25.0;
    let m = TrueMachine::from_seed(o.machine_seed);
    let g = |x: f64| o.guide_factor * profile(&m.guide_y, x);
    let th = |x: f64| o.guide_factor * profile(&m.guide_pitch, x);
    let edge = Straightedge::from_seed(o.seed);
    let n_probes = setup.probe_levers_mm.len();
    let inst = Instruments::from_seed(o.seed, n_probes);
    let mut noise = Rng::new(
        o.seed,
        if o.reversal {
            "separation-noise-reversal"
        } else {
            "separation-noise"
        },
    );
    let dt = 1.0 / o.rate_hz;
    let (move_s, settle_s, dwell_s) = (1.0, 0.3, 1.0);
    let (y0, z_mid) = (edge.face_y_mm - 60.0, -250.0);
    let mut t = 0.0;
    let (mut seq_s, mut seq_d, mut seq_g) = (0u64, 0u64, 0u64);
    let ns = |t: f64| (t * 1e9).round() as i64;
    let mut x = setup.stations_mm[0] - setup.step_mm;
    let quant = |v: f64, q: f64| if q > 0.0 { (v / q).round() * q } else { v };
    let mut per_reading = 0;
    let mut stage_at = 0.0;
    let mut stage_noise = Rng::new(o.seed, "separation-stage-sensor");
    let gap = |x_carriage: f64, lever: f64, perp: f64, dz: f64| -> f64 {
        let xs = x_carriage + lever;
        let mount_y = y0 + g(x_carriage) + th(x_carriage) * lever + perp;
        edge.face_y_mm + edge.tilt_rad * (xs - 500.0) + flip * edge.surface_mm(xs, dz) - mount_y
    };
    // The scales, as they stream.
    let scale_reading = |seq: &mut u64, t: f64, x: f64, z: f64| {
        let r = Reading::Scale {
            seq: *seq,
            t_ns: ns(t),
            pos: [x, y0, z],
        };
        *seq += 1;
        r
    };
    for (line, &xk) in (0..o.lines).flat_map(|j| setup.stations_mm.iter().map(move |x| (j, x))) {
        let dz = dz_of(line);
        let z0 = z_mid + dz;
        // Move (a smooth step), settle.
        let x_from = x;
        let steps = ((move_s + settle_s) / dt).round() as usize;
        for i in 0..steps {
            let u = ((i as f64 * dt) / move_s).min(1.0);
            x = x_from + (xk - x_from) * (3.0 * u * u - 2.0 * u * u * u);
            sink(scale_reading(&mut seq_s, t, x, z0));
            t += dt;
        }
        x = xk;
        // Dwell: every probe, or every shear of the stage in turn.
        let shears: Vec<Option<f64>> = if setup.shears_mm.is_empty() {
            vec![None]
        } else {
            let mut v = setup.shears_mm.clone();
            if xk == setup.stations_mm[0] {
                v.extend_from_slice(&setup.start_shears_mm);
                v.sort_by(f64::total_cmp);
            }
            v.into_iter().map(Some).collect()
        };
        for shear in shears {
            let real_shear = shear.map(|s| s * (1.0 + inst.stage_scale_error));
            // The stage's sensor, as it streams: the stage where it really is, with noise.
            let mut stage_reading = |t: f64, commanded: f64, at: f64, seq: &mut u64| {
                let r = Reading::Stage {
                    seq: *seq,
                    t_ns: ns(t),
                    probe_id: 1,
                    commanded_mm: commanded,
                    sensor_mm: at + inst.stage_sensor_noise_mm * stage_noise.normal(),
                };
                *seq += 1;
                r
            };
            if let (Some(s), Some(target)) = (shear, real_shear) {
                // The stage moves (a smooth step over 0.2 s), its sensor streams throughout.
                let from = stage_at;
                let steps = (0.2 / dt).round() as usize;
                for i in 0..steps {
                    let u = (i + 1) as f64 / steps as f64;
                    let at = from + (target - from) * (3.0 * u * u - 2.0 * u * u * u);
                    sink(stage_reading(t, s, at, &mut seq_g));
                    sink(scale_reading(&mut seq_s, t, x, z0));
                    t += dt;
                }
                stage_at = target;
            }
            let steps = (dwell_s / dt).round() as usize;
            per_reading = steps;
            for _ in 0..steps {
                let tn = ns(t);
                sink(scale_reading(&mut seq_s, t, x, z0));
                if let Some(s) = shear {
                    sink(stage_reading(t, s, stage_at, &mut seq_g));
                }
                for (j, lever) in setup.probe_levers_mm.iter().enumerate() {
                    let (lever_now, perp) = match real_shear {
                        Some(s) => (lever + s, inst.stage_perpendicular_rad * s),
                        None => (*lever, 0.0),
                    };
                    let d = gap(x, lever_now, perp, dz) - gap(0.0, 0.0, 0.0, 0.0)
                        + inst.probe_offsets_mm[j]
                        + inst.probe_noise_mm * noise.normal();
                    sink(Reading::Distance {
                        seq: seq_d,
                        t_ns: tn,
                        probe_id: j as u32 + 1,
                        distance_mm: quant(d, inst.probe_resolution_mm),
                        spacing_mm: *lever,
                    });
                    seq_d += 1;
                }
                t += dt;
            }
        }
    }
    let st = &setup.stations_mm;
    let mut part: Vec<f64> = vec![];
    for x in st {
        for l in &setup.probe_levers_mm {
            if setup.shears_mm.is_empty() {
                part.push(x + l);
            }
            for s in setup.shears_mm.iter().chain(&setup.start_shears_mm) {
                part.push(x + l + s);
            }
        }
    }
    part.sort_by(f64::total_cmp);
    part.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
    Ok(SeparationTruth {
        stations_mm: st.clone(),
        guide_straightness_mm: st.iter().map(|x| g(*x)).collect(),
        pitch_rad: st.iter().map(|x| th(*x)).collect(),
        part_positions_mm: part.clone(),
        part_straightness_mm: part.iter().map(|x| edge.form_mm(*x)).collect(),
        reversal: o.reversal,
        lines: if o.lines > 1 {
            (0..o.lines)
                .map(|j| {
                    let dz = dz_of(j);
                    (
                        z_mid + dz,
                        part.iter().map(|x| edge.surface_mm(*x, dz)).collect(),
                    )
                })
                .collect()
        } else {
            vec![]
        },
        probe_noise_mm: inst.probe_noise_mm,
        samples_per_reading: per_reading,
        setup,
        straightedge: edge,
        instruments: inst,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn collect(program: &str) -> (Vec<Reading>, SeparationTruth) {
        let mut v = vec![];
        let t = run(
            &SeparationOptions {
                program: program.into(),
                machine_seed: 3,
                seed: 4,
                rate_hz: 200.0,
                guide_factor: 1.0,
                reversal: false,
                lines: 1,
            },
            |r| v.push(r),
        )
        .unwrap();
        (v, t)
    }

    /// The readings are the gap geometry: with the noise averaged out, three probes'
    /// second difference at a station is the form's second difference plus the offsets'
    /// (the carriage's displacement and yaw cancel exactly).
    #[test]
    fn three_probes_see_the_form_not_the_carriage() {
        let (v, t) = collect("straightness-three-probe");
        let l = t.setup.step_mm;
        let mut sum = vec![[0.0; 3]; t.stations_mm.len()];
        let mut n = vec![[0usize; 3]; t.stations_mm.len()];
        let mut xnow = 0.0;
        for r in &v {
            match r {
                Reading::Scale { pos, .. } => xnow = pos[0],
                Reading::Distance {
                    probe_id,
                    distance_mm,
                    ..
                } => {
                    let k = t
                        .stations_mm
                        .iter()
                        .position(|s| (s - xnow).abs() < 1e-9)
                        .expect("read at a station");
                    sum[k][*probe_id as usize - 1] += distance_mm;
                    n[k][*probe_id as usize - 1] += 1;
                }
                Reading::Stage { .. } => panic!("no stage here"),
            }
        }
        let o = &t.instruments.probe_offsets_mm;
        for (k, x) in t.stations_mm.iter().enumerate() {
            let m: Vec<f64> = (0..3).map(|j| sum[k][j] / n[k][j] as f64).collect();
            let second = m[0] - 2.0 * m[1] + m[2];
            let e = &t.straightedge;
            let want = e.form_mm(x - l) - 2.0 * e.form_mm(*x)
                + e.form_mm(x + l)
                + (o[0] - 2.0 * o[1] + o[2]);
            assert!((second - want).abs() < 0.03e-3, "{k}: {second} vs {want}");
        }
        // A form of a few µm, not below the noise.
        assert_eq!(t.part_positions_mm.len(), t.stations_mm.len() + 2);
        let f = &t.part_straightness_mm;
        let pv =
            f.iter().cloned().fold(f64::MIN, f64::max) - f.iter().cloned().fold(f64::MAX, f64::min);
        assert!(pv > 1.5e-3, "form {pv} mm");
    }

    #[test]
    fn the_stage_sensor_reads_the_real_shear() {
        let (v, t) = collect("straightness-shear-stage");
        let k = 1.0 + t.instruments.stage_scale_error;
        // While the probe reads (the stage stands), the sensor reads the real shear; while
        // the stage moves, its travel.
        let reading_at: std::collections::BTreeSet<i64> = v
            .iter()
            .filter_map(|r| match r {
                Reading::Distance { t_ns, .. } => Some(*t_ns),
                _ => None,
            })
            .collect();
        let (mut standing, mut moving) = (0, 0);
        for r in &v {
            if let Reading::Stage {
                t_ns,
                commanded_mm,
                sensor_mm,
                ..
            } = r
            {
                if reading_at.contains(t_ns) {
                    assert!((sensor_mm - commanded_mm * k).abs() < 20e-6);
                    standing += 1;
                } else if (sensor_mm - commanded_mm * k).abs() > 1e-3 {
                    moving += 1;
                }
            }
        }
        assert!(standing > 100 && moving > 10, "{standing} {moving}");
        assert!(run(
            &SeparationOptions {
                program: "straightness-four-probe".into(),
                machine_seed: 1,
                seed: 1,
                rate_hz: 100.0,
                guide_factor: 1.0,
                reversal: false,
                lines: 1,
            },
            |_| {}
        )
        .unwrap_err()
        .contains("straightness-three-probe"));
    }
}
