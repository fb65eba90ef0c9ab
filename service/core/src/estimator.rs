//! The motion estimator: what the machine did, predicted from what it was told to do.
//!
//! Equation: E = G_N·C per axis (G_N = G1·G2, discretised at the sample period, see
//! [`transfer`](crate::transfer)); A = Ë from the model state (the second derivative of the
//! estimate, never of the noisy scales). On an arc of commanded centre c the rotation
//! frequency is the estimate's angular rate about c, f = |r × V|/(2π|r|²) with r = E − c,
//! and the axis (r × V)/|r × V| — right at constant speed, while the scan speeds up or
//! slows down, and whatever the servo's amplitude loss (at constant speed on a commanded
//! circle of radius R the estimate is a circle of radius R·|G(jω)| about c traversed at ω,
//! so f = ω/2π exactly). It uses E and V only: V carries no polygon bias (below) to first
//! order, A does. (Until this round f was √(|A_n|/R)/(2π) with the commanded R: low by half
//! A's polygon bias plus half the amplitude loss, 0.19–0.23 % at 1 kHz on the campaign's
//! rings; the lab absorbed it in φ's b0, b1 and b2: `lab fit` gave φ_y's b1 0.9–1.7 % steep
//! and b0 +4e-7…+1.3e-6 rad on machines 101–110, 0.15–0.6 % and ≤ 3.7e-7 rad with f as
//! above; with the servo phase alone in the simulator 0.74 → 0.06 % on machine 101, 1.08 →
//! 0.14 % on 6113, `tests/arc_phase.rs`.)
//!
//! Commands without an arc (a controller streaming circles as points): the arc is taken from
//! the estimated path itself, its osculating circle — curvature κ = |V × A|/|V|³, radius
//! 1/κ, centre E + n̂/κ (n̂ the unit part of A normal to V), so f = |V|·κ/(2π) =
//! |V × A|/(2π|V|²) and the axis (V × A)/|V × A|. [`Estimator::step`] fills the estimate's
//! command with that arc when the command carries none, the path bends (radius between
//! [`MIN_ESTIMATED_RADIUS_MM`] and [`MAX_ESTIMATED_RADIUS_MM`]) and the speed is above
//! [`MIN_ESTIMATED_ARC_SPEED_MM_S`]; at constant speed on a commanded circle of radius R the
//! estimate is a circle of radius R·|G(jω)| about the same centre, so the estimated centre is
//! the commanded one and f = ω/2π, but for A's polygon bias: it lengthens the radius and
//! lowers f by as much, so f·|s − c| (what the arc effects multiply) keeps no bias.
//!
//! Accuracy: the discretised model sees the command as a polygon through its samples, so at
//! the sample instants A carries a relative bias of about T²·h'(0)/12 (T the period, h the
//! impulse response of G_N; T²/(12·τ1·τ2) for two lags: 0.35 % for 12 ms and 2 ms at 1 kHz).
//! The bias is a fixed scale factor at scanning frequencies and is absorbed by every fitted
//! coefficient that multiplies A, because fitting and correcting use the same estimator.
//!
//! Source idea: the dynamic-error correction of scanning CMMs (e.g. Renishaw's patents on
//! scanning at speed) drives the deflection model with the acceleration predicted from the
//! command through a nominal servo model, because scale data are too noisy to differentiate.

use crate::sample::{CommandSample, Vec3};
use crate::transfer::{Discrete, DiscreteState};
use std::sync::Arc;

/// Slowest estimated speed at which an arc is taken from the path's curvature, mm/s.
pub const MIN_ESTIMATED_ARC_SPEED_MM_S: f64 = 0.5;
/// Smallest radius of an arc taken from the path's curvature, mm (tighter bends are
/// corners, not scanned circles).
pub const MIN_ESTIMATED_RADIUS_MM: f64 = 0.5;
/// Largest radius of an arc taken from the path's curvature, mm (flatter bends are lines).
pub const MAX_ESTIMATED_RADIUS_MM: f64 = 2000.0;

/// The estimate at one command instant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Estimate {
    /// The command it was computed from; when it carries no arc (`arc_radius` 0) and the
    /// estimated path bends, its arc centre and radius are the estimated path's osculating
    /// circle ([`osculating_arc`]).
    pub cmd: CommandSample,
    /// Estimated position, mm.
    pub pos: Vec3,
    /// Estimated velocity, mm/s.
    pub vel: Vec3,
    /// Estimated acceleration, mm/s².
    pub acc: Vec3,
}

/// Runs G_N on the command stream.
#[derive(Debug, Clone)]
pub struct Estimator {
    model: Arc<[Discrete; 3]>,
    state: [DiscreteState; 3],
    /// Commands stepped since the last (re)start; the estimate is settled after
    /// `settle_samples` of them.
    steps: u64,
    started: bool,
    /// Steps after which the estimate is settled: the slowest axis model's.
    settle_samples: u64,
}

impl Estimator {
    /// A new estimator for the per-axis models.
    pub fn new(model: Arc<[Discrete; 3]>) -> Estimator {
        let state = [
            model[0].steady(0.0),
            model[1].steady(0.0),
            model[2].steady(0.0),
        ];
        Estimator {
            settle_samples: settle_samples(&model),
            model,
            state,
            steps: 0,
            started: false,
        }
    }

    /// The models in use.
    pub fn model(&self) -> &Arc<[Discrete; 3]> {
        &self.model
    }

    /// Restarts at rest at the command `c` (first sample, after a gap or a model change).
    pub fn restart(&mut self, c: &CommandSample) -> Estimate {
        for i in 0..3 {
            self.state[i] = self.model[i].steady(c.pos[i]);
        }
        self.steps = 0;
        self.started = true;
        Estimate {
            cmd: *c,
            pos: c.pos,
            vel: Vec3::zeros(),
            acc: Vec3::zeros(),
        }
    }

    /// Swaps the models and restarts at `c`.
    pub fn switch_model(&mut self, model: Arc<[Discrete; 3]>, c: &CommandSample) -> Estimate {
        self.settle_samples = settle_samples(&model);
        self.model = model;
        self.restart(c)
    }

    /// Advances one sample period to the command `c`.
    #[inline]
    pub fn step(&mut self, c: &CommandSample) -> Estimate {
        let mut e = Estimate {
            cmd: *c,
            pos: Vec3::zeros(),
            vel: Vec3::zeros(),
            acc: Vec3::zeros(),
        };
        self.step_into(c, &mut e);
        e
    }

    /// [`Self::step`], writing the estimate into `e` (where the caller keeps it, rather than
    /// copying it there).
    #[inline]
    pub fn step_into(&mut self, c: &CommandSample, e: &mut Estimate) {
        if !self.started {
            *e = self.restart(c);
            return;
        }
        let [x, y, z] = Discrete::step3(&self.model, &mut self.state, c.pos.into());
        e.cmd = *c;
        e.pos = Vec3::new(x.y, y.y, z.y);
        e.vel = Vec3::new(x.dy, y.dy, z.dy);
        e.acc = Vec3::new(x.ddy, y.ddy, z.ddy);
        self.steps += 1;
        if c.arc_radius <= 0.0 {
            if let Some((center, radius)) = osculating_arc(&e.pos, &e.vel, &e.acc) {
                e.cmd.arc_center = center;
                e.cmd.arc_radius = radius;
            }
        }
    }

    /// True once a restart's transient has decayed.
    #[inline]
    pub fn settled(&self) -> bool {
        self.steps >= self.settle_samples
    }
}

/// Samples for the slowest of the axis models to settle.
fn settle_samples(model: &[Discrete; 3]) -> u64 {
    model.iter().map(|m| m.settle_samples).max().unwrap_or(0)
}

/// Rotation on an arc: (f in Hz, unit angular-velocity axis), both zero off arcs or at rest.
///
/// f = |r × V|/(2π|r|²), r = `pos` − `center` (module doc). |r|² is taken at least
/// (`radius`/2)²: an estimate nearer the centre than half the commanded radius is not on the
/// arc (a transient), and its rate about c would mean nothing.
#[inline]
pub fn rotation(pos: &Vec3, vel: &Vec3, center: &Vec3, radius: f64) -> (f64, Vec3) {
    if radius <= 0.0 {
        return (0.0, Vec3::zeros());
    }
    let r = pos - center;
    let w = r.cross(vel);
    let wn = w.norm();
    let vn = vel.norm();
    if wn <= 1e-12 * (1.0 + radius * vn) || vn == 0.0 {
        return (0.0, Vec3::zeros());
    }
    let r2 = r.norm_squared().max(0.25 * radius * radius);
    const INV_TAU: f64 = 1.0 / (2.0 * std::f64::consts::PI);
    (wn / r2 * INV_TAU, w * (1.0 / wn))
}

/// The osculating circle of the estimated path at `pos` (centre, radius in mm), for commands
/// that carry no arc: radius 1/κ with κ = |V × A|/|V|³, centre `pos` + n̂/κ with n̂ the unit
/// component of A normal to V. `None` below [`MIN_ESTIMATED_ARC_SPEED_MM_S`] (near a stop the
/// direction of travel means nothing) and outside [`MIN_ESTIMATED_RADIUS_MM`] ..=
/// [`MAX_ESTIMATED_RADIUS_MM`] (corners, lines). With it, [`rotation`] gives
/// f = |V × A|/(2π|V|²) and the axis (V × A)/|V × A|.
#[inline]
pub fn osculating_arc(pos: &Vec3, vel: &Vec3, acc: &Vec3) -> Option<(Vec3, f64)> {
    let v2 = vel.norm_squared();
    if v2.is_nan() || v2 < MIN_ESTIMATED_ARC_SPEED_MM_S * MIN_ESTIMATED_ARC_SPEED_MM_S {
        return None;
    }
    // Normal acceleration: |a_n| = |V × A|/|V| = |V|²·κ.
    let a_n = acc - vel * (acc.dot(vel) / v2);
    let a_nn = a_n.norm();
    // radius = |V|²/|a_n|, checked without dividing by a vanishing |a_n|.
    if a_nn.is_nan() || a_nn * MAX_ESTIMATED_RADIUS_MM < v2 || a_nn * MIN_ESTIMATED_RADIUS_MM > v2 {
        return None;
    }
    let radius = v2 / a_nn;
    let center = pos + a_n * (radius / a_nn);
    (center.iter().all(|x| x.is_finite()) && radius.is_finite()).then_some((center, radius))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transfer::TransferFunction;
    use std::f64::consts::PI;

    fn model(tau: f64, tau_p: f64, t: f64) -> Arc<[Discrete; 3]> {
        let g = TransferFunction::FirstOrder { tau_s: tau }
            .rational()
            .unwrap()
            .mul(
                &TransferFunction::FirstOrder { tau_s: tau_p }
                    .rational()
                    .unwrap(),
            );
        let d = Discrete::new(&g, t).unwrap();
        Arc::new([d.clone(), d.clone(), d])
    }

    fn cmd(t: f64, p: Vec3, c: Vec3, r: f64) -> CommandSample {
        CommandSample {
            seq: 0,
            t_ns: (t * 1e9) as i64,
            pos: p,
            arc_center: c,
            arc_radius: r,
            segment_id: 0,
        }
    }

    #[test]
    fn circle_at_constant_speed_gives_v2_over_r_and_f() {
        let (tau, taup, t) = (0.012, 0.002, 0.001);
        let (r, v) = (25.0, 50.0);
        let w = v / r;
        let c0 = Vec3::new(100.0, 200.0, 50.0);
        let mut est = Estimator::new(model(tau, taup, t));
        // Constant speed from t = 0 (a step in velocity: the transient must die out).
        let mut last = None;
        for k in 0..2000 {
            let th = w * k as f64 * t;
            let p = c0 + Vec3::new(r * th.cos(), r * th.sin(), 0.0);
            last = Some(est.step(&cmd(k as f64 * t, p, c0, r)));
        }
        let e = last.unwrap();
        // Exact steady state: the estimate is a circle of radius r·|G(jω)| traversed at ω,
        // so |A| = ω² r |G(jω)|; |G(jω)| = 1/sqrt((1+(ωτ)²)(1+(ωτp)²)).
        let g = 1.0 / ((1.0 + (w * tau).powi(2)) * (1.0 + (w * taup).powi(2))).sqrt();
        // The model sees the command as a polygon (linear between samples): A at the samples
        // is biased by about T²/(12·τ·τp) relative (0.35 % here), see the module doc.
        let a = e.acc.norm();
        let bias = t * t / (12.0 * tau * taup);
        assert!(
            (a / (w * w * r * g) - (1.0 - bias)).abs() < 5e-4,
            "{a} vs {}",
            w * w * r * g
        );
        assert!(
            (a - v * v / r).abs() < 5e-3 * a,
            "|A| = {a}, v²/R = {}",
            v * v / r
        );
        // A points at the centre.
        let radial = (c0 - e.pos).normalize();
        assert!(e.acc.normalize().dot(&radial) > 0.9999);
        // f: the estimate's rate about the commanded centre, exact (A's bias does not enter).
        let (f, axis) = rotation(&e.pos, &e.vel, &c0, r);
        assert!((f - w / (2.0 * PI)).abs() < 2e-5 * f, "{f}");
        assert!((axis - Vec3::z()).norm() < 1e-9);
        assert!(est.settled());
    }

    #[test]
    fn commanded_arc_rate_is_exact_where_the_acceleration_formula_was_low() {
        // The campaign's ring (R = 23.8 mm) at its four speeds, 1 kHz, lags of 11.2 and 2 ms:
        // f from the estimate's rate about the commanded centre is ω/2π to 2e-5, both senses.
        // The acceleration formula used before, √(A_n/R)/(2π), is low by half A's polygon
        // bias plus half the amplitude loss (0.19–0.23 %): what biased φ's b1.
        let (tau, taup, t) = (0.0112, 0.002, 0.001);
        let r = 23.8;
        let c0 = Vec3::new(250.0, 200.0, -300.0);
        for v in [10.0, 30.0, 60.0, 90.0] {
            for dir in [1.0, -1.0] {
                let w = v / r;
                let mut est = Estimator::new(model(tau, taup, t));
                let mut e = None;
                for k in 0..2500 {
                    let th = dir * w * k as f64 * t;
                    let p = c0 + Vec3::new(r * th.cos(), r * th.sin(), 0.0);
                    e = Some(est.step(&cmd(k as f64 * t, p, c0, r)));
                }
                let e = e.unwrap();
                let exact = w / (2.0 * PI);
                let (f, axis) = rotation(&e.pos, &e.vel, &c0, r);
                assert!(
                    (f / exact - 1.0).abs() < 2e-5,
                    "v {v}: f/exact = {}",
                    f / exact
                );
                assert!((axis - Vec3::z() * dir).norm() < 1e-9);
                let v2 = e.vel.norm_squared();
                let a_n = (e.acc * v2 - e.vel * e.acc.dot(&e.vel)).norm() / v2;
                let old = (a_n / r).sqrt() / (2.0 * PI);
                let low = 1.0 - old / exact;
                assert!(
                    (1.5e-3..3e-3).contains(&low),
                    "v {v}: old formula low by {low}"
                );
            }
        }
    }

    #[test]
    fn commanded_arc_rate_follows_the_estimate_while_speeding_up() {
        // Spin-up on a commanded arc: f is the estimate's tangential speed over its distance
        // from the centre at every sample, and zero at rest.
        let (tau, taup, t) = (0.0112, 0.002, 0.001);
        let (r, vmax, ramp) = (23.8, 90.0, 0.6);
        let c0 = Vec3::new(10.0, -5.0, 3.0);
        let mut est = Estimator::new(model(tau, taup, t));
        let s = |tt: f64| {
            if tt < ramp {
                0.5 * vmax / ramp * tt * tt
            } else {
                vmax * (tt - ramp / 2.0)
            }
        };
        let e0 = est.step(&cmd(0.0, c0 + Vec3::new(r, 0.0, 0.0), c0, r));
        assert_eq!(rotation(&e0.pos, &e0.vel, &c0, r), (0.0, Vec3::zeros()));
        for k in 1..800 {
            let tt = k as f64 * t;
            let th = s(tt) / r;
            let e = est.step(&cmd(
                tt,
                c0 + Vec3::new(r * th.cos(), r * th.sin(), 0.0),
                c0,
                r,
            ));
            let (f, _) = rotation(&e.pos, &e.vel, &c0, r);
            let rr = e.pos - c0;
            let v_t = Vec3::z().cross(&rr.normalize()).dot(&e.vel);
            let want = v_t / (2.0 * PI * rr.norm());
            assert!(
                (f - want).abs() <= 1e-12 * want.max(1e-9),
                "t {tt}: {f} vs {want}"
            );
        }
    }

    #[test]
    fn spin_up_follows_the_estimate_not_the_command() {
        // Command: speed ramps from 0 to 60 mm/s over 0.1 s along a circle; the command's
        // own acceleration jumps at the start, the estimate's rises smoothly.
        let (tau, taup, t) = (0.012, 0.002, 0.001);
        let (r, vmax, ramp) = (20.0, 60.0, 0.1);
        let c0 = Vec3::zeros();
        let mut est = Estimator::new(model(tau, taup, t));
        let s = |tt: f64| {
            if tt < ramp {
                0.5 * vmax / ramp * tt * tt
            } else {
                vmax * (tt - ramp / 2.0)
            }
        };
        let pos = |tt: f64| {
            let th = s(tt.max(0.0)) / r;
            Vec3::new(r * th.cos(), r * th.sin(), 0.0)
        };
        est.step(&cmd(0.0, pos(0.0), c0, r));
        let mut at = vec![];
        for k in 1..=60 {
            let tt = k as f64 * t;
            let e = est.step(&cmd(tt, pos(tt), c0, r));
            at.push((tt, e));
        }
        // At t = 2 ms the command's tangential acceleration is already vmax/ramp = 600 mm/s²;
        // the estimate (two lags, 12 and 2 ms) has barely started.
        let (_, e2) = at[1];
        let tangent = Vec3::new(0.0, 1.0, 0.0);
        assert!(e2.acc.dot(&tangent) < 0.2 * 600.0, "{:?}", e2.acc);
        // Closed form of the tangential acceleration of G(s) = 1/((τs+1)(τp s+1)) driven by
        // a step of 600 mm/s²: a(t) = 600·(1 − (τ e^{−t/τ} − τp e^{−t/τp})/(τ − τp)).
        // (the path curvature adds only a radial part at these small angles).
        for (tt, e) in &at[10..] {
            let exact = 600.0
                * (1.0 - (tau * (-tt / tau).exp() - taup * (-tt / taup).exp()) / (tau - taup));
            let a_t = e.acc.dot(&(Vec3::z().cross(&(e.pos - c0)).normalize()));
            assert!(
                (a_t - exact).abs() < 0.02 * 600.0,
                "t={tt}: {a_t} vs {exact}"
            );
        }
    }

    /// f and axis from a command stream without arcs (the osculating circle filled in).
    fn rotation_of(e: &Estimate) -> (f64, Vec3) {
        rotation(&e.pos, &e.vel, &e.cmd.arc_center, e.cmd.arc_radius)
    }

    #[test]
    fn osculating_arc_of_an_exact_circle() {
        // Position, velocity and acceleration of a circle of radius 25 mm at 40 mm/s, tilted
        // out of the XY plane: f = v/(2πR), the centre, and the axis by the right-hand rule.
        let (r, v) = (25.0, 40.0);
        let w = v / r;
        let c0 = Vec3::new(300.0, -20.0, 7.0);
        let (u1, u2) = (
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(0.0, 0.6, 0.8), // u1 × u2 = (0, −0.8, 0.6)
        );
        for dir in [1.0, -1.0] {
            for th in [0.0f64, 1.0, 2.5, 4.0] {
                let p = c0 + (u1 * th.cos() + u2 * th.sin()) * r;
                let vel = (-u1 * th.sin() + u2 * th.cos()) * (dir * v);
                let acc = (p - c0) * (-w * w);
                let (c, rr) = osculating_arc(&p, &vel, &acc).unwrap();
                assert!(
                    (c - c0).norm() < 1e-9 && (rr - r).abs() < 1e-9,
                    "{c:?} {rr}"
                );
                let (f, axis) = rotation(&p, &vel, &c, rr);
                assert!((f / (v / (2.0 * PI * r)) - 1.0).abs() < 1e-3, "{f}");
                assert!((axis - u1.cross(&u2) * dir).norm() < 1e-9, "{axis:?}");
                // A tangential part (speeding up) changes neither.
                let (c2, r2) = osculating_arc(&p, &vel, &(acc + vel * 3.0)).unwrap();
                assert!((c2 - c0).norm() < 1e-9 && (r2 - r).abs() < 1e-9);
            }
        }
        // Lines, stops and corners carry no arc.
        let x = Vec3::x();
        assert_eq!(osculating_arc(&c0, &(x * 40.0), &Vec3::zeros()), None);
        assert_eq!(osculating_arc(&c0, &(x * 40.0), &(x * 500.0)), None);
        assert_eq!(
            osculating_arc(&c0, &(x * 40.0), &Vec3::new(0.0, 0.5, 0.0)),
            None
        );
        assert_eq!(
            osculating_arc(&c0, &(x * 0.3), &Vec3::new(0.0, 0.01, 0.0)),
            None
        );
        assert_eq!(osculating_arc(&c0, &Vec3::zeros(), &Vec3::y()), None);
        assert_eq!(
            osculating_arc(&c0, &(x * 1.0), &Vec3::new(0.0, 1e4, 0.0)),
            None
        );
        let nan = Vec3::new(f64::NAN, 0.0, 0.0);
        assert_eq!(osculating_arc(&c0, &nan, &Vec3::y()), None);
        assert_eq!(osculating_arc(&c0, &(x * 40.0), &nan), None);
        let inf = Vec3::y() * f64::INFINITY;
        assert_eq!(osculating_arc(&c0, &(x * 40.0), &inf), None);
    }

    #[test]
    fn circle_streamed_as_points_gets_its_rotation_from_the_estimated_path() {
        // R = 25 mm at 40 mm/s, CCW and CW, commanded without centre and radius.
        let (tau, taup, t) = (0.012, 0.002, 0.001);
        let (r, v) = (25.0, 40.0);
        let w = v / r;
        let c0 = Vec3::new(100.0, 200.0, 50.0);
        for dir in [1.0, -1.0] {
            let mut est = Estimator::new(model(tau, taup, t));
            let mut with_arc = Estimator::new(model(tau, taup, t));
            let (mut e, mut ea) = (None, None);
            for k in 0..3000 {
                let th = dir * w * k as f64 * t;
                let p = c0 + Vec3::new(r * th.cos(), r * th.sin(), 0.0);
                e = Some(est.step(&cmd(k as f64 * t, p, Vec3::zeros(), 0.0)));
                ea = Some(with_arc.step(&cmd(k as f64 * t, p, c0, r)));
            }
            let (e, ea) = (e.unwrap(), ea.unwrap());
            // The estimated centre is the commanded one (the estimate's circle is smaller by
            // |G(jω)|, about the same centre), but for the polygon bias of A (see the module
            // doc), which lengthens the radius |V|²/|A_n| by `bias` and moves the centre by as
            // much along the normal.
            let bias = t * t / (12.0 * tau * taup);
            let g = 1.0 / ((1.0 + (w * tau).powi(2)) * (1.0 + (w * taup).powi(2))).sqrt();
            let rr = e.cmd.arc_radius;
            assert!((rr / (r * g) - (1.0 + bias)).abs() < 2e-4, "{rr}");
            let off = e.cmd.arc_center - c0;
            assert!(off.norm() < 1.2 * bias * r, "{off:?}");
            assert!(off.dot(&(c0 - e.pos).normalize()) > 0.99 * off.norm());
            let (f, axis) = rotation_of(&e);
            let exact = v / (2.0 * PI * r);
            // Within 0.1 % of v/(2πR) apart from the polygon bias of A, which the
            // estimator-independent test above does not have.
            assert!(
                (f / exact - (1.0 - bias)).abs() < 1e-3,
                "f = {f}, v/(2πR) = {exact}"
            );
            assert!((f / exact - 1.0).abs() < 5e-3);
            assert!((axis - Vec3::z() * dir).norm() < 1e-9, "{axis:?}");
            // The commanded arc gives ω/2π itself; the osculating circle a rate lower and a
            // lever longer by A's polygon bias, so what the arc effects multiply, f times
            // the lever, agrees to well within 0.1 %.
            let (fa, axa) = rotation_of(&ea);
            assert_eq!(ea.cmd.arc_radius, r);
            assert!((fa / exact - 1.0).abs() < 2e-5, "{fa} vs {exact}");
            assert!((axa - axis).norm() < 1e-9);
            let (lever, lever_a) = ((e.pos - e.cmd.arc_center).norm(), (ea.pos - c0).norm());
            assert!(
                (f * lever / (fa * lever_a) - 1.0).abs() < 1e-4,
                "{f}·{lever} vs {fa}·{lever_a}"
            );
        }
    }

    #[test]
    fn lines_and_stops_streamed_as_points_have_no_rotation() {
        let (tau, taup, t) = (0.012, 0.002, 0.001);
        let mut est = Estimator::new(model(tau, taup, t));
        let (p0, u) = (Vec3::new(10.0, 20.0, 30.0), Vec3::new(0.6, 0.0, -0.8));
        // Speeding up along a line, cruising, then a stop.
        let s = |tt: f64| {
            if tt < 0.2 {
                0.5 * 200.0 * tt * tt
            } else if tt < 1.0 {
                4.0 + 40.0 * (tt - 0.2)
            } else {
                36.0
            }
        };
        for k in 0..1500 {
            let tt = k as f64 * t;
            let e = est.step(&cmd(tt, p0 + u * s(tt), Vec3::zeros(), 0.0));
            assert_eq!(e.cmd.arc_radius, 0.0, "t = {tt}");
            assert_eq!(rotation_of(&e), (0.0, Vec3::zeros()));
        }
        // A near-stop on a circle (R = 25 mm at 0.2 mm/s) is not an arc either.
        let mut est = Estimator::new(model(tau, taup, t));
        let w = 0.2 / 25.0;
        for k in 0..2000 {
            let th = w * k as f64 * t;
            let p = Vec3::new(25.0 * th.cos(), 25.0 * th.sin(), 0.0);
            let e = est.step(&cmd(k as f64 * t, p, Vec3::zeros(), 0.0));
            assert_eq!(rotation_of(&e).0, 0.0);
        }
    }
}
