//! What a calibration costs per point, measured before it runs.
//!
//! A calibration can be valid in every field and still too costly to run in real time (240
//! `custom` terms of 4 kB each took 3.1 ms of CPU per point: a machine at 1 kHz would need
//! three cores). The core evaluates a built model on a point it is given
//! (`corrector::synthesize`, the effects and the synthesis every corrected point goes
//! through); here it is given a reference point — mid-travel, on an arc, deflected, every
//! temperature read — and timed. A put whose cost is over `max_point_cost_us` is refused; a
//! stored one is served and said (see `server`). What a machine's points cost as it runs is
//! measured on its shard as well (`cost_us_per_point` on its status).

use scancorr_core::calib::Model;
use scancorr_core::corrector::synthesize;
use scancorr_core::sample::{PointContext, Vec3, MAX_SENSORS};
use scancorr_core::Calibration;
use std::time::{Duration, Instant};

/// How long a measurement may take, at most (a costly model is measured on fewer repeats).
#[derive(Clone, Copy, Debug)]
pub struct Budget {
    /// Timed rounds; the cheapest round's mean is the cost (the least disturbed by other work
    /// on the host).
    rounds: u32,
    /// Each round repeats the evaluation for at least this long (one evaluation at least).
    round: Duration,
}

/// At a put: about 3 ms for a cheap model, three evaluations for a costly one.
pub const AT_PUT: Budget = Budget {
    rounds: 3,
    round: Duration::from_millis(1),
};

/// For each stored calibration at start-up (thousands of machines).
pub const AT_START: Budget = Budget {
    rounds: 2,
    round: Duration::from_micros(100),
};

/// The reference point: the middle of the travel, moving at 20 mm/s on an arc of 10 mm about
/// z, deflected 0.3 mm, with the model's first tip, every temperature read at 20.5 °C.
pub fn reference_point(model: &Model) -> PointContext {
    let v = &model.volume_mm;
    let mid = |k: usize| {
        let (a, b) = (v[k][0], v[k][1]);
        if a.is_finite() && b.is_finite() {
            0.5 * (a + b)
        } else {
            0.0
        }
    };
    let pos = Vec3::new(mid(0), mid(1), mid(2));
    let mut c = PointContext::at_rest(pos);
    let (r, speed) = (10.0, 20.0);
    c.t_ns = 1_000_000_000;
    c.est_vel = Vec3::new(0.0, speed, 0.0);
    c.est_acc = Vec3::new(-speed * speed / r, 0.0, 0.0);
    c.arc_center = pos - Vec3::new(r, 0.0, 0.0);
    c.arc_radius = r;
    c.f_hz = speed / (2.0 * std::f64::consts::PI * r);
    c.rot_axis = Vec3::new(0.0, 0.0, 1.0);
    c.deflection_probe = Vec3::new(0.3, 0.0, 0.0);
    c.deflection = c.deflection_probe;
    if let Some(t) = model.tips.values().next() {
        c.tip_id = t.id;
        c.tip_radius = t.radius_mm;
        c.tip_shank = Vec3::new(0.0, 0.0, -t.l1_mm);
    }
    c.temps = [20.5; MAX_SENSORS];
    c.temps_valid = (1u16 << MAX_SENSORS) - 1;
    c
}

/// CPU time one point costs with `model` (its effects and the synthesis), µs.
pub fn point_cost_us(model: &Model, budget: Budget) -> f64 {
    let ctx = reference_point(model);
    let min_contact = model.settings.min_contact_deflection_mm;
    let eval = || std::hint::black_box(synthesize(&ctx, &model.effects, false, min_contact));
    // Warm-up (caches, lazily built tables).
    eval();
    let mut best = f64::INFINITY;
    for _ in 0..budget.rounds {
        let t0 = Instant::now();
        let mut n = 0u32;
        loop {
            eval();
            n += 1;
            if t0.elapsed() >= budget.round || n >= 100_000 {
                break;
            }
        }
        best = best.min(t0.elapsed().as_secs_f64() / n as f64);
    }
    best * 1e6
}

/// Why a put is refused: the cost, the limit, and what the machine would need.
pub fn refusal(cal: &Calibration, cost_us: f64, limit_us: f64) -> String {
    let rate = 1.0 / cal.sample_period_s;
    let cores = if rate.is_finite() && rate > 0.0 {
        format!(
            "; at the calibration's {:.0} Hz it would need {:.2} core(s) for this machine alone",
            rate,
            cost_us * 1e-6 * rate
        )
    } else {
        String::new()
    };
    format!(
        "the calibration costs {cost_us:.0} µs of CPU per point (measured on a reference point), \
         more than the {limit_us:.0} µs this service accepts (`max_point_cost_us`){cores}: it \
         could not be corrected in real time. Simplify its effects (fewer or shorter `custom` \
         terms), or raise `max_point_cost_us` on a service with the cores for it"
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_costly_model_costs_more_than_the_example() {
        let cheap = Calibration::example("m1");
        let m = cheap.build().unwrap();
        let c0 = point_cost_us(&m, AT_PUT);
        assert!(c0 > 0.0 && c0 < 200.0, "{c0} µs");
        // 40 custom terms of many sines each.
        let mut doc: serde_json::Value = serde_json::from_str(&cheap.to_json()).unwrap();
        let term: String = (0..60)
            .map(|i| format!("sin(x*{}.0001+y)", i + 1))
            .collect::<Vec<_>>()
            .join("+");
        let terms: Vec<_> = (0..40)
            .map(|k| serde_json::json!({"axis": "x", "expr": format!("{term}+{k}")}))
            .collect();
        doc["effects"]
            .as_array_mut()
            .unwrap()
            .push(serde_json::json!({"kind": "custom", "id": "heavy", "terms": terms, "coefficients": vec![1e-9; 40]}));
        let costly = Calibration::from_json(&doc.to_string()).unwrap();
        let c1 = point_cost_us(&costly.build().unwrap(), AT_PUT);
        assert!(c1 > 10.0 * c0, "{c1} µs against {c0} µs");
        let why = refusal(&costly, c1, 1.0);
        assert!(why.contains("max_point_cost_us"), "{why}");
    }
}
