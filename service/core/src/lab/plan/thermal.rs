//! The temperature span of a plan: what a rise of the room's temperature over the campaign
//! buys for the thermal effects' σ, and the span the plan asks the user to reach.
//!
//! A thermal parameter enters a correction as its coefficient times a temperature difference
//! times a lever: `scale_thermal` δ_i = α_i·(T_i − 20 °C)·(s_i − o_i) (lever: the axis' travel),
//! `stylus_thermal` δ = α·(T − 20 °C)·l (lever: the longest stylus), `thermal_drift`
//! δ = k·(L_τ[T] − T_ref) (mm/K, lever 1). At one temperature a coefficient is seen only
//! through the level T − 20 °C, where the artifacts' placement takes most of it; a span makes
//! its column vary along the campaign, so σ falls about as 1/span (the design's σ,
//! [`predict`], with the program's temperature rising linearly by the span, as
//! `sim --program` makes it: `Program::temperature`).
//!
//! The span to reach: the smallest of [`LADDER_K`] (up to what the user can produce) at which
//! every thermal parameter's correction uncertainty at the temperatures of use (±`use_k` about
//! 20 °C), σ·lever·use_k, is at most a third of the noise floor (it then adds under 6 % to the
//! noise in quadrature); when none reaches it, the largest span, and what is left is said. A
//! parameter the scans leave undetermined at the largest span (α_z with horizontal rings) needs
//! other scans, not a span: it is named and left out of the target.
//! The ladder is computed at a coarser stride (every [`LADDER_STRIDE`]-th point, σ scaled by
//! √(stride ratio): the points' noise is independent in the design) and the plan's own
//! prediction is then made at the span chosen.
//!
//! Source idea: ISO 1 (lengths at 20 °C), and the design of a thermal test as in ISO 230-3
//! (the temperatures varied over the range the coefficients are to hold for).

use super::*;

/// Spans the plan weighs, K (0: the room held constant).
pub const LADDER_K: [f64; 9] = [0.0, 0.5, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0];
/// Every `LADDER_STRIDE`-th point for the ladder (at least the lab's stride).
pub const LADDER_STRIDE: usize = 16;

/// One thermal parameter at one span.
#[derive(Debug, Clone, Serialize)]
pub struct ThermalSigma {
    /// Effect id.
    pub effect: String,
    /// Parameter name with unit.
    pub name: String,
    /// Predicted σ (None: undetermined at this span).
    pub sigma: Option<f64>,
    /// Its correction uncertainty at ±use_k about 20 °C over its lever, µm.
    pub error_um: Option<f64>,
}

/// The prediction at one span.
#[derive(Debug, Clone, Serialize)]
pub struct SpanStep {
    /// Rise over the program, K.
    pub span_k: f64,
    /// Each thermal parameter.
    pub params: Vec<ThermalSigma>,
}

/// What the plan says of the temperature.
#[derive(Debug, Clone, Serialize)]
pub struct ThermalPlan {
    /// The span to reach, K.
    pub span_k: f64,
    /// Whether it meets the target (else it is the largest the user can produce).
    pub meets_target: bool,
    /// The corrections are to hold within ±use_k of 20 °C, K.
    pub use_k: f64,
    /// Target of each parameter's correction uncertainty, µm (a third of the noise floor).
    pub target_um: f64,
    /// The prediction at each span weighed.
    pub ladder: Vec<SpanStep>,
    /// Why, in words.
    pub why: String,
}

/// The lever of a thermal parameter (mm; 1 for a coefficient already in mm/K), None when
/// the parameter is not thermal.
fn lever(kind: &str, name: &str, travel: &[[f64; 3]; 2], stylus_mm: f64) -> Option<f64> {
    if name.contains("(mm/K)") {
        return Some(1.0);
    }
    if !name.contains("(1/K)") {
        return None;
    }
    match kind {
        "scale_thermal" => {
            let i = ["alpha_x", "alpha_y", "alpha_z"]
                .iter()
                .position(|a| name.starts_with(a))?;
            Some((travel[1][i] - travel[0][i]).abs())
        }
        _ => Some(stylus_mm),
    }
}

/// The thermal parameters of `program` at each span of the ladder up to `max_span_k`, and the
/// span to reach (see the module). None when the model and the candidates have no thermal
/// parameter.
pub fn thermal_plan(
    cal: &Calibration,
    program: &Program,
    candidates: &[String],
    a: &Assumptions,
    travel_mm: [[f64; 2]; 3],
    max_span_k: f64,
    use_k: f64,
) -> Result<Option<ThermalPlan>, LabError> {
    if !(max_span_k.is_finite() && (0.0..=MAX_SPAN_K).contains(&max_span_k)) {
        return Err(LabError::Data(format!(
            "temperature span: {max_span_k} K is not a span within 0…{MAX_SPAN_K} K"
        )));
    }
    if !(use_k.is_finite() && use_k > 0.0 && use_k <= 50.0) {
        return Err(LabError::Data(format!(
            "temperature of use: ±{use_k} K is not a range within (0, 50] K"
        )));
    }
    let travel = [
        [travel_mm[0][0], travel_mm[1][0], travel_mm[2][0]],
        [travel_mm[0][1], travel_mm[1][1], travel_mm[2][1]],
    ];
    let stylus_mm = cal
        .geometry
        .tips
        .iter()
        .map(|t| {
            let p = TipPose::new(t, 0.0, 0.0);
            (p.shank + p.bent).norm()
        })
        .fold(0.0, f64::max);
    // Which parameters are thermal, by the configs the prediction covers.
    let ds = ideal_dataset(cal, program, a)?;
    let configs = configs_for(&ds, candidates)?;
    let mut which: Vec<Option<f64>> = vec![];
    for (_, c) in &configs {
        for n in c.param_names() {
            which.push(lever(c.kind(), &n, &travel, stylus_mm));
        }
    }
    if which.iter().all(|w| w.is_none()) {
        return Ok(None);
    }
    let coarse = LADDER_STRIDE.max(a.stride);
    let ac = Assumptions {
        stride: coarse,
        ..a.clone()
    };
    let scale = (a.stride.max(1) as f64 / coarse as f64).sqrt();
    let target_um = a.noise_um / 3.0;
    let mut spans: Vec<f64> = LADDER_K
        .iter()
        .copied()
        .filter(|s| *s < max_span_k - 1e-9)
        .collect();
    spans.push(max_span_k);
    let mut ladder = vec![];
    for &s in &spans {
        let mut p = program.clone();
        p.temperature = Some(TemperatureSpan {
            span_k: s,
            why: String::new(),
        });
        let pred = predict_on(&ideal_dataset(cal, &p, &ac)?, &configs, &ac)?;
        let params = pred
            .params
            .iter()
            .zip(&which)
            .filter_map(|(q, w)| {
                let l = (*w)?;
                let sigma = q.sigma.map(|x| x * scale);
                Some(ThermalSigma {
                    effect: q.effect.clone(),
                    name: q.name.clone(),
                    sigma,
                    error_um: sigma.map(|x| x * l * use_k * 1e3),
                })
            })
            .collect();
        ladder.push(SpanStep { span_k: s, params });
    }
    // A parameter the design leaves undetermined at the largest span needs other scans, not a
    // span: it is named and left out of the target.
    let det: Vec<bool> = ladder
        .last()
        .map(|st| st.params.iter().map(|p| p.sigma.is_some()).collect())
        .unwrap_or_default();
    let lacking: Vec<String> = ladder
        .last()
        .map(|st| {
            st.params
                .iter()
                .filter(|p| p.sigma.is_none())
                .map(|p| format!("{}: {}", p.effect, p.name))
                .collect()
        })
        .unwrap_or_default();
    let meets = |st: &SpanStep| {
        st.params
            .iter()
            .zip(&det)
            .filter(|(_, d)| **d)
            .all(|(p, _)| p.error_um.is_some_and(|e| e <= target_um))
    };
    let chosen = ladder.iter().position(meets);
    let i = chosen.unwrap_or(ladder.len() - 1);
    let worst = |st: &SpanStep| {
        st.params
            .iter()
            .zip(&det)
            .filter(|(_, d)| **d)
            .map(|(p, _)| {
                (
                    p.error_um.unwrap_or(f64::INFINITY),
                    format!("{}: {}", p.effect, p.name),
                    p.sigma,
                )
            })
            .max_by(|x, y| x.0.total_cmp(&y.0).then_with(|| y.1.cmp(&x.1)))
    };
    let (span_k, step) = (ladder[i].span_k, &ladder[i]);
    let at0 = worst(&ladder[0]);
    let here = worst(step);
    let fmt = |w: &Option<(f64, String, Option<f64>)>| match w {
        Some((e, n, Some(s))) if e.is_finite() => format!("{n} σ {s:.2e}, {e:.3} µm"),
        Some((_, n, _)) => format!("{n} undetermined"),
        None => "no thermal parameter".into(),
    };
    let lack = if lacking.is_empty() {
        String::new()
    } else {
        format!(
            "; not determined by these scans at any span (they need other scans, not a span): {}",
            lacking.join(", ")
        )
    };
    let why = if chosen.is_some() {
        format!(
            "a rise of {span_k} K over the campaign determines the thermal coefficients well enough that their corrections at ±{use_k} K about 20 °C stay within a third of the {:.3} µm noise floor ({:.3} µm); worst {} (at {} K: {})",
            a.noise_um,
            target_um,
            fmt(&here),
            ladder[0].span_k,
            fmt(&at0)
        ) + &lack
    } else {
        format!(
            "the largest rise you can produce, {span_k} K, leaves the worst thermal correction at ±{use_k} K about 20 °C above a third of the {:.3} µm noise floor ({:.3} µm): {} (at {} K: {}); σ falls about as 1/span: a larger span, or a narrower range of use",
            a.noise_um,
            target_um,
            fmt(&here),
            ladder[0].span_k,
            fmt(&at0)
        ) + &lack
    };
    Ok(Some(ThermalPlan {
        span_k,
        meets_target: chosen.is_some(),
        use_k,
        target_um,
        ladder,
        why,
    }))
}

/// Puts the span to reach into a plan: the program record asks for it
/// (`Program::temperature`), the plan's prediction is made at it, and the thermal plan is
/// returned (None: no thermal parameter, the plan unchanged).
pub fn apply_thermal(
    cal: &Calibration,
    planned: &mut Planned,
    req: &PlanRequest,
    max_span_k: f64,
    use_k: f64,
) -> Result<Option<ThermalPlan>, LabError> {
    let Some(t) = thermal_plan(
        cal,
        &planned.program,
        &req.candidates,
        &req.assumptions,
        req.travel_mm,
        max_span_k,
        use_k,
    )?
    else {
        return Ok(None);
    };
    planned.program.temperature = Some(TemperatureSpan {
        span_k: t.span_k,
        why: t.why.clone(),
    });
    let beyond = std::mem::take(&mut planned.prediction.beyond_reach);
    planned.prediction = predict(cal, &planned.program, &req.candidates, &req.assumptions)?;
    planned.prediction.beyond_reach = beyond;
    Ok(Some(t))
}
