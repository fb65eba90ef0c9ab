//! # scancorr-sim — a simulated scanning CMM with ground truth
//!
//! A gantry CMM with an analog scanning probe that follows scan programs and emits the four
//! raw streams (command, scales, probe, temperatures). It models the physical machine its own
//! way ([`machine`]): servo loops that are not the nominal model, a compliant structure with
//! a resonance, scale readouts that latch after the time stamp (Y and Z later than X: the
//! arc phase lag is that delay, not a formula), a stiff second mode between the reading
//! heads and the probe (the arc gain is its compliance, not a formula), stylus and scale expansion
//! following a temperature history measured by noisy sensors, stylus bending with probing
//! force, guide straightness and pitch, sensor noise and quantisation — and optionally effects
//! outside the correction library (an encoder's cyclic error, backlash, further latching
//! delays, a lobing probe, the 21 rigid-body errors of the kinematic chain) and faults.
//!
//! Every effect can be switched and scaled; a hidden effect stays in the machine but is left
//! out of the starting calibration. Ground truth (every true parameter, the true surfaces, the
//! true calibration) is returned separately, never inside the samples.
#![forbid(unsafe_code)]

pub mod machine;
pub mod program;
pub mod rng;
pub mod straightness;
pub mod wall;

use machine::{head_rotation, profile, TrueMachine, V3};
use program::{FeatureInfo, Path, Plan, ProgramInfo, SegmentInfo, SegmentKind};
use rng::Rng;
use scancorr_core::calib::Calibration;
use scancorr_core::datasheet::{
    Catalogue, CatalogueProbe, CatalogueStylus, DataSheet, SheetAxes, SheetAxis,
};
use scancorr_core::effects::{self as fx, EffectConfig};
use scancorr_core::sample::*;
use scancorr_core::transfer::TransferFunction;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Effects of the correction library the machine has (and the calibration can describe).
///
/// There is no `servo_gain` among them: on this machine, as on any whose axes are linear
/// systems, a radial gain ∝ f² on arcs is a compliance (the structure's and the mount mode's,
/// [`TrueMachine::mount_compliance_s2`]), which the library's `accel_deflection` describes
/// everywhere and `servo_gain` only on arcs. Both stay in the library; the truth is the former.
pub const LIBRARY_EFFECTS: [&str; 6] = [
    "accel_deflection",
    "servo_phase",
    "stylus_thermal",
    "scale_thermal",
    "probe_force",
    "guide_straightness",
];
/// Effects outside the library (off unless switched on; never in a calibration).
///
/// `deflection_quadratic` is the compliance's change quadratic in X
/// ([`TrueMachine::compliance_x2`]): the library's `accel_deflection` describes it (position
/// order 2, the ξx² monomial), so when it is on the true calibration carries it.
///
/// `force_probe` makes the probe a force probe ([`machine::ForceProbe`]): the stylus bends with
/// the force F = F0 + c·|d| (its preload F0 scaled by the factor), and the probe publishes the
/// force (wire v1.5). The library describes the bending per mm of deflection only, so the
/// preload's share (a constant bending along the probing direction) is not in the true
/// calibration.
pub const EXTRA_EFFECTS: [&str; 8] = [
    "cyclic_error",
    "backlash",
    "latching",
    "probe_lobing",
    "rigid_body",
    "squareness",
    "deflection_quadratic",
    "force_probe",
];

/// Faults for the judgement stage.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Fault {
    /// The X and Y position loops lose half their gain (the real time constant changes).
    ServoDrift,
    /// The X and Y carriages are blocked for 30 ms.
    Collision,
    /// The X drive stops and the carriage coasts to rest.
    Stall,
}

impl std::str::FromStr for Fault {
    type Err = String;
    fn from_str(s: &str) -> Result<Fault, String> {
        match s {
            "servo-drift" => Ok(Fault::ServoDrift),
            "collision" => Ok(Fault::Collision),
            "stall" => Ok(Fault::Stall),
            _ => Err(format!(
                "unknown fault `{s}` (known: servo-drift, collision, stall)"
            )),
        }
    }
}

/// What to simulate.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Options {
    /// Program: ring, ring-speeds, campaign, part.
    pub program: String,
    /// Where to place the program's artifact, mm.
    pub position: Option<[f64; 3]>,
    /// Machine id in the streams.
    pub machine_id: String,
    /// Picks the machine (its true parameters).
    pub machine_seed: u64,
    /// Picks the run's noise, temperatures and timing.
    pub seed: u64,
    /// Command, scale and probe rate, Hz.
    pub rate_hz: f64,
    /// Temperature rate, Hz.
    pub temperature_rate_hz: f64,
    /// Scale factor per effect (library effects default 1, extra effects 0).
    pub effects: BTreeMap<String, f64>,
    /// Effects kept in the machine but left out of the starting calibration.
    pub hide: Vec<String>,
    /// A fault.
    pub fault: Option<Fault>,
    /// Fault onset, s from the start (default: mid-way through the first fast scan).
    pub fault_at_s: Option<f64>,
    /// Repeat the program until this many minutes have passed.
    pub minutes: Option<f64>,
    /// Stream circles as points: every command sample without arc centre and radius (a
    /// controller that interpolates arcs itself). The machine moves the same.
    #[serde(default)]
    pub no_arcs: bool,
    /// A program record to run instead of the named `program` (`sim --program FILE.json`,
    /// what `lab plan` writes).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub program_record: Option<scancorr_core::lab::plan::Program>,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            program: "ring".into(),
            position: None,
            machine_id: "m1".into(),
            machine_seed: 1,
            seed: 1,
            rate_hz: 1000.0,
            temperature_rate_hz: 10.0,
            effects: BTreeMap::new(),
            hide: vec![],
            fault: None,
            fault_at_s: None,
            minutes: None,
            no_arcs: false,
            program_record: None,
        }
    }
}

/// Why a simulation cannot run.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// Bad options.
    #[error("{0}")]
    Options(String),
}

/// Ground truth of a run: never inside the bag.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Truth {
    /// The options of the run.
    pub options: Options,
    /// Effect scale factors in force.
    pub effects: BTreeMap<String, f64>,
    /// The true machine (after scaling effects).
    pub machine: TrueMachine,
    /// True surfaces of the features.
    pub features: Vec<program::Feature>,
    /// Fault onsets, ns.
    pub faults: Vec<FaultTruth>,
    /// Noise floor of a surface point along its normal (1σ), µm.
    pub noise_floor_um: f64,
    /// Temperature range of the run (min, max) per sensor, °C.
    pub temperatures: BTreeMap<String, [f64; 2]>,
    /// The calibration with every effect at its true parameters.
    pub true_calibration: Calibration,
    /// The true parameters under the names the calibration procedures print
    /// (`tip2.l1_mm`, `tip1.radius_mm`, `tip2.alpha_per_k`, `tip2.probe_k_u_mm_per_mm`, …).
    pub params: BTreeMap<String, f64>,
}

/// Time constant of the probe's own response (the nominal model's G2), s.
pub const PROBE_TAU_S: f64 = 0.002;

/// The true parameters of `m` under the names `scancorr calibrate` prints.
///
/// `dynamics.*` are what the ring-gauge procedure determines: τ of each axis's first-order
/// nominal model (1/kp less the probe's and less the scale readout's delay), the compliance
/// P = −C (C the displacement of the probe per unit acceleration, per monomial 1, x, y, z of
/// the position over 500 mm), the servo phase b0, b1, b2 of Y and Z against X per monomial
/// (b1 = −2π·Δτ of the readouts, the rest zero), and the servo gain's f² and f¹ terms (zero:
/// the arcs' gain of this machine is its compliance, the structure's plus the mount mode's
/// on the diagonal of P).
pub fn procedure_params(m: &TrueMachine) -> BTreeMap<String, f64> {
    // Each name ends with its unit: P in mm per mm/s² (s²), the phase's b0, b1, b2 in rad,
    // rad/Hz, rad/Hz², the gain's f¹ and f² terms in 1/Hz and 1/Hz².
    const PHASE_UNITS: [&str; 3] = ["_rad", "_rad_per_hz", "_rad_per_hz2"];
    let mut p = BTreeMap::new();
    const AX: [&str; 3] = ["x", "y", "z"];
    const MONO: [&str; 4] = ["1", "x", "y", "z"];
    for (i, a) in AX.iter().enumerate() {
        // What the scales show: they read the carriage τ_readout later, so they lag the
        // command by that much less.
        p.insert(
            format!("dynamics.tau_{a}_s"),
            1.0 / m.servo[i].kp - PROBE_TAU_S - m.readout_delay_s[i] - m.latching.tau_s[i],
        );
        p.insert(format!("dynamics.gain_{a}.f1.1_per_hz"), 0.0);
        p.insert(format!("dynamics.gain_{a}.f2.1_per_hz2"), 0.0);
    }
    for (k, mono) in MONO.iter().enumerate() {
        for (i, a) in AX.iter().enumerate() {
            for (j, b) in AX.iter().enumerate() {
                p.insert(
                    format!("dynamics.P_{a}{b}.{mono}_mm_per_mm_s2"),
                    -m.compliance_total(k, i, j),
                );
                // P's term quadratic in X (P2 of P = P0 + P1·ξx + P2·ξx²; zero unless
                // `deflection_quadratic` is on).
                if k == 0 {
                    p.insert(
                        format!("dynamics.P_{a}{b}.x2_mm_per_mm_s2"),
                        -m.compliance_x2[i][j],
                    );
                }
            }
        }
    }
    for (ai, a) in ["y", "z"].iter().enumerate() {
        for mono in MONO {
            for b in 0..3 {
                let v = if mono == "1" && b == 1 {
                    m.phase_b1()[ai]
                } else {
                    0.0
                };
                p.insert(
                    format!("dynamics.phase_{a}.b{b}.{mono}{}", PHASE_UNITS[b]),
                    v,
                );
            }
        }
    }
    let first = m.styli.iter().min_by_key(|s| s.id);
    for s in &m.styli {
        let t = format!("tip{}", s.id);
        p.insert(format!("{t}.l1_mm"), s.l1_mm);
        if let Some(r) = first.filter(|r| r.id != s.id) {
            // Measured from the reference stylus (the lowest id), as `calibrate tips` prints.
            p.insert(format!("{t}.l1_from_tip{}_mm", r.id), s.l1_mm - r.l1_mm);
        }
        if s.l2_mm > 0.0 {
            p.insert(format!("{t}.l2_mm"), s.l2_mm);
        }
        p.insert(format!("{t}.radius_mm"), s.radius_mm);
        p.insert(format!("{t}.alpha_per_k"), s.alpha_per_k);
        for (a, k) in ["u", "v", "w"].iter().zip(m.probe_k) {
            p.insert(format!("{t}.probe_k_{a}_mm_per_mm"), k * s.bend_scale);
            if let Some(fp) = &m.force_probe {
                // A force probe's stylus bends per newton.
                p.insert(
                    format!("{t}.probe_kf_{a}_mm_per_n"),
                    k * s.bend_scale / fp.rate_n_per_mm,
                );
            }
        }
    }
    if let Some(fp) = &m.force_probe {
        p.insert("force_probe.preload_n".into(), fp.preload_n);
        p.insert("force_probe.rate_n_per_mm".into(), fp.rate_n_per_mm);
    }
    // The scales' expansion, as `calibrate scales` prints it.
    for (a, alpha) in ["x", "y", "z"].iter().zip(m.scale_alpha) {
        p.insert(format!("scale_{a}.alpha_per_k"), alpha);
    }
    p
}

/// A fault's onset.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FaultTruth {
    /// Which.
    pub fault: Fault,
    /// Onset, ns.
    pub onset_t_ns: i64,
}

/// Everything a run produces besides its samples.
#[derive(Debug, Clone)]
pub struct RunResult {
    /// Ground truth.
    pub truth: Truth,
    /// The starting calibration (hidden effects left out).
    pub start_calibration: Calibration,
    /// What the bag may say about the program (features, segments).
    pub program: ProgramInfo,
    /// Samples emitted per stream.
    pub counts: [u64; 4],
}

/// Sensor names of the temperature stream.
pub const SENSORS: [&str; 5] = ["stylus", "scale_x", "scale_y", "scale_z", "air"];

const NO_GAIN: &str = "servo_gain: the simulated machine has no arc gain of its own — the gain \
    its arcs show is its compliance (the structure's and the probe mount's), the simulator's \
    `accel_deflection`";

fn effect_factors(o: &Options) -> Result<BTreeMap<String, f64>, SimError> {
    let mut f: BTreeMap<String, f64> = LIBRARY_EFFECTS
        .iter()
        .map(|e| (e.to_string(), 1.0))
        .collect();
    f.extend(EXTRA_EFFECTS.iter().map(|e| (e.to_string(), 0.0)));
    for (k, v) in &o.effects {
        if k == "servo_gain" {
            return Err(SimError::Options(NO_GAIN.into()));
        }
        if !f.contains_key(k) {
            return Err(SimError::Options(format!(
                "unknown effect `{k}` (library: {}; outside the library: {})",
                LIBRARY_EFFECTS.join(", "),
                EXTRA_EFFECTS.join(", ")
            )));
        }
        if !v.is_finite() || *v < 0.0 {
            return Err(SimError::Options(format!(
                "effect scale for `{k}` must be a finite number ≥ 0"
            )));
        }
        f.insert(k.clone(), *v);
    }
    for h in &o.hide {
        match f.get(h) {
            None if h == "servo_gain" => return Err(SimError::Options(NO_GAIN.into())),
            None => return Err(SimError::Options(format!("--hide {h}: unknown effect"))),
            Some(v) if *v == 0.0 => {
                return Err(SimError::Options(format!(
                    "--hide {h}: the effect is switched off"
                )))
            }
            _ => {}
        }
    }
    Ok(f)
}

fn scaled_machine(seed: u64, f: &BTreeMap<String, f64>) -> TrueMachine {
    let mut m = TrueMachine::from_seed(seed);
    let k = |n: &str| f[n];
    m.compliance
        .iter_mut()
        .flatten()
        .flatten()
        .for_each(|c| *c *= k("accel_deflection"));
    m.readout_delay_s
        .iter_mut()
        .for_each(|c| *c *= k("servo_phase"));
    m.mount_compliance_s2
        .iter_mut()
        .for_each(|c| *c *= k("accel_deflection"));
    let fp = k("force_probe");
    if fp != 0.0 {
        m.force_probe = Some(machine::ForceProbe::from_seed(seed, fp));
    }
    let q = k("deflection_quadratic");
    if q != 0.0 {
        m.compliance_x2 = m.quadratic_compliance().map(|r| r.map(|c| c * q));
    }
    m.styli
        .iter_mut()
        .for_each(|s| s.alpha_per_k *= k("stylus_thermal"));
    m.scale_alpha
        .iter_mut()
        .for_each(|c| *c *= k("scale_thermal"));
    m.probe_k.iter_mut().for_each(|c| *c *= k("probe_force"));
    for w in m
        .guide_y
        .iter_mut()
        .chain(m.guide_z.iter_mut())
        .chain(m.guide_pitch.iter_mut())
    {
        w.amplitude *= k("guide_straightness");
    }
    m.cyclic.amplitude *= k("cyclic_error");
    m.backlash_mm *= k("backlash");
    m.latching
        .tau_s
        .iter_mut()
        .for_each(|t| *t *= k("latching"));
    m.lobing.scale(k("probe_lobing"));
    // Squareness alone (without the axes' own errors): the three angles between the axes.
    let square = (m.rigid_body.s_xy, m.rigid_body.s_zx, m.rigid_body.s_zy);
    m.rigid_body.scale(k("rigid_body"));
    if k("squareness") != 0.0 {
        m.rigid_body.s_xy = square.0 * k("squareness");
        m.rigid_body.s_zx = square.1 * k("squareness");
        m.rigid_body.s_zy = square.2 * k("squareness");
    }
    m
}

/// The calibration describing `m` with library effects (those switched on, minus `hide`).
pub fn calibration_for(
    m: &TrueMachine,
    machine_id: &str,
    f: &BTreeMap<String, f64>,
    hide: &[String],
    period: f64,
) -> Calibration {
    let mut c = Calibration::example(machine_id);
    c.sample_period_s = period;
    let tp = PROBE_TAU_S;
    let g1 = |i: usize| TransferFunction::FirstOrder {
        tau_s: 1.0 / m.servo[i].kp - tp,
    };
    c.nominal.axes.x = g1(0);
    c.nominal.axes.y = g1(1);
    c.nominal.axes.z = g1(2);
    c.nominal.probes = [(
        "sp25".to_string(),
        TransferFunction::FirstOrder { tau_s: tp },
    )]
    .into();
    c.geometry.tips = m
        .styli
        .iter()
        .map(|s| scancorr_core::stylus::TipGeometry {
            id: s.id,
            probe: s.probe.clone(),
            l1_mm: s.l1_mm,
            radius_mm: s.radius_mm,
            l2_mm: s.l2_mm,
            beta1_deg: s.beta1_deg,
            l3_mm: 0.0,
            beta2_deg: 0.0,
        })
        .collect();
    let on = |n: &str| f.get(n).copied().unwrap_or(0.0) != 0.0 && !hide.iter().any(|h| h == n);
    if on("accel_deflection") {
        let quadratic = m.compliance_x2.iter().flatten().any(|c| *c != 0.0);
        let mut e = fx::accel_deflection::Config::zeros(if quadratic { 2 } else { 1 }, false);
        for (k, p) in e.p.iter_mut().enumerate().take(4) {
            for i in 0..3 {
                for j in 0..3 {
                    p[i][j] = -m.compliance_total(k, i, j);
                }
            }
        }
        if quadratic {
            // The position basis's fifth monomial is ξx².
            e.p[4] = m.compliance_x2.map(|r| r.map(|c| -c));
        }
        c.effects.push(EffectConfig::AccelDeflection(e));
    }
    if on("servo_phase") {
        let mut e = fx::servo_phase::Config::zeros(0);
        // The readouts' delays seen on an arc (first order in τ·ω; the rest is below 0.1 nm).
        let b1 = m.phase_b1();
        e.y[0] = [0.0, b1[0], 0.0];
        e.z[0] = [0.0, b1[1], 0.0];
        c.effects.push(EffectConfig::ServoPhase(e));
    }
    if on("stylus_thermal") {
        c.effects
            .push(EffectConfig::StylusThermal(fx::stylus_thermal::Config {
                alpha_shank_per_k: m.styli[0].alpha_per_k,
                alpha_per_tip: m.styli.iter().map(|s| (s.id, s.alpha_per_k)).collect(),
                ..fx::stylus_thermal::Config::zeros(false)
            }));
    }
    if on("scale_thermal") {
        c.effects
            .push(EffectConfig::ScaleThermal(fx::scale_thermal::Config {
                alpha_per_k: m.scale_alpha,
                ..fx::scale_thermal::Config::zeros()
            }));
    }
    if on("probe_force") {
        c.effects
            .push(EffectConfig::ProbeForce(fx::probe_force::Config {
                id: None,
                k: m.probe_k,
                per_tip: m
                    .styli
                    .iter()
                    .map(|s| (s.id, m.probe_k.map(|k| k * s.bend_scale)))
                    .collect(),
            }));
    }
    if on("guide_straightness") {
        let mut e = fx::guide_straightness::Config::zeros(Axis::X, 0.0, 1000.0, 101, true);
        e.pitch_about = Some(Axis::Z);
        let knots = e.knots_mm.clone();
        let arm = V3::from(m.abbe_arm_mm);
        for (j, x) in knots.iter().enumerate() {
            let eps = profile(&m.guide_pitch, *x);
            let fixed = V3::z().cross(&arm) * eps;
            e.straightness.get_mut(&Axis::Y).unwrap()[j] = profile(&m.guide_y, *x) + fixed.y;
            e.straightness.get_mut(&Axis::Z).unwrap()[j] = profile(&m.guide_z, *x) + fixed.z;
            e.pitch_rad.as_mut().unwrap()[j] = eps;
        }
        c.effects.push(EffectConfig::GuideStraightness(e));
    }
    c.note = if hide.is_empty() {
        "simulator: every effect at its true parameters".into()
    } else {
        format!(
            "simulator starting calibration: {} left out",
            hide.join(", ")
        )
    };
    c
}

/// How far the data sheet's time constants are off the machine's: its maker states each 30 %
/// longer than the axis follows (what a user starts from, which the procedures refit).
pub const DATA_SHEET_TAU_FACTOR: f64 = 1.3;

/// The simulated machines' travel, [min, max] per axis (x, y, z) in machine coordinates, mm:
/// every program's carriage path lies inside it (checked by a test).
pub const TRAVEL_MM: [[f64; 2]; 3] = [[0.0, 1000.0], [0.0, 800.0], [-600.0, 0.0]];

/// What the maker's data sheet of `m` says: each axis's time constant as stated
/// ([`DATA_SHEET_TAU_FACTOR`] times the first-order τ the truth's calibration has: not the
/// truth), the travel, the streaming period `period` and the machine's id.
pub fn data_sheet(m: &TrueMachine, machine_id: &str, period: f64) -> DataSheet {
    let axis = |i: usize| SheetAxis {
        tau_s: (1.0 / m.servo[i].kp - PROBE_TAU_S) * DATA_SHEET_TAU_FACTOR,
        travel_mm: TRAVEL_MM[i],
    };
    DataSheet {
        machine_id: machine_id.to_string(),
        note: format!(
            "the simulator's data sheet of machine seed {} (time constants as its maker \
             states them, {} % off)",
            m.machine_seed,
            ((DATA_SHEET_TAU_FACTOR - 1.0) * 100.0).round()
        ),
        sample_period_s: period,
        axes: SheetAxes {
            x: axis(0),
            y: axis(1),
            z: axis(2),
        },
    }
}

/// The probe and stylus catalogue of every simulated machine: the probe's own response and
/// the styli as listed ([`machine::catalogue_styli`]; each machine's are built a few µm off),
/// with their materials' expansion coefficients.
pub fn stylus_catalogue() -> Catalogue {
    Catalogue {
        note: "the simulator's probe and stylus catalogue (listed lengths, not qualified)".into(),
        probes: machine::catalogue_styli()
            .iter()
            .map(|s| (s.probe.clone(), CatalogueProbe { tau_s: PROBE_TAU_S }))
            .collect(),
        tips: machine::catalogue_styli()
            .into_iter()
            .map(|s| CatalogueStylus {
                id: s.id,
                probe: s.probe,
                l1_mm: s.l1_mm,
                l2_mm: s.l2_mm,
                beta1_deg: s.beta1_deg,
                l3_mm: 0.0,
                beta2_deg: 0.0,
                radius_mm: s.radius_mm,
                alpha_per_k: Some(s.alpha_per_k),
            })
            .collect(),
    }
}

/// Dynamic state of the three axes and the structure.
#[derive(Debug, Clone, Copy, Default)]
struct State {
    x: [f64; 3],
    v: [f64; 3],
    a: [f64; 3],
    d: [f64; 3],
    dd: [f64; 3],
    /// The mount mode's displacement and velocity.
    h: [f64; 3],
    hd: [f64; 3],
}

impl State {
    fn axpy(&self, k: &State, h: f64) -> State {
        let f = |a: [f64; 3], b: [f64; 3]| [a[0] + h * b[0], a[1] + h * b[1], a[2] + h * b[2]];
        State {
            x: f(self.x, k.x),
            v: f(self.v, k.v),
            a: f(self.a, k.a),
            d: f(self.d, k.d),
            dd: f(self.dd, k.dd),
            h: f(self.h, k.h),
            hd: f(self.hd, k.hd),
        }
    }
}

struct Physics<'a> {
    m: &'a TrueMachine,
    kp_scale: [f64; 3],
    blocked: [bool; 3],
    stalled: [bool; 3],
}

impl Physics<'_> {
    fn deriv(&self, s: &State, c: &V3) -> State {
        let mut k = State::default();
        for i in 0..3 {
            let sv = &self.m.servo[i];
            let a_target = if self.blocked[i] {
                -s.v[i] / 0.0005
            } else if self.stalled[i] {
                // The drive trips and the axis brake stops the carriage.
                -s.v[i] / 0.005
            } else {
                let vcmd = sv.kp * self.kp_scale[i] * (c[i] - s.x[i]);
                (vcmd - s.v[i]) / sv.tau_v
            };
            k.x[i] = s.v[i];
            k.v[i] = s.a[i];
            k.a[i] = (a_target - s.a[i]) / sv.tau_i;
        }
        // Structure: δ̈ = ω²(−C(p)·a − δ) − 2ζω δ̇.
        let cm = self.m.compliance_at(&V3::from(s.x));
        let load = -(cm * V3::from(s.a));
        for i in 0..3 {
            let w = 2.0 * std::f64::consts::PI * self.m.structure_freq_hz[i];
            k.d[i] = s.dd[i];
            k.dd[i] = w * w * (load[i] - s.d[i]) - 2.0 * self.m.structure_damping * w * s.dd[i];
        }
        // Mount mode: η̈ = ω_m²(−γ·a − η) − 2ζ_m ω_m η̇, driven by the axis's own acceleration.
        for i in 0..3 {
            let w = 2.0 * std::f64::consts::PI * self.m.mount_freq_hz[i];
            let load = -self.m.mount_compliance_s2[i] * s.a[i];
            k.h[i] = s.hd[i];
            k.hd[i] = w * w * (load - s.h[i]) - 2.0 * self.m.mount_damping * w * s.hd[i];
        }
        k
    }
    fn rk4(&self, s: &State, c0: &V3, c1: &V3, h: f64) -> State {
        let cm = (c0 + c1) * 0.5;
        let k1 = self.deriv(s, c0);
        let k2 = self.deriv(&s.axpy(&k1, h / 2.0), &cm);
        let k3 = self.deriv(&s.axpy(&k2, h / 2.0), &cm);
        let k4 = self.deriv(&s.axpy(&k3, h), c1);
        let mut out = *s;
        let comb = |a: [f64; 3], b1: [f64; 3], b2: [f64; 3], b3: [f64; 3], b4: [f64; 3]| {
            [0, 1, 2].map(|i| a[i] + h / 6.0 * (b1[i] + 2.0 * b2[i] + 2.0 * b3[i] + b4[i]))
        };
        out.x = comb(s.x, k1.x, k2.x, k3.x, k4.x);
        out.v = comb(s.v, k1.v, k2.v, k3.v, k4.v);
        out.a = comb(s.a, k1.a, k2.a, k3.a, k4.a);
        out.d = comb(s.d, k1.d, k2.d, k3.d, k4.d);
        out.dd = comb(s.dd, k1.dd, k2.dd, k3.dd, k4.dd);
        out.h = comb(s.h, k1.h, k2.h, k3.h, k4.h);
        out.hd = comb(s.hd, k1.hd, k2.hd, k3.hd, k4.hd);
        out
    }
}

fn quantise(x: f64, q: f64) -> f64 {
    if q > 0.0 {
        (x / q).round() * q
    } else {
        x
    }
}

/// Runs a simulation, handing every sample (in time order) to `sink`.
pub fn run(o: &Options, mut sink: impl FnMut(Sample)) -> Result<RunResult, SimError> {
    if !(o.rate_hz.is_finite() && (10.0..=100_000.0).contains(&o.rate_hz)) {
        return Err(SimError::Options(
            "--rate must be between 10 and 100000 Hz".into(),
        ));
    }
    if !(o.temperature_rate_hz.is_finite()
        && o.temperature_rate_hz > 0.0
        && o.temperature_rate_hz <= o.rate_hz)
    {
        return Err(SimError::Options(
            "temperature rate must be > 0 and at most the sample rate".into(),
        ));
    }
    if o.position.is_some_and(|p| p.iter().any(|v| !v.is_finite())) {
        return Err(SimError::Options(
            "--position must be three finite numbers".into(),
        ));
    }
    let factors = effect_factors(o)?;
    let m = scaled_machine(o.machine_seed, &factors);
    let plan: Plan = match &o.program_record {
        Some(p) => program::plan_record(p, &m)
            .map_err(|e| SimError::Options(format!("program {}: {e}", o.program)))?,
        None => {
            program::plan(&o.program, &m, o.position.map(V3::from)).map_err(SimError::Options)?
        }
    };
    let period = 1.0 / o.rate_hz;
    let plan_d = plan.duration();
    let reps = match o.minutes {
        Some(min) if min.is_finite() && min > 0.0 => {
            ((min * 60.0) / plan_d).ceil().max(1.0) as usize
        }
        Some(_) => return Err(SimError::Options("--minutes must be > 0".into())),
        None => 1,
    };
    let total = plan_d * reps as f64;
    let n = (total / period).floor() as u64 + 1;
    let seg_per_rep = plan.segments.len() as u32;

    // Fault onset: by default in the first fast scan, where the X axis moves fastest
    // (a fault of a standing axis would show no dynamics to detect).
    let fault_at = o.fault.map(|_| {
        o.fault_at_s.unwrap_or_else(|| {
            plan.segments
                .iter()
                .zip(&plan.starts)
                .find(|(s, _)| s.kind == SegmentKind::Scan && s.speed >= 40.0)
                .map(|(s, t0)| {
                    let (a, b) = (s.ramp_s, (s.duration_s - s.ramp_s).max(s.ramp_s));
                    let mut best = (a, 0.0);
                    let mut t = a;
                    while t < b {
                        let vx = ((s.at(t + 1e-3) - s.at(t)) / 1e-3).x.abs();
                        if vx > best.1 {
                            best = (t, vx);
                        }
                        t += 1e-3;
                    }
                    t0 + best.0
                })
                .unwrap_or(plan_d / 2.0)
        })
    });

    // Temperature history of this run.
    let mut tr = Rng::new(o.seed, "thermal");
    let t0_air = 20.0 + tr.range(0.2, 0.8);
    let drift = tr.range(2.5, 3.5);
    // A program record that asks for a temperature span gets it (the air's rise over the run).
    let drift = o
        .program_record
        .as_ref()
        .and_then(|p| p.temperature.as_ref())
        .map_or(drift, |t| t.span_k);
    let wobble = tr.range(0.03, 0.08);
    let scale_off = [
        tr.range(-0.3, 0.3),
        tr.range(-0.3, 0.3),
        tr.range(-0.3, 0.3),
    ];
    // With a span asked for, the room has been warming at that rate for a while: the air leads
    // the scales by rate·τ (their lag) and the styli follow it, so each rises by the span over
    // the program from its usual start, not by the span less its lag's start-up.
    let rate = drift / total;
    let spanned = o
        .program_record
        .as_ref()
        .is_some_and(|p| p.temperature.is_some());
    let lead = if spanned { rate * 120.0 } else { 0.0 };
    let air = |t: f64| {
        t0_air + lead + drift * t / total + wobble * (std::f64::consts::TAU * t / 240.0).sin()
    };
    let mut t_stylus = t0_air + 0.1 + if spanned { rate * 80.0 } else { 0.0 };
    let mut t_scale = [0, 1, 2].map(|i| t0_air - 0.2 + scale_off[i]);
    let mut t_range: BTreeMap<String, [f64; 2]> = BTreeMap::new();

    let mut noise = Rng::new(o.seed, "noise");
    // The force probe's own noise (a stream of its own: no other draw moves).
    let mut force_noise = Rng::new(o.seed, "force_noise");
    let nz = m.noise;
    let mut st = State::default();
    // Start at rest at the first command.
    let c_first = plan.segments[0].at(0.0);
    st.x = [c_first.x, c_first.y, c_first.z];
    let mut backlash_dir = 1.0;
    let t_every = ((o.rate_hz / o.temperature_rate_hz).round() as u64).max(1);
    let mut tseq = 0u64;
    let mut counts = [0u64; 4];
    let substeps = 10;
    let cmd_at = |k: u64| -> (V3, usize, usize) {
        let t = k as f64 * period;
        let rep = ((t / plan_d).floor() as usize).min(reps - 1);
        let tt = t - rep as f64 * plan_d;
        let si = plan.segment_at(tt);
        let seg = &plan.segments[si];
        (seg.at(tt - plan.starts[si]), si, rep)
    };
    let mut phys = Physics {
        m: &m,
        kp_scale: [1.0; 3],
        blocked: [false; 3],
        stalled: [false; 3],
    };
    // When each scale's counter latches: its readout's own delay plus, with `latching`,
    // the extra delays outside the library.
    let latch_s: [f64; 3] = std::array::from_fn(|i| m.readout_delay_s[i] + m.latching.tau_s[i]);
    let latching = latch_s.iter().any(|t| *t != 0.0);
    let lobing = m.lobing.is_on();
    let rigid_body = factors["rigid_body"] != 0.0 || factors["squareness"] != 0.0;
    for k in 0..n {
        let t = k as f64 * period;
        let t_ns = (k as i64) * (1e9 / o.rate_hz).round() as i64;
        let (c, si, rep) = cmd_at(k);
        let seg = &plan.segments[si];
        let seg_id = seg.id + rep as u32 * seg_per_rep;
        let (arc_c, arc_r) = match seg.path {
            Path::Arc { center, radius, .. } if seg.kind == SegmentKind::Scan => (center, radius),
            _ => (V3::zeros(), 0.0),
        };
        // Faults.
        if let (Some(f), Some(tf)) = (o.fault, fault_at) {
            match f {
                Fault::ServoDrift if t >= tf => phys.kp_scale = [0.5, 0.5, 1.0],
                Fault::Collision => {
                    let on = t >= tf && t < tf + 0.03;
                    phys.blocked = [on, on, false];
                }
                Fault::Stall if t >= tf => phys.stalled = [true, false, false],
                _ => {}
            }
        }
        // Temperatures (true), first-order followers of the air.
        let ta = air(t);
        t_stylus += (ta - t_stylus) * period / 40.0;
        for (i, ts) in t_scale.iter_mut().enumerate() {
            *ts += (ta + scale_off[i] - *ts) * period / 120.0;
        }

        // --- outputs at t ---
        let x = V3::from(st.x);
        let rot = head_rotation(seg.a1_deg, seg.a2_deg);
        let stylus = m.stylus(seg.tip).expect("known tip");
        let (shank, bent) = stylus.limbs();
        let dts = t_stylus - 20.0;
        let offset_true = rot * (shank + bent) * (1.0 + stylus.alpha_per_k * dts);
        // Displacement e of the probe body relative to what the scales read: the structure's
        // and the mount mode's.
        let mut e = V3::from(st.d) + V3::from(st.h);
        let pitch = profile(&m.guide_pitch, x.x);
        e += V3::new(0.0, profile(&m.guide_y, x.x), profile(&m.guide_z, x.x));
        e += V3::z().cross(&(offset_true + V3::from(m.abbe_arm_mm))) * pitch;
        // Backlash, idealised: the lost motion flips at the instant the X velocity changes
        // sign (a real drive takes up its lash over a few µm of travel).
        if st.v[0] > 0.0 {
            backlash_dir = 1.0;
        } else if st.v[0] < 0.0 {
            backlash_dir = -1.0;
        }
        e.x -= 0.5 * m.backlash_mm * backlash_dir;
        // Rigid-body errors: the tip through the exact transforms of the chain.
        if rigid_body {
            e += m.rigid_body.tip(&x, &offset_true) - (x + offset_true);
        }
        let tip_free = x + e + offset_true;
        let d_total = match (seg.kind, seg.feature) {
            (SegmentKind::Scan | SegmentKind::Dwell, Some(fid)) => {
                plan.features[fid as usize - 1].push(&tip_free, stylus.radius_mm)
            }
            _ => V3::zeros(),
        };
        let feature = seg.feature.map(|fid| &plan.features[fid as usize - 1]);
        let bending = m.probe_k.map(|k| k * stylus.bend_scale);
        // The probe's deflection (before its noise) and, for a force probe, its force.
        let (d_read, force) = match &m.force_probe {
            None => {
                // A thin wall gives under the probing force (`wall`).
                let d_total = match feature {
                    Some(f) => wall::yielded(f, &tip_free, d_total, &rot, bending),
                    None => d_total,
                };
                let mut d_probe = rot.transpose() * d_total;
                if lobing {
                    d_probe = m.lobing.apply(&d_probe);
                }
                let d = V3::from_fn(|i, _| d_probe[i] / (1.0 + bending[i]));
                (d, None)
            }
            Some(fp) => {
                // The stylus bends with the force; a thin wall gives by c_w·F/c.
                let cw = feature.map_or(0.0, |f| wall::compliance(f, &tip_free));
                let len = d_total.norm();
                let (d, f) = fp.solve(
                    |f| {
                        let give = if len > 0.0 {
                            (1.0 - cw * f / fp.rate_n_per_mm / len).max(0.0)
                        } else {
                            0.0
                        };
                        let d_probe = rot.transpose() * d_total * give;
                        if lobing {
                            m.lobing.apply(&d_probe)
                        } else {
                            d_probe
                        }
                    },
                    bending,
                );
                (d, Some(f + fp.noise_n * force_noise.normal()))
            }
        };
        let mut defl = V3::zeros();
        for i in 0..3 {
            let dm = d_read[i] + nz.probe_sigma_mm * noise.normal();
            defl[i] = quantise(dm, nz.probe_resolution_mm);
        }
        // The counters latch the carriage where it is τ_i after the time stamp.
        let mut x_read = x;
        if latching {
            let (c_next, _, _) = cmd_at(k + 1);
            for i in 0..3 {
                let tau = latch_s[i];
                if tau != 0.0 {
                    let c_tau = c + (c_next - c) * (tau / period);
                    let steps = (tau / (period / substeps as f64)).ceil().max(1.0) as usize;
                    let h = tau / steps as f64;
                    let mut s_tau = st;
                    for j in 0..steps {
                        let ca = c + (c_tau - c) * (j as f64 / steps as f64);
                        let cb = c + (c_tau - c) * ((j + 1) as f64 / steps as f64);
                        s_tau = phys.rk4(&s_tau, &ca, &cb, h);
                    }
                    x_read[i] = s_tau.x[i];
                }
            }
        }
        let mut scale = V3::zeros();
        for i in 0..3 {
            let mut s = x_read[i] / (1.0 + m.scale_alpha[i] * (t_scale[i] - 20.0));
            if i == 0 {
                s += m.cyclic.at(x_read[i]);
            }
            scale[i] = quantise(
                s + nz.scale_sigma_mm * noise.normal(),
                nz.scale_resolution_mm,
            );
        }
        // The machine follows the arc either way; only what the controller says differs.
        let (cmd_arc_c, cmd_arc_r) = if o.no_arcs {
            (V3::zeros(), 0.0)
        } else {
            (arc_c, arc_r)
        };
        sink(Sample::Command(CommandSample {
            seq: k,
            t_ns,
            pos: c,
            arc_center: cmd_arc_c,
            arc_radius: cmd_arc_r,
            segment_id: seg_id,
        }));
        sink(Sample::Scale(ScaleSample {
            seq: k,
            t_ns,
            pos: scale,
        }));
        sink(Sample::Probe(ProbeSample {
            seq: k,
            t_ns,
            deflection: defl,
            tip_id: seg.tip,
            head_a1_deg: seg.a1_deg,
            head_a2_deg: seg.a2_deg,
            force_n: force,
        }));
        counts[0] += 1;
        counts[1] += 1;
        counts[2] += 1;
        if k % t_every == 0 {
            let vals = [t_stylus, t_scale[0], t_scale[1], t_scale[2], ta];
            for (name, val) in SENSORS.iter().zip(vals) {
                let r = t_range.entry(name.to_string()).or_insert([val, val]);
                r[0] = r[0].min(val);
                r[1] = r[1].max(val);
                let reading =
                    quantise(val + nz.temp_sigma_k * noise.normal(), nz.temp_resolution_k);
                sink(Sample::Temperature(TemperatureSample {
                    seq: tseq,
                    t_ns,
                    sensor: name.to_string(),
                    celsius: reading,
                }));
                tseq += 1;
                counts[3] += 1;
            }
        }
        // --- advance to t + period ---
        let (c_next, _, _) = cmd_at(k + 1);
        let h = period / substeps as f64;
        for j in 0..substeps {
            let ca = c + (c_next - c) * (j as f64 / substeps as f64);
            let cb = c + (c_next - c) * ((j + 1) as f64 / substeps as f64);
            st = phys.rk4(&st, &ca, &cb, h);
        }
        if let Some(ts) = t_range.get_mut("stylus") {
            let _ = ts;
        }
    }

    let true_cal = calibration_for(&m, &o.machine_id, &factors, &[], period);
    let mut start = calibration_for(&m, &o.machine_id, &factors, &o.hide, period);
    start.version = 1;
    let mut features: Vec<FeatureInfo> = vec![];
    let mut segments: Vec<SegmentInfo> = vec![];
    for rep in 0..reps {
        let (f, s) = plan.info(rep as u32 * seg_per_rep, rep as f64 * plan_d);
        if rep == 0 {
            features = f;
        }
        segments.extend(s);
    }
    let faults = match (o.fault, fault_at) {
        (Some(f), Some(t)) => vec![FaultTruth {
            fault: f,
            onset_t_ns: (t * 1e9).round() as i64,
        }],
        _ => vec![],
    };
    Ok(RunResult {
        truth: Truth {
            options: o.clone(),
            effects: factors,
            noise_floor_um: m.noise.point_sigma_mm() * 1e3,
            features: plan.features.clone(),
            params: procedure_params(&m),
            machine: m,
            faults,
            temperatures: t_range,
            true_calibration: true_cal,
        },
        start_calibration: start,
        program: ProgramInfo {
            program: plan.name.clone(),
            features,
            segments,
        },
        counts,
    })
}

#[cfg(test)]
mod tests;
