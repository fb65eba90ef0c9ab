//! The true machine: its parameters (drawn from the machine seed) and its physics.
//!
//! The simulator models the machine its own way — a cascaded servo loop per axis (position
//! gain, velocity loop, current loop) integrated with RK4 at ten sub-steps per sample, a
//! compliant structure with its own resonance driven by the true carriage acceleration, an
//! explicit contact between the stylus tip and the artifact's surface, thermal expansion by
//! division (not by the first-order products the corrector uses) — and never calls the
//! corrector's formulas. What it shares with the corrector is only the meaning of the
//! calibration document, so that it can write the true calibration for comparison.

use crate::rng::Rng;
use nalgebra::{Matrix3, Matrix4, Vector3, Vector4};
use serde::{Deserialize, Serialize};

/// Vector in machine axes.
pub type V3 = Vector3<f64>;

/// A sinusoidal component of an error profile along a travel.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Wave {
    /// Amplitude (mm or rad).
    pub amplitude: f64,
    /// Wavelength along the travel, mm.
    pub wavelength_mm: f64,
    /// Phase, rad.
    pub phase: f64,
}

impl Wave {
    /// Value at `s`.
    pub fn at(&self, s: f64) -> f64 {
        self.amplitude * (2.0 * std::f64::consts::PI * s / self.wavelength_mm + self.phase).sin()
    }
}

/// Sum of waves.
pub fn profile(w: &[Wave], s: f64) -> f64 {
    w.iter().map(|w| w.at(s)).sum()
}

/// One axis's cascaded servo loop.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Servo {
    /// Position-loop gain, 1/s.
    pub kp: f64,
    /// Velocity-loop time constant, s.
    pub tau_v: f64,
    /// Current-loop time constant, s.
    pub tau_i: f64,
}

/// A stylus as built (lengths at 20 °C).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Stylus {
    /// Tip id.
    pub id: u32,
    /// Probe type.
    pub probe: String,
    /// Shank length, mm.
    pub l1_mm: f64,
    /// Tip radius, mm.
    pub radius_mm: f64,
    /// Bent limb, mm.
    pub l2_mm: f64,
    /// Bend angle of the limb, degrees.
    pub beta1_deg: f64,
    /// Expansion coefficient of the whole stylus (one material), 1/K.
    pub alpha_per_k: f64,
    /// How much more this stylus bends under the probing force than the reference stylus
    /// (the machine's `probe_k` is the reference's): a cantilever bends as L³/(E·I), so a
    /// long or cranked or steel stylus differs. The catalogue does not state it (1).
    #[serde(default = "one")]
    pub bend_scale: f64,
}

fn one() -> f64 {
    1.0
}

fn mount_freq_default() -> [f64; 3] {
    [140.0; 3]
}

fn mount_damping_default() -> f64 {
    0.15
}

impl Stylus {
    /// Shank and bent limb in probe axes at 20 °C.
    pub fn limbs(&self) -> (V3, V3) {
        let b = self.beta1_deg.to_radians();
        (
            V3::new(0.0, 0.0, -self.l1_mm),
            self.l2_mm * V3::new(b.sin(), 0.0, -b.cos()),
        )
    }
}

/// The styli as the catalogue lists them (what a user starts from): a 50 mm carbon-fibre
/// reference stylus and a steel crank of 40 mm + 40 mm at 90°; the expansion coefficients are
/// the materials' data-sheet values.
pub fn catalogue_styli() -> Vec<Stylus> {
    vec![
        Stylus {
            id: 1,
            probe: "sp25".into(),
            l1_mm: 50.0,
            radius_mm: 1.5,
            l2_mm: 0.0,
            beta1_deg: 0.0,
            alpha_per_k: 2.0e-6,
            bend_scale: 1.0,
        },
        Stylus {
            id: 2,
            probe: "sp25".into(),
            l1_mm: 40.0,
            radius_mm: 1.0,
            l2_mm: 40.0,
            beta1_deg: 90.0,
            alpha_per_k: 11.5e-6,
            bend_scale: 1.0,
        },
    ]
}

/// Sensor noise and resolution.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Noise {
    /// Scale noise (1σ), mm.
    pub scale_sigma_mm: f64,
    /// Scale resolution, mm.
    pub scale_resolution_mm: f64,
    /// Probe noise (1σ, per probe axis), mm.
    pub probe_sigma_mm: f64,
    /// Probe resolution, mm.
    pub probe_resolution_mm: f64,
    /// Temperature sensor noise (1σ), K.
    pub temp_sigma_k: f64,
    /// Temperature resolution, K.
    pub temp_resolution_k: f64,
}

impl Noise {
    /// The noise floor of one surface point along its normal (1σ): scale and probe noise
    /// with their quantisation, mm.
    pub fn point_sigma_mm(&self) -> f64 {
        let q = |r: f64| r * r / 12.0;
        (self.scale_sigma_mm.powi(2)
            + q(self.scale_resolution_mm)
            + self.probe_sigma_mm.powi(2)
            + q(self.probe_resolution_mm))
        .sqrt()
    }
}

/// Every true parameter of one machine.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrueMachine {
    /// The seed it was drawn from.
    pub machine_seed: u64,
    /// Servo loops of x, y, z.
    pub servo: [Servo; 3],
    /// Structure compliance C(p) = C_1 + C_x ξx + C_y ξy + C_z ξz (ξ = p/500 mm), s²: the probe
    /// body is displaced by −C(p)·a (quasi-statically) when the carriages accelerate by a.
    pub compliance: [[[f64; 3]; 3]; 4],
    /// The compliance's change quadratic in X, C_x2 (s²): C(p) above plus C_x2·ξx², the bridge
    /// bending more towards the middle of its travel than a line says (the ring-gauge patent's
    /// example error is quadratic in X). Zero unless `deflection_quadratic` is switched on
    /// (`sim --with deflection_quadratic`), so no other machine changes.
    #[serde(default, skip_serializing_if = "is_zero_matrix")]
    pub compliance_x2: [[f64; 3]; 3],
    /// Resonance of the structure per axis, Hz.
    pub structure_freq_hz: [f64; 3],
    /// Damping ratio of the structure.
    pub structure_damping: f64,
    /// Delay of each axis's scale readout (counter latch and interpolator) behind the
    /// controller's time stamp, s: the reading of axis i at t is the carriage at t + τ_i,
    /// integrated through the machine's own dynamics. Y and Z latch later than X. On an arc
    /// of rotation frequency f this puts Y (Z) ahead of X by the angle 2π·(τ_y − τ_x)·f — the
    /// library's `servo_phase` (see [`TrueMachine::phase_b1`]), which the simulator does not
    /// inject as a formula.
    pub readout_delay_s: [f64; 3],
    /// A second, stiff mode per axis between the scale's reading head and the probe: the
    /// probe head on its mount (displaced against the acceleration, γ > 0) or the reading
    /// head on its bracket (the scale then reads ahead of the carriage, γ < 0), whichever
    /// dominates on that axis. Static compliance γ_i, s²: the probe is displaced by −γ_i·a_i
    /// relative to what the scale reads, through the mode's own resonance
    /// ([`TrueMachine::mount_freq_hz`]). On a steady arc of rotation frequency f this is a
    /// radial gain γ_i (2πf)² — what the library's `servo_gain` f² term describes on arcs,
    /// and its `accel_deflection` diagonal everywhere; the simulator injects no gain formula.
    pub mount_compliance_s2: [f64; 3],
    /// Resonance of the mount mode per axis, Hz (well above the structure's).
    #[serde(default = "mount_freq_default")]
    pub mount_freq_hz: [f64; 3],
    /// Damping ratio of the mount mode.
    #[serde(default = "mount_damping_default")]
    pub mount_damping: f64,
    /// Scale expansion per axis, 1/K (zero points at 0).
    pub scale_alpha: [f64; 3],
    /// Stylus bending per probe axis, mm per mm of deflection, of the reference stylus (each
    /// stylus bends `bend_scale` times as much).
    pub probe_k: [f64; 3],
    /// X guide straightness towards y, mm.
    pub guide_y: Vec<Wave>,
    /// X guide straightness towards z, mm.
    pub guide_z: Vec<Wave>,
    /// X carriage angular error about z (yaw), rad: the library's guide `pitch` term with
    /// `pitch_about: z`. Seen through the Abbe lever of an offset (bent) stylus.
    pub guide_pitch: Vec<Wave>,
    /// Distance from the x guide to the probe-head centre (the fixed Abbe arm), mm. Zero on
    /// this machine: the head sits in line with the guide, the stylus is the whole lever.
    pub abbe_arm_mm: [f64; 3],
    /// X encoder cyclic error (outside the library).
    pub cyclic: Wave,
    /// X backlash at reversal (outside the library), mm.
    pub backlash_mm: f64,
    /// Styli.
    pub styli: Vec<Stylus>,
    /// Sensor noise.
    pub noise: Noise,
    /// Scale counters latching after the controller's time stamp (outside the library
    /// physics of the corrector; zero unless `latching` is switched on).
    #[serde(default)]
    pub latching: Latching,
    /// Direction-dependent probe error (zero unless `probe_lobing` is switched on).
    #[serde(default)]
    pub lobing: ProbeLobing,
    /// The 21 rigid-body errors of the moving-bridge kinematic chain (zero unless
    /// `rigid_body` is switched on).
    #[serde(default)]
    pub rigid_body: RigidBody,
    /// A force probe reporting its probing force (wire v1.5; `None` unless `force_probe` is
    /// switched on, `sim --with force_probe`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub force_probe: Option<ForceProbe>,
}

/// A force probe (or an active probe in constant-force mode): it reports the probing force
/// itself, and the force is not proportional to the deflection. Its springs are preloaded,
///
/// F = F0 + c·|d|  (F0 the preload, c the spring rate, d the probe's deflection),
///
/// and the stylus, a cantilever, bends with the force, not with the deflection: by
/// b = K_F·F·û (K_F = diag(k_i/c) mm per N, k_i the stylus's bending per mm of deflection of
/// a probe without preload, û the direction of the interference in probe axes). A thin wall
/// gives by c_w(s)·F/c (the `wall` module's compliance per mm of deflection at the spring
/// rate). With F0 = 0 this is the deflection-only probe of every other machine. Not in
/// contact, the probe reports no force. The reported force carries its own noise.
///
/// Source idea: Renishaw's calibration of a coordinate positioning apparatus — the variants
/// with a measured probing force (a force probe, or a constant-force probe), where each point
/// is extrapolated to zero force in the force itself.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ForceProbe {
    /// Preload F0, N: the force at zero deflection.
    pub preload_n: f64,
    /// Spring rate c, N per mm of deflection.
    pub rate_n_per_mm: f64,
    /// Noise of the reported force (1σ), N.
    pub noise_n: f64,
}

impl ForceProbe {
    /// The force probe of machine `seed`, its preload scaled by `scale` (the effect factor):
    /// a preload about 0.2 N, a spring rate about 1 N/mm, 1 mN of noise.
    pub fn from_seed(seed: u64, scale: f64) -> ForceProbe {
        let mut r = Rng::new(seed, "force_probe");
        ForceProbe {
            preload_n: jitter(&mut r, 0.2, 0.3) * scale,
            rate_n_per_mm: jitter(&mut r, 1.0, 0.2),
            noise_n: 1.0e-3,
        }
    }

    /// The probe's deflection (probe axes, mm) and its force (N) for the interference
    /// `interference(F)` (probe axes, mm; the interference may depend on the force, as a thin
    /// wall gives under it), with `k` the stylus's bending per mm of deflection per probe
    /// axis: d = δ − K_F·F·û with F = F0 + c·|d|, solved by iteration (the bending is a
    /// percent of the deflection, so each step gains two digits). An interference the stylus
    /// takes alone (its bending under a force below the preload) leaves the deflection 0.
    pub fn solve(&self, interference: impl Fn(f64) -> V3, k: [f64; 3]) -> (V3, f64) {
        let c = self.rate_n_per_mm;
        let kf = V3::new(k[0] / c, k[1] / c, k[2] / c);
        let mut f = self.preload_n;
        let mut d = V3::zeros();
        for _ in 0..8 {
            let delta = interference(f);
            let len = delta.norm();
            if len == 0.0 {
                return (V3::zeros(), 0.0);
            }
            let u = delta / len;
            d = delta - kf.component_mul(&u) * f;
            if d.dot(&u) <= 0.0 {
                // The stylus bends by the whole interference: F = δ/(K_F along û) < F0.
                let along = kf.component_mul(&u).dot(&u);
                return (V3::zeros(), (len / along).min(self.preload_n));
            }
            f = self.preload_n + c * d.norm();
        }
        (d, f)
    }
}

fn is_zero_matrix(m: &[[f64; 3]; 3]) -> bool {
    m.iter().flatten().all(|v| *v == 0.0)
}

/// Latching instants of the scale counters: the reading of axis i at controller time t is
/// the carriage position at t + τ_i (the machine's own dynamics integrated over τ_i).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Latching {
    /// τ_x, τ_y, τ_z, s.
    pub tau_s: [f64; 3],
}

impl Latching {
    fn from_seed(seed: u64) -> Latching {
        let mut r = Rng::new(seed, "latching");
        // Three different delays spread over 20–120 µs, in a seed-dependent order.
        let base = [
            r.range(20e-6, 50e-6),
            r.range(55e-6, 85e-6),
            r.range(90e-6, 120e-6),
        ];
        let k = (r.next_u64() % 6) as usize;
        let perm = [
            [0, 1, 2],
            [0, 2, 1],
            [1, 0, 2],
            [1, 2, 0],
            [2, 0, 1],
            [2, 1, 0],
        ][k];
        Latching {
            tau_s: perm.map(|i| base[i]),
        }
    }
}

/// Lobing of the probe: with φ the probing direction in the probe's u-v plane and sin θ =
/// |d_uv|/|d| (d the true deflection in probe axes), the probe reports its deflection off
/// along d by L = sin θ · Σ_k A_k cos(k(φ − φ_k)) (before stylus bending, i.e. the reported
/// deflection is (d + L·d/|d|)/(1 + k_probe)). A positive L moves the measured point along
/// the probing direction (out of the material).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct ProbeLobing {
    /// Highest harmonic K; the series runs over k = 2…K (as in the calibration document).
    pub max_harmonic: u8,
    /// A_k, k = 2…K, mm.
    pub amplitude_mm: Vec<f64>,
    /// φ_k, k = 2…K, rad.
    pub phase_rad: Vec<f64>,
    /// The correction in the `probe_lobing` document's convention (δ along n = +Σ a_k cos kφ
    /// + b_k sin kφ): a_k = −A_k cos kφ_k, mm.
    pub a_mm: Vec<f64>,
    /// b_k = −A_k sin kφ_k, mm.
    pub b_mm: Vec<f64>,
}

impl ProbeLobing {
    fn from_seed(seed: u64) -> ProbeLobing {
        let mut r = Rng::new(seed, "probe_lobing");
        let amp3 = r.range(0.3e-3, 1.0e-3);
        let amplitude_mm = vec![r.range(0.05, 0.15) * amp3, amp3, r.range(0.05, 0.15) * amp3];
        let phase_rad: Vec<f64> = (0..3)
            .map(|_| r.range(0.0, std::f64::consts::TAU))
            .collect();
        let mut l = ProbeLobing {
            max_harmonic: 4,
            amplitude_mm,
            phase_rad,
            a_mm: vec![],
            b_mm: vec![],
        };
        l.update_document();
        l
    }
    fn update_document(&mut self) {
        let k = |i: usize| (i + 2) as f64;
        self.a_mm = (0..self.amplitude_mm.len())
            .map(|i| -self.amplitude_mm[i] * (k(i) * self.phase_rad[i]).cos())
            .collect();
        self.b_mm = (0..self.amplitude_mm.len())
            .map(|i| -self.amplitude_mm[i] * (k(i) * self.phase_rad[i]).sin())
            .collect();
    }
    /// Scales every amplitude.
    pub fn scale(&mut self, f: f64) {
        self.amplitude_mm.iter_mut().for_each(|a| *a *= f);
        self.update_document();
    }
    /// Whether the probe lobes at all.
    pub fn is_on(&self) -> bool {
        self.amplitude_mm.iter().any(|a| *a != 0.0)
    }
    /// The reported deflection (before stylus bending) for a true deflection `d` in probe axes.
    pub fn apply(&self, d: &V3) -> V3 {
        let dn = d.norm();
        let uv = d.x.hypot(d.y);
        if dn == 0.0 || uv == 0.0 {
            return *d;
        }
        let phi = d.y.atan2(d.x);
        let l: f64 = self
            .amplitude_mm
            .iter()
            .zip(&self.phase_rad)
            .enumerate()
            .map(|(i, (a, p))| a * ((i + 2) as f64 * (phi - p)).cos())
            .sum();
        d + d / dn * (l * uv / dn)
    }
}

/// One error component of an axis as a function of the axis position u, mm or rad:
/// e(u) = c1·ξ + c2·ξ² + w(u), ξ = u / 1000 mm, w a [`Wave`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ErrorFn {
    /// c1, c2.
    pub poly: [f64; 2],
    /// The wave term.
    pub wave: Wave,
}

impl Default for ErrorFn {
    fn default() -> Self {
        ErrorFn {
            poly: [0.0; 2],
            wave: Wave {
                amplitude: 0.0,
                wavelength_mm: 1000.0,
                phase: 0.0,
            },
        }
    }
}

impl ErrorFn {
    /// Value at position `u`.
    pub fn at(&self, u: f64) -> f64 {
        let xi = u / 1000.0;
        self.poly[0] * xi + self.poly[1] * xi * xi + self.wave.at(u)
    }
    fn draw(r: &mut Rng, amp: f64) -> ErrorFn {
        let sgn = |r: &mut Rng| if r.uniform() < 0.5 { -1.0 } else { 1.0 };
        ErrorFn {
            poly: [
                amp * r.range(0.5, 1.5) * sgn(r),
                amp * r.range(0.3, 1.0) * sgn(r),
            ],
            wave: Wave {
                amplitude: amp * r.range(0.2, 0.5),
                wavelength_mm: r.range(250.0, 700.0),
                phase: r.range(0.0, std::f64::consts::TAU),
            },
        }
    }
    fn scale(&mut self, f: f64) {
        self.poly[0] *= f;
        self.poly[1] *= f;
        self.wave.amplitude *= f;
    }
}

/// The six errors of one axis, in machine axes: `translation[j]` is the displacement of the
/// moving part along machine axis j (the axis's own component is its positioning error, the
/// others its straightness), mm; `rotation[j]` its rotation about machine axis j (roll, pitch,
/// yaw as the case may be), rad.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct AxisErrors {
    /// Translations along x, y, z.
    pub translation: [ErrorFn; 3],
    /// Rotations about x, y, z.
    pub rotation: [ErrorFn; 3],
}

impl AxisErrors {
    /// The homogeneous transform of the moving part at position `u` along the unit direction
    /// `dir`: Trans(u·dir + δ(u)) · Rz(γ)·Ry(β)·Rx(α).
    pub fn transform(&self, u: f64, dir: &V3) -> Matrix4<f64> {
        let d = dir * u + V3::from(self.translation.map(|f| f.at(u)));
        let [a, b, g] = self.rotation.map(|f| f.at(u));
        let r = nalgebra::Rotation3::from_axis_angle(&V3::z_axis(), g)
            * nalgebra::Rotation3::from_axis_angle(&V3::y_axis(), b)
            * nalgebra::Rotation3::from_axis_angle(&V3::x_axis(), a);
        let mut t = Matrix4::identity();
        t.fixed_view_mut::<3, 3>(0, 0).copy_from(r.matrix());
        t.fixed_view_mut::<3, 1>(0, 3).copy_from(&d);
        t
    }
}

/// The rigid-body errors of a moving-bridge machine (Y carries the bridge over the table, X
/// the carriage along the bridge, Z the ram in the carriage). The tip centre is
/// T_Y(y)·T_X(x)·T_Z(z)·(offset, 1) with each T an exact homogeneous transform
/// ([`AxisErrors::transform`]); the axes move along the unit directions ŷ = (0, 1, 0),
/// x̂ = (1, s_xy, 0)/|·|, ẑ = (s_zx, s_zy, 1)/|·| (squareness errors, rad). With every error
/// zero the tip is (x, y, z) + offset.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct RigidBody {
    /// The chain, base first.
    pub chain: [char; 3],
    /// The bridge (Y axis).
    pub y: AxisErrors,
    /// The carriage (X axis).
    pub x: AxisErrors,
    /// The ram (Z axis).
    pub z: AxisErrors,
    /// Squareness of X to Y, rad.
    pub s_xy: f64,
    /// Squareness of Z to X, rad.
    pub s_zx: f64,
    /// Squareness of Z to Y, rad.
    pub s_zy: f64,
}

impl RigidBody {
    fn from_seed(seed: u64) -> RigidBody {
        let mut r = Rng::new(seed, "rigid_body");
        let axis = |r: &mut Rng| AxisErrors {
            translation: [0, 1, 2].map(|_| ErrorFn::draw(r, 2.5e-3)),
            rotation: [0, 1, 2].map(|_| ErrorFn::draw(r, 3.0e-6)),
        };
        let y = axis(&mut r);
        let x = axis(&mut r);
        let z = axis(&mut r);
        let mut sq = || r.range(2e-6, 8e-6) * if r.uniform() < 0.5 { -1.0 } else { 1.0 };
        RigidBody {
            chain: ['y', 'x', 'z'],
            y,
            x,
            z,
            s_xy: sq(),
            s_zx: sq(),
            s_zy: sq(),
        }
    }
    /// Scales every error.
    pub fn scale(&mut self, f: f64) {
        for a in [&mut self.y, &mut self.x, &mut self.z] {
            a.translation.iter_mut().for_each(|e| e.scale(f));
            a.rotation.iter_mut().for_each(|e| e.scale(f));
        }
        self.s_xy *= f;
        self.s_zx *= f;
        self.s_zy *= f;
    }
    /// The true tip centre for axis positions `p` and stylus offset `offset` (machine axes).
    pub fn tip(&self, p: &V3, offset: &V3) -> V3 {
        let dy = V3::y();
        let dx = V3::new(1.0, self.s_xy, 0.0).normalize();
        let dz = V3::new(self.s_zx, self.s_zy, 1.0).normalize();
        let t =
            self.y.transform(p.y, &dy) * self.x.transform(p.x, &dx) * self.z.transform(p.z, &dz);
        let h = t * Vector4::new(offset.x, offset.y, offset.z, 1.0);
        V3::new(h.x, h.y, h.z)
    }
}

fn jitter(r: &mut Rng, x: f64, rel: f64) -> f64 {
    x * (1.0 + rel * (2.0 * r.uniform() - 1.0))
}

impl TrueMachine {
    /// The machine of seed `seed`: plausible parameters for a mid-size bridge CMM.
    pub fn from_seed(seed: u64) -> TrueMachine {
        let mut r = Rng::new(seed, "machine");
        let servo = [
            Servo {
                kp: jitter(&mut r, 85.0, 0.1),
                tau_v: jitter(&mut r, 0.0022, 0.15),
                tau_i: jitter(&mut r, 0.0004, 0.2),
            },
            Servo {
                kp: jitter(&mut r, 70.0, 0.1),
                tau_v: jitter(&mut r, 0.0025, 0.15),
                tau_i: jitter(&mut r, 0.0004, 0.2),
            },
            Servo {
                kp: jitter(&mut r, 95.0, 0.1),
                tau_v: jitter(&mut r, 0.0018, 0.15),
                tau_i: jitter(&mut r, 0.0004, 0.2),
            },
        ];
        // Compliance: the bridge and ram bend more with the ram extended (low z) and the
        // carriage far along the bridge (high y); cross-coupling x→z (nodding).
        let mut c = [[[0.0; 3]; 3]; 4];
        c[0] = [
            [
                jitter(&mut r, 10.0e-6, 0.2),
                jitter(&mut r, 0.8e-6, 0.5),
                0.0,
            ],
            [
                jitter(&mut r, 0.2e-6, 0.5),
                jitter(&mut r, 12.0e-6, 0.2),
                0.0,
            ],
            [
                jitter(&mut r, 2.0e-6, 0.4),
                0.0,
                jitter(&mut r, 4.0e-6, 0.2),
            ],
        ];
        c[2] = [[0.0; 3], [0.0, jitter(&mut r, 3.0e-6, 0.3), 0.0], [0.0; 3]];
        c[3] = [
            [jitter(&mut r, -4.0e-6, 0.3), 0.0, 0.0],
            [0.0, jitter(&mut r, -2.5e-6, 0.3), 0.0],
            [0.0; 3],
        ];
        let waves = |r: &mut Rng, amp: f64| {
            (0..3)
                .map(|_| Wave {
                    amplitude: amp * r.range(0.4, 1.0) * if r.uniform() < 0.5 { -1.0 } else { 1.0 },
                    wavelength_mm: r.range(300.0, 800.0),
                    phase: r.range(0.0, std::f64::consts::TAU),
                })
                .collect::<Vec<_>>()
        };
        let guide_y = waves(&mut r, 5.0e-3);
        let guide_z = waves(&mut r, 3.0e-3);
        let guide_pitch = waves(&mut r, 20e-6);
        TrueMachine {
            machine_seed: seed,
            servo,
            compliance: c,
            compliance_x2: [[0.0; 3]; 3],
            structure_freq_hz: [
                jitter(&mut r, 48.0, 0.1),
                jitter(&mut r, 42.0, 0.1),
                jitter(&mut r, 45.0, 0.1),
            ],
            structure_damping: 0.5,
            // τ_x, then Y 65–125 µs and Z 20–40 µs later (three draws, as before this field).
            readout_delay_s: {
                let x = jitter(&mut r, 20.0e-6, 0.3);
                let dy = jitter(&mut r, 95.0e-6, 0.3);
                let dz = jitter(&mut r, 32.0e-6, 0.3);
                [x, x + dy, x + dz]
            },
            mount_compliance_s2: [
                jitter(&mut r, 18.0e-6, 0.2),
                jitter(&mut r, -12.0e-6, 0.2),
                0.0,
            ],
            scale_alpha: [
                jitter(&mut r, 10.5e-6, 0.1),
                jitter(&mut r, 10.5e-6, 0.1),
                jitter(&mut r, 8.0e-6, 0.1),
            ],
            probe_k: [
                jitter(&mut r, 0.012, 0.3),
                jitter(&mut r, 0.018, 0.3),
                jitter(&mut r, 0.006, 0.3),
            ],
            guide_y,
            guide_z,
            guide_pitch,
            abbe_arm_mm: [0.0, 0.0, 0.0],
            cyclic: Wave {
                amplitude: jitter(&mut r, 2.0e-3, 0.2),
                wavelength_mm: 4.0,
                phase: r.range(0.0, std::f64::consts::TAU),
            },
            backlash_mm: jitter(&mut r, 3.0e-3, 0.2),
            // As built: lengths and radii off their catalogue values by a few tens and a few
            // µm, each stylus of one material (a carbon-fibre reference, a steel crank).
            styli: {
                let mut r = Rng::new(seed, "styli");
                let mut off = |mm: f64| mm * r.range(-1.0, 1.0);
                // The reference (lowest id) defines `probe_k`; the steel crank's two 40 mm
                // limbs bend 1.3–1.9 times as much as the 50 mm carbon-fibre shank.
                let mut rb = Rng::new(seed, "bending");
                let first = catalogue_styli().iter().map(|c| c.id).min();
                catalogue_styli()
                    .into_iter()
                    .map(|c| Stylus {
                        bend_scale: if Some(c.id) == first {
                            1.0
                        } else {
                            jitter(&mut rb, 1.6, 0.2)
                        },
                        l1_mm: c.l1_mm + off(0.05),
                        radius_mm: c.radius_mm + off(1.5e-3),
                        l2_mm: if c.l2_mm > 0.0 {
                            c.l2_mm + off(0.05)
                        } else {
                            0.0
                        },
                        alpha_per_k: c.alpha_per_k * (1.0 + off(0.1)),
                        ..c
                    })
                    .collect()
            },
            noise: Noise {
                scale_sigma_mm: 0.06e-3,
                scale_resolution_mm: 0.05e-3,
                probe_sigma_mm: 0.08e-3,
                probe_resolution_mm: 0.02e-3,
                temp_sigma_k: 0.002,
                temp_resolution_k: 0.001,
            },
            // Its own stream, so that no other parameter moved when the mode was added.
            mount_freq_hz: {
                let mut r = Rng::new(seed, "mount");
                [0, 1, 2].map(|_| r.range(120.0, 170.0))
            },
            mount_damping: 0.15,
            latching: Latching::from_seed(seed),
            lobing: ProbeLobing::from_seed(seed),
            rigid_body: RigidBody::from_seed(seed),
            force_probe: None,
        }
    }

    /// What the scale readouts' delays amount to on an arc, in the library's terms: the lag of
    /// Y and Z behind X per hertz of rotation, b1 = −2π·(τ_i − τ_x) rad/Hz. A reading at
    /// t + τ_i puts the measured point ahead by τ_i·v_i = 2πf·τ_i·(ŵ × r)_i, as a probe body
    /// lagging by −2πf·τ_i·(ŵ × r)_i would (the library's φ is a lag: the body displaced by
    /// φ·(ŵ × r), the point measured short of it); the part common to all axes slides the point
    /// along the arc and is not an error of the surface.
    pub fn phase_b1(&self) -> [f64; 2] {
        let d = self.readout_delay_s;
        [
            -std::f64::consts::TAU * (d[1] - d[0]),
            -std::f64::consts::TAU * (d[2] - d[0]),
        ]
    }

    /// Structure compliance at position p, s².
    pub fn compliance_at(&self, p: &V3) -> Matrix3<f64> {
        let xi = [1.0, p.x / 500.0, p.y / 500.0, p.z / 500.0];
        let mut m = Matrix3::zeros();
        for (k, w) in xi.iter().enumerate() {
            m += Matrix3::from_fn(|i, j| self.compliance[k][i][j]) * *w;
        }
        m + Matrix3::from_fn(|i, j| self.compliance_x2[i][j]) * xi[1] * xi[1]
    }

    /// The quadratic-in-X compliance as `deflection_quadratic` switches it on (scale 1): 40 %
    /// of the constant compliance on P_xx, 30 % on P_yy and on the nodding P_zx — what the
    /// machine's own draw gives, so no random number is drawn for it.
    pub fn quadratic_compliance(&self) -> [[f64; 3]; 3] {
        let c = &self.compliance[0];
        [
            [0.4 * c[0][0], 0.0, 0.0],
            [0.0, 0.3 * c[1][1], 0.0],
            [0.3 * c[2][0], 0.0, 0.0],
        ]
    }

    /// The quasi-static compliance the corrector can describe, per monomial k (1, ξx, ξy, ξz)
    /// and axes i, j: the structure's plus, on the diagonal of the constant term, the mount
    /// mode's (both move the probe by −C·a relative to the scales at low frequency).
    pub fn compliance_total(&self, k: usize, i: usize, j: usize) -> f64 {
        let mount = if k == 0 && i == j {
            self.mount_compliance_s2[i]
        } else {
            0.0
        };
        self.compliance[k][i][j] + mount
    }

    /// The stylus of a tip id.
    pub fn stylus(&self, id: u32) -> Option<&Stylus> {
        self.styli.iter().find(|s| s.id == id)
    }
}

/// Rotation of the articulating head, probe axes → machine axes: swivel A1 about z, then tilt
/// A2 about the swivelled x axis (the convention of the calibration document).
pub fn head_rotation(a1_deg: f64, a2_deg: f64) -> Matrix3<f64> {
    let (a1, a2) = (a1_deg.to_radians(), a2_deg.to_radians());
    let rz = nalgebra::Rotation3::from_axis_angle(&V3::z_axis(), a1);
    let rx = nalgebra::Rotation3::from_axis_angle(&V3::x_axis(), a2);
    (rz * rx).into_inner()
}
