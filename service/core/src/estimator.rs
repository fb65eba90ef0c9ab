//! The motion estimator: what the machine did, predicted from what it was told to do.
//!
//! Equation: E = G_N·C per axis (G_N = G1·G2, discretised at the sample period, see
//! [`transfer`](crate::transfer)); A = Ë from the model state (the second derivative of the
//! estimate, never of the noisy scales); on arcs of commanded radius Rs the rotation frequency
//! is f = sqrt(|A_n|/Rs)/(2π), where A_n is the component of A normal to the estimated
//! velocity — equal to |A| at constant speed, and still right while the scan speeds up or
//! slows down, when A gains a tangential part.
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

/// The estimate at one command instant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Estimate {
    /// The command it was computed from.
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
        self.model = model;
        self.restart(c)
    }

    /// Advances one sample period to the command `c`.
    #[inline]
    pub fn step(&mut self, c: &CommandSample) -> Estimate {
        if !self.started {
            return self.restart(c);
        }
        let mut e = Estimate {
            cmd: *c,
            pos: Vec3::zeros(),
            vel: Vec3::zeros(),
            acc: Vec3::zeros(),
        };
        for i in 0..3 {
            let d = self.model[i].step(&mut self.state[i], c.pos[i]);
            e.pos[i] = d.y;
            e.vel[i] = d.dy;
            e.acc[i] = d.ddy;
        }
        self.steps += 1;
        e
    }

    /// True once a restart's transient has decayed.
    pub fn settled(&self) -> bool {
        let need = self
            .model
            .iter()
            .map(|m| m.settle_samples)
            .max()
            .unwrap_or(0);
        self.steps >= need
    }
}

/// Rotation on an arc: (f in Hz, unit angular-velocity axis), both zero off arcs or at rest.
#[inline]
pub fn rotation(pos: &Vec3, vel: &Vec3, acc: &Vec3, center: &Vec3, radius: f64) -> (f64, Vec3) {
    if radius <= 0.0 {
        return (0.0, Vec3::zeros());
    }
    let w = (pos - center).cross(vel);
    let wn = w.norm();
    let vn = vel.norm();
    if wn <= 1e-12 * (1.0 + radius * vn) || vn == 0.0 {
        return (0.0, Vec3::zeros());
    }
    let vhat = vel / vn;
    let a_n = (acc - vhat * acc.dot(&vhat)).norm();
    ((a_n / radius).sqrt() / (2.0 * std::f64::consts::PI), w / wn)
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
        // f recovered from A.
        let (f, axis) = rotation(&e.pos, &e.vel, &e.acc, &c0, r);
        assert!((f - w / (2.0 * PI)).abs() < 2.5e-3 * f, "{f}");
        assert!((axis - Vec3::z()).norm() < 1e-9);
        assert!(est.settled());
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
}
