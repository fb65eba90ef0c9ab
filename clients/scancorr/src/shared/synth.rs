//! Synthetic input for the benchmark and the first demo: a probe scanning the inside of ring
//! gauges at several speeds, with ideal scales (no machine physics — that is the simulator's
//! job). Deterministic.

use scancorr_core::effects::*;
use scancorr_core::sample::*;
use scancorr_core::Calibration;

/// A calibration with every effect of the library enabled (small parameters).
pub fn all_effects_calibration(machine: &str) -> Calibration {
    let mut c = Calibration::example(machine);
    let mut ad = accel_deflection::Config::zeros(2, false);
    ad.p[0] = [[2e-6, 1e-7, 0.0], [1e-7, 3e-6, 0.0], [0.0, 0.0, 1e-6]];
    ad.p[1][0][0] = 5e-7;
    c.effects.push(EffectConfig::AccelDeflection(ad));
    let mut sp = servo_phase::Config::zeros(1);
    sp.y[0] = [0.0, 2e-4, 1e-5];
    c.effects.push(EffectConfig::ServoPhase(sp));
    let mut sg = servo_gain::Config::zeros(1, vec![1, 2]);
    sg.x[1] = 1e-5;
    c.effects.push(EffectConfig::ServoGain(sg));
    c.effects
        .push(EffectConfig::StylusThermal(stylus_thermal::Config {
            alpha_shank_per_k: 11.5e-6,
            ..stylus_thermal::Config::zeros(false)
        }));
    c.effects
        .push(EffectConfig::ScaleThermal(scale_thermal::Config {
            alpha_per_k: [10e-6, 10e-6, 10e-6],
            ..scale_thermal::Config::zeros()
        }));
    c.effects
        .push(EffectConfig::ProbeForce(probe_force::Config {
            id: None,
            k: [0.01, 0.01, 0.005],
            per_tip: Default::default(),
        }));
    let mut gs = guide_straightness::Config::zeros(Axis::X, 0.0, 1000.0, 11, true);
    gs.straightness.values_mut().for_each(|v| v[5] = 1e-3);
    c.effects.push(EffectConfig::GuideStraightness(gs));
    c.effects.push(EffectConfig::Custom(custom::Config {
        id: "x_cyclic".into(),
        dynamic: false,
        terms: vec![
            custom::Term {
                axis: Axis::X,
                expr: "sin(2*pi*x/4)".into(),
            },
            custom::Term {
                axis: Axis::X,
                expr: "cos(2*pi*x/4)".into(),
            },
        ],
        coefficients: vec![2e-4, -1e-4],
    }));
    c.note = "every effect of the library (benchmark)".into();
    c
}

/// Where a ring scan runs and what the machine reports besides its motion.
#[derive(Debug, Clone, PartialEq)]
pub struct RingSetup {
    /// The ring's centre, mm (the scales read it 50 mm higher: the stylus's length).
    pub centre: Vec3,
    /// The tip every probe sample names.
    pub tip_id: u32,
    /// The temperature sensors read (every 100 ms).
    pub sensors: Vec<String>,
}

impl Default for RingSetup {
    /// The benchmarks' ring: at (250, 300, −150) mm, tip 1, five sensors (the every-effect
    /// calibration's and more).
    fn default() -> RingSetup {
        RingSetup {
            centre: Vec3::new(250.0, 300.0, -150.0),
            tip_id: 1,
            sensors: ["stylus", "scale_x", "scale_y", "scale_z", "air"]
                .map(String::from)
                .to_vec(),
        }
    }
}

impl RingSetup {
    /// A ring that `cal` can correct: centred in its travel, scanned with its first tip, with
    /// every temperature sensor its effects read.
    pub fn for_calibration(cal: &Calibration) -> Result<RingSetup, scancorr_core::CalibError> {
        let model = cal.build()?;
        let [x, y, z] = cal.limits.travel_mm.map(|[lo, hi]| 0.5 * (lo + hi));
        Ok(RingSetup {
            centre: Vec3::new(x, y, z - 50.0),
            // A built calibration has at least one tip.
            tip_id: cal.geometry.tips.first().map_or(1, |t| t.id),
            sensors: model.sensors.names().to_vec(),
        })
    }
}

/// Samples of `n` scale instants at 1 kHz: rings at 4 speeds, each starting from rest.
/// Returns the samples in time order and the number of scale samples.
pub fn ring_scan(n: usize) -> Vec<Sample> {
    ring_scan_with(n, &RingSetup::default())
}

/// [`ring_scan`] of the ring `setup` places.
pub fn ring_scan_with(n: usize, setup: &RingSetup) -> Vec<Sample> {
    let mut out = Vec::with_capacity(n * 3 + n / 100 * (setup.sensors.len() + 1) + 8);
    let centre = setup.centre;
    let (ring_r, tip_r, defl) = (25.0, 1.5, 0.3);
    let path_r = ring_r - tip_r;
    let speeds = [10.0, 25.0, 50.0, 80.0];
    let per = 4000usize;
    let mut theta = 0.0f64;
    let mut tseq = 0u64;
    for k in 0..n {
        let seg = k / per;
        let tk = (k % per) as f64 * 1e-3;
        let v = speeds[seg % speeds.len()];
        let speed = if tk < 0.2 { v * tk / 0.2 } else { v };
        theta += speed * 1e-3 / path_r;
        let dir = Vec3::new(theta.cos(), theta.sin(), 0.0);
        let tip = centre + dir * path_r;
        let offset = Vec3::new(0.0, 0.0, -50.0);
        let t_ns = k as i64 * 1_000_000;
        out.push(Sample::Command(CommandSample {
            seq: k as u64,
            t_ns,
            pos: tip - offset + dir * defl,
            arc_center: centre - offset,
            arc_radius: path_r + defl,
            segment_id: seg as u32,
        }));
        out.push(Sample::Scale(ScaleSample {
            seq: k as u64,
            t_ns,
            pos: tip - offset + dir * defl,
        }));
        out.push(Sample::Probe(ProbeSample {
            seq: k as u64,
            t_ns,
            deflection: -dir * defl,
            tip_id: setup.tip_id,
            head_a1_deg: 0.0,
            head_a2_deg: 0.0,
            force_n: None,
        }));
        if k % 100 == 0 {
            for s in &setup.sensors {
                out.push(Sample::Temperature(TemperatureSample {
                    seq: tseq,
                    t_ns: t_ns - 1000,
                    sensor: s.clone(),
                    celsius: 20.0 + 2.0 * (k as f64 / n as f64),
                }));
                tseq += 1;
            }
        }
    }
    out.sort_by_key(|s| s.t_ns());
    out
}
