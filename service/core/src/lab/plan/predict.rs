//! The prediction: each parameter's σ and the worst correlations from the design alone (the
//! ideal points of every scan, the lab's own rows g·r, see the module above).

use super::*;

/// How the prediction sees the measurement.
#[derive(Debug, Clone, PartialEq)]
pub struct Assumptions {
    /// Noise of a point along its normal, µm (the calibration's noise floor).
    pub noise_um: f64,
    /// Lag-1 correlation of the residuals.
    pub rho: f64,
    /// Every `stride`-th point of a scan (the lab's `--stride`).
    pub stride: usize,
    /// Every other scan of each feature held out (the lab without `--validate`).
    pub heldout_alternate: bool,
    /// Room temperature at the start, °C, and its rise over the program, K.
    pub temp_c: f64,
    /// Rise over the program, K (a program record's `temperature.span_k` takes its place).
    pub temp_rise_k: f64,
}

impl Default for Assumptions {
    fn default() -> Self {
        Assumptions {
            noise_um: 0.1,
            rho: 0.0,
            stride: 4,
            heldout_alternate: true,
            temp_c: 20.5,
            temp_rise_k: 1.0,
        }
    }
}

impl Assumptions {
    /// The noise floor the calibration's lab figures state (`metrics.noise_floor_um`), else
    /// `fallback`.
    pub fn noise_from(cal: &Calibration, fallback: f64) -> f64 {
        cal.metrics
            .get("noise_floor_um")
            .copied()
            .filter(|v| v.is_finite() && *v > 0.0)
            .unwrap_or(fallback)
    }
}

/// The lab's dataset of the ideal points `program` yields (no measurement: the points lie on
/// the nominal surfaces; their contexts are the commanded motion).
pub fn ideal_dataset(
    cal: &Calibration,
    program: &Program,
    a: &Assumptions,
) -> Result<Dataset, LabError> {
    program
        .validate()
        .map_err(|e| LabError::Data(format!("program: {e}")))?;
    let model = cal.build().map_err(LabError::Calibration)?;
    let mut sensors = model.sensors.clone();
    for s in ["stylus", "scale_x", "scale_y", "scale_z", "air"] {
        sensors.slot(s).map_err(LabError::Data)?;
    }
    let period = cal.sample_period_s;
    if !(period.is_finite() && period > 0.0) {
        return Err(LabError::Data(
            "sample_period_s: the calibration needs a positive sample period".into(),
        ));
    }
    let dt = period * a.stride.max(1) as f64;
    let tip = |id: u32, i: usize| {
        cal.geometry
            .tips
            .iter()
            .find(|t| t.id == id)
            .ok_or_else(|| {
                LabError::Data(format!(
                    "program: scans[{i}].tip: tip {id} is not in the calibration's geometry.tips"
                ))
            })
    };
    let total: f64 = program
        .scans
        .iter()
        .enumerate()
        .map(|(i, s)| tip(s.tip, i).map(|t| scan_duration(program, s, t.radius_mm)))
        .sum::<Result<f64, _>>()?;
    let features: Vec<(usize, FeatureSpec)> = program
        .features
        .iter()
        .enumerate()
        .map(|(i, f)| (0usize, f.spec(i as u32 + 1)))
        .collect();
    // The program's own span when it asks for one, else the room's assumed rise.
    let rise = program
        .temperature
        .as_ref()
        .map(|t| t.span_k)
        .unwrap_or(a.temp_rise_k);
    let mut points = vec![];
    let mut scan_no = vec![0usize; program.features.len()];
    let mut t_run = 0.0;
    for (i, s) in program.scans.iter().enumerate() {
        let g = tip(s.tip, i)?;
        let f = &program.features[s.feature];
        let pose = TipPose::new(g, s.a1_deg, s.a2_deg);
        let off = pose.shank + pose.bent;
        let rt = g.radius_mm;
        let held = a.heldout_alternate && scan_no[s.feature] % 2 == 1;
        scan_no[s.feature] += 1;
        let d = scan_duration(program, s, rt);
        let c = Vec3::from(f.center_mm);
        let mut t = 0.0;
        while t <= d {
            // carriage, velocity, acceleration, normal out of the material, deflection,
            // surface point, arc (centre, radius, frequency, axis).
            let (car, vel, acc, n, defl, surf, arc) = match s.kind {
                ScanKind::Circle => {
                    let r = circle_path_radius(f, rt, s.deflection_mm);
                    let v = s.speed_mm_s;
                    let ramp = circle_ramp_s(v);
                    let l = TAU * r + v * ramp;
                    let (sp, sd, sdd) = profile(t, v, ramp, l);
                    let dir = s.direction as f64;
                    let th = if s.direction > 0 { 0.0 } else { PI } + dir * sp / r;
                    let u = Vec3::new(th.cos(), th.sin(), 0.0);
                    let tang = Vec3::new(-th.sin(), th.cos(), 0.0) * dir;
                    let cc = c - off;
                    let n = if f.artifact == Artifact::Ring { -u } else { u };
                    (
                        cc + u * r,
                        tang * sd,
                        -u * (sd * sd / r) + tang * sdd,
                        n,
                        s.deflection_mm,
                        // On the artifact as the lab's fit holds it: the certified
                        // diameter (the nominal one put every point 0.6 µm off a 50.0012 mm
                        // ring, and `predict_by_fit`'s σ came from that offset, not noise).
                        c + u * (f.certified_diameter_mm.unwrap_or(f.nominal_diameter_mm) / 2.0),
                        Some((cc, r, sd / (TAU * r), Vec3::z() * dir)),
                    )
                }
                ScanKind::FaceLine => {
                    let n = f.normal_unit();
                    let al = along_of(&n);
                    let l = (s.to_mm - s.from_mm).abs();
                    let v = s.speed_mm_s.min(l / LINE_RAMP_S);
                    let (sp, sd, sdd) = profile(t, v, LINE_RAMP_S, l);
                    let sign = (s.to_mm - s.from_mm).signum();
                    let pos = s.from_mm + sign * sp;
                    let base = c + n * (rt - s.deflection_mm) - off;
                    (
                        base + al * pos,
                        al * (sign * sd),
                        al * (sign * sdd),
                        n,
                        s.deflection_mm,
                        c + al * pos,
                        None,
                    )
                }
                ScanKind::FaceWeave => {
                    let n = f.normal_unit();
                    let al = along_of(&n);
                    let amp = s.amplitude_mm;
                    let v = s.peak_speed();
                    let l = TAU * amp * s.cycles;
                    let (sp, sd, sdd) = profile(t, v, WEAVE_RAMP_S, l);
                    let ph = sp / amp;
                    let (w, wd) = (sd / amp, sdd / amp);
                    let base = c + n * (rt - s.deflection_mm) - off + al * s.at_mm;
                    (
                        base + n * (amp * ph.sin()),
                        n * (amp * ph.cos() * w),
                        n * (-amp * ph.sin() * w * w + amp * ph.cos() * wd),
                        n,
                        s.deflection_mm - amp * ph.sin(),
                        c + al * s.at_mm,
                        None,
                    )
                }
            };
            let mut ctx = PointContext::at_rest(car);
            let tt = t_run + t;
            ctx.t_ns = (tt * 1e9).round() as i64;
            ctx.est_vel = vel;
            ctx.est_acc = acc;
            if let Some((ac, ar, fz, ax)) = arc {
                if fz > 0.0 {
                    ctx.arc_center = ac;
                    ctx.arc_radius = ar;
                    ctx.f_hz = fz;
                    ctx.rot_axis = ax;
                } else {
                    ctx.arc_center = ac;
                    ctx.arc_radius = ar;
                }
            }
            let dvec = n * defl;
            ctx.deflection = dvec;
            ctx.deflection_probe = pose.machine_from_probe.transpose() * dvec;
            ctx.machine_from_probe = pose.machine_from_probe;
            ctx.tip_shank = pose.shank;
            ctx.tip_bent = pose.bent;
            ctx.tip_radius = rt;
            ctx.tip_id = s.tip;
            ctx.head_a1_deg = s.a1_deg;
            ctx.head_a2_deg = s.a2_deg;
            ctx.segment_id = i as u32 + 1;
            let temp = a.temp_c + rise * tt / total.max(1e-9);
            ctx.temps = [temp; MAX_SENSORS];
            ctx.temps_valid = (1u16 << MAX_SENSORS) - 1;
            points.push(LabPoint {
                ctx,
                surface: surf,
                normal: n,
                feature: s.feature,
                segment: i as u32 + 1,
                bag: 0,
                speed: s.peak_speed(),
                direction: if s.kind == ScanKind::Circle {
                    s.direction
                } else {
                    0
                },
                phase: Phase::Steady,
                held_out: held,
            });
            t += dt;
        }
        t_run += d;
    }
    Ok(Dataset {
        points,
        features,
        sensors,
        noise_floor_um: a.noise_um,
        tracking: vec![],
        calibration: cal.clone(),
        warnings: vec![],
    })
}

/// A parameter's predicted uncertainty.
#[derive(Debug, Clone, Serialize)]
pub struct ParamSigma {
    /// Effect id (with the candidate's variant for a candidate).
    pub effect: String,
    /// Parameter name with unit.
    pub name: String,
    /// Its current value (0 for a candidate).
    pub value: f64,
    /// Predicted standard uncertainty; None when the design cannot determine it.
    pub sigma: Option<f64>,
    /// The design's σ from the normal matrix alone, s·√([(JᵀJ)⁺]_kk·(1+ρ)/(1−ρ)) (no
    /// penalty, no fold spread); `sigma` is the lab's own σ when [`predict_by_fit`] made it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sigma_design: Option<f64>,
    /// Its variance inflation in the design, [(JᵀJ)⁺]_kk·[JᵀJ]_kk: how much of its column the
    /// other parameters' follow (above [`JOINT_VIF`] it is confounded with them, and its σ
    /// depends on the lab's penalties and on what the data hold beyond noise).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub vif: Option<f64>,
}

/// The variance inflation above which a parameter is confounded: 99.9 % of its column
/// follows the other parameters', so the design gives it no σ of its own — the lab's ridge
/// and what the data hold beyond noise (model error) set it. Measured on the lab's fit of a
/// planned bag (tests/tests/lab_plan.rs): below it the lab's σ fell within 0.68–1.43× of the
/// prediction, above it 0.4–120×.
pub const JOINT_VIF: f64 = 1e3;

impl ParamSigma {
    /// Determined by the design (a σ, and not confounded with other parameters).
    pub fn determined_alone(&self) -> bool {
        self.sigma.is_some() && self.vif.is_some_and(|v| v <= JOINT_VIF)
    }
}

/// A correlation between two parameters' estimates.
#[derive(Debug, Clone, Serialize)]
pub struct Correlation {
    /// First parameter (`effect: name`).
    pub a: String,
    /// Second.
    pub b: String,
    /// Correlation coefficient.
    pub r: f64,
}

/// What a design will determine.
#[derive(Debug, Clone, Serialize)]
pub struct Prediction {
    /// Every parameter of every effect (model first, then candidates).
    pub params: Vec<ParamSigma>,
    /// The strongest correlations between determined parameters (|r| ≥ 0.9, at most 12).
    pub correlations: Vec<Correlation>,
    /// Parameters the design cannot determine (`effect: name`).
    pub undetermined: Vec<String>,
    /// Parameters confounded with others (variance inflation above [`JOINT_VIF`]): their σ
    /// is the lab's penalty's, not a prediction (`effect: name`).
    pub confounded: Vec<String>,
    /// Parameters no campaign with the artifacts owned can determine beside this model
    /// (`effect: name`; see `plan`'s `beyond_reach`): undetermined here for want of data the
    /// artifacts cannot give, not of places. Empty when not examined.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub beyond_reach: Vec<String>,
    /// Points the lab would fit.
    pub points: usize,
    /// The noise and correlation assumed: µm, ρ.
    pub noise_um: f64,
    /// ρ.
    pub rho: f64,
    /// How `sigma` was made: `design` (the normal matrix alone) or `lab fit` (the lab's own
    /// fit on simulated measurements of the design, see [`predict_by_fit`]).
    pub method: String,
    /// Simulated measurements the lab fitted (0 for `design`).
    pub replicates: usize,
}

impl Prediction {
    /// The predicted σ of `effect: name` (None: undetermined or absent).
    pub fn sigma_of(&self, effect: &str, name: &str) -> Option<f64> {
        self.params
            .iter()
            .find(|p| p.effect == effect && p.name == name)
            .and_then(|p| p.sigma)
    }
}

/// The configs a prediction covers: the model's effects, then each candidate (by library
/// name, e.g. `servo_gain:powers=1+2`, `rigid_body`) not already in the model as that kind.
pub fn configs_for(
    ds: &Dataset,
    candidates: &[String],
) -> Result<Vec<(String, EffectConfig)>, LabError> {
    let mut v: Vec<(String, EffectConfig)> = ds
        .calibration
        .effects
        .iter()
        .map(|c| (c.id(), c.clone()))
        .collect();
    for name in candidates {
        let cfg = candidates::candidate(name, ds)?;
        if v.iter().any(|(_, c)| c.kind() == cfg.kind()) {
            continue;
        }
        v.push((name.clone(), cfg));
    }
    Ok(v)
}

/// Predicts each parameter's σ from the design alone (see the module's equation): the
/// calibration's effects and the `candidates` on the ideal points of `program`.
pub fn predict(
    cal: &Calibration,
    program: &Program,
    candidates: &[String],
    a: &Assumptions,
) -> Result<Prediction, LabError> {
    if !(a.noise_um.is_finite() && a.noise_um > 0.0) {
        return Err(LabError::Data(format!(
            "noise: {} µm is not a positive noise floor",
            a.noise_um
        )));
    }
    if !(a.rho.is_finite() && (0.0..0.99).contains(&a.rho)) {
        return Err(LabError::Data(format!(
            "rho: {} is not a lag-1 correlation in [0, 0.99)",
            a.rho
        )));
    }
    let ds = ideal_dataset(cal, program, a)?;
    let configs = configs_for(&ds, candidates)?;
    predict_on(&ds, &configs, a)
}

/// [`predict`] on a dataset already made, for `configs` (name, config).
pub fn predict_on(
    ds: &Dataset,
    configs: &[(String, EffectConfig)],
    a: &Assumptions,
) -> Result<Prediction, LabError> {
    let surfaces: Vec<Vec3> = ds.points.iter().map(|p| p.surface).collect();
    let all = vec![true; ds.points.len()];
    let art = fit_artifacts(ds, &surfaces, &all);
    let mut sensors: SensorTable = ds.sensors.clone();
    let mut models = vec![];
    let mut offs = vec![];
    let mut k = 0;
    for (name, c) in configs {
        let b = c
            .build(&mut sensors)
            .map_err(|e| LabError::Data(format!("{name}: {e}")))?;
        offs.push(k);
        k += b.model.n_params();
        models.push(b.model);
    }
    let fit_pt: Vec<bool> = ds
        .points
        .iter()
        .map(|p| !p.held_out && art.features[p.feature].is_some())
        .collect();
    let n_fit = fit_pt.iter().filter(|b| **b).count();
    if n_fit < 50 {
        return Err(LabError::Data(
            "the program gives fewer than 50 points to fit: add scans".into(),
        ));
    }
    let nmax = models.iter().map(|m| m.n_params()).max().unwrap_or(0);
    let mut r = vec![Vec3::zeros(); nmax];
    let mut row = vec![0.0; k];
    let rows = |i: usize, r: &mut Vec<Vec3>, row: &mut Vec<f64>| {
        let p = &ds.points[i];
        let g = art.grad[i];
        for (m, &o) in models.iter().zip(&offs) {
            let n = m.n_params();
            m.regressors(&p.ctx, &mut r[..n]);
            for j in 0..n {
                let x = g.dot(&r[j]);
                row[o + j] = if x.is_finite() { x } else { 0.0 };
            }
        }
    };
    // Pass 1: column strength (the lab does not fit a column far weaker than its effect's
    // strongest).
    let mut ss = vec![0.0; k];
    for i in (0..ds.points.len()).filter(|i| fit_pt[*i]) {
        rows(i, &mut r, &mut row);
        for j in 0..k {
            ss[j] += row[j] * row[j];
        }
    }
    let mut keep = vec![true; k];
    // (the strongest of its own unit: a translation's column beside a rotation's times its
    // lever is not weak, as in the lab's `select`).
    for ((m, &o), (_, c)) in models.iter().zip(&offs).zip(configs) {
        let n = m.n_params();
        let rms: Vec<f64> = (o..o + n).map(|j| ss[j].sqrt()).collect();
        let tops = crate::lab::select::unit_tops(&c.param_names(), &rms);
        for (j, (r, top)) in rms.iter().zip(&tops).enumerate() {
            keep[o + j] = *top > 0.0 && *r > 1e-3 * top;
        }
    }
    let kept: Vec<usize> = (0..k).filter(|j| keep[*j]).collect();
    let mut ne = Normal::new(kept.len() + art.n_cols);
    let mut dense = vec![0.0; kept.len()];
    let mut nu = vec![];
    for i in (0..ds.points.len()).filter(|i| fit_pt[*i]) {
        rows(i, &mut r, &mut row);
        for (d, &j) in dense.iter_mut().zip(&kept) {
            *d = row[j];
        }
        nuisance_row(&art, &ds.points[i], &ds.points[i].surface, &mut nu);
        ne.add(&dense, &nu, 0.0);
    }
    let sol = ne.solve();
    let infl = (1.0 + a.rho) / (1.0 - a.rho);
    let noise = a.noise_um * 1e-3;
    let mut params = vec![];
    let mut undetermined = vec![];
    let mut label = vec![];
    for ((name, c), &o) in configs.iter().zip(&offs) {
        let effect = if c.kind() == name || c.id() == *name {
            c.id()
        } else {
            name.clone()
        };
        for (j, (pn, v)) in c.param_names().into_iter().zip(c.params()).enumerate() {
            let col = kept.iter().position(|x| *x == o + j);
            let sigma = col.and_then(|cc| {
                (!sol.unidentifiable.contains(&cc))
                    .then(|| noise * (sol.cov[(cc, cc)] * infl).max(0.0).sqrt())
                    .filter(|s| s.is_finite())
            });
            if sigma.is_none() {
                undetermined.push(format!("{effect}: {pn}"));
            }
            if let Some(cc) = col {
                label.push((cc, format!("{effect}: {pn}"), sigma.is_some()));
            }
            let vif = col
                .filter(|_| sigma.is_some())
                .map(|cc| sol.cov[(cc, cc)] * ne.m[(cc, cc)])
                .filter(|v| v.is_finite());
            params.push(ParamSigma {
                effect: effect.clone(),
                name: pn,
                value: v,
                sigma,
                sigma_design: sigma,
                vif,
            });
        }
    }
    let mut correlations = vec![];
    for (x, (ci, li, oki)) in label.iter().enumerate() {
        for (cj, lj, okj) in label.iter().skip(x + 1) {
            if !(oki & okj) {
                continue;
            }
            let d = (sol.cov[(*ci, *ci)] * sol.cov[(*cj, *cj)]).sqrt();
            if d > 0.0 {
                let rr = sol.cov[(*ci, *cj)] / d;
                if rr.is_finite() && rr.abs() >= 0.9 {
                    correlations.push(Correlation {
                        a: li.clone(),
                        b: lj.clone(),
                        r: rr,
                    });
                }
            }
        }
    }
    correlations.sort_by(|p, q| {
        q.r.abs()
            .total_cmp(&p.r.abs())
            .then_with(|| p.a.cmp(&q.a))
            .then_with(|| p.b.cmp(&q.b))
    });
    correlations.truncate(12);
    let confounded = params
        .iter()
        .filter(|p| p.sigma.is_some() && !p.determined_alone())
        .map(|p| format!("{}: {}", p.effect, p.name))
        .collect();
    Ok(Prediction {
        params,
        correlations,
        undetermined,
        confounded,
        beyond_reach: vec![],
        points: n_fit,
        noise_um: a.noise_um,
        rho: a.rho,
        method: "design".into(),
        replicates: 0,
    })
}

/// Simulated measurements of a design the lab fits in [`predict_by_fit`].
pub const FIT_REPLICATES: usize = 3;

/// A deterministic normal deviate stream (SplitMix64 and Box–Muller): the same design gives
/// the same prediction.
struct Gauss(u64);

impl Gauss {
    fn uniform(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        ((z >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    fn next(&mut self) -> f64 {
        let (u, v) = (self.uniform(), self.uniform());
        (-2.0 * u.ln()).sqrt() * (TAU * v).cos()
    }
}

/// The ideal dataset with noise along each point's normal: s·e, e a lag-1 autoregressive
/// sequence of correlation ρ along each scan (unit variance), from `seed`.
pub fn noisy(ds: &Dataset, a: &Assumptions, seed: u64) -> Dataset {
    let mut out = ds.clone();
    let mut g = Gauss(seed.wrapping_mul(0x2545_F491_4F6C_DD1D) ^ 0x5CA7_C0);
    let s = a.noise_um * 1e-3;
    let rho = a.rho.clamp(0.0, 0.99);
    let innov = (1.0 - rho * rho).sqrt();
    let mut e = 0.0;
    let mut last = u32::MAX;
    for p in &mut out.points {
        e = if p.segment == last {
            rho * e + innov * g.next()
        } else {
            g.next()
        };
        last = p.segment;
        p.surface += p.normal * (s * e);
    }
    out.noise_floor_um = a.noise_um;
    out
}

/// Predicts each parameter's σ as the lab will report it: the lab's own fit
/// (`analysis::fit_effects`: the same artifact fit, folds, cross-validated smoothness and
/// ridge, and the σ it composes — statistical part, fold spread, penalty shift) on
/// `replicates` simulated measurements of the design (its ideal points with noise of the
/// assumed floor and lag-1 correlation along the scans), the median σ of each parameter. A
/// parameter the lab leaves undetermined in most replicates is undetermined. Correlations and
/// the design's own σ are those of [`predict`].
///
/// The simulated measurements carry noise and no model error, around the calibration's
/// current values: what a penalty does to a large unmodelled signal is not in it. Their points
/// lie on the artifacts' certified diameters, where the lab's fit holds them (on the nominal
/// ones the lab's σ was scaled by a 0.6 µm offset: 14–30× the design's).
///
/// With no model error the lab's σ comes out about 0.55× the design's (a campaign's plan, white
/// noise): the final fit uses both folds where the design counts the fit half's points (1/√2);
/// the rest is not traced. On a measured bag the residual carries
/// what the model leaves, and the lab's σ its scan-clustered part: `lab plan --bag` predicts at
/// that residual.
pub fn predict_by_fit(
    cal: &Calibration,
    program: &Program,
    candidates: &[String],
    a: &Assumptions,
    replicates: usize,
) -> Result<Prediction, LabError> {
    let mut pred = predict(cal, program, candidates, a)?;
    let ds = ideal_dataset(cal, program, a)?;
    let configs = configs_for(&ds, candidates)?;
    let cfgs: Vec<EffectConfig> = configs.iter().map(|(_, c)| c.clone()).collect();
    let n = replicates.max(1);
    let mut sig: Vec<Vec<Option<f64>>> = vec![vec![]; pred.params.len()];
    for r in 0..n {
        let dr = noisy(&ds, a, r as u64 + 1);
        let prep = super::super::types::prepare(&dr)?;
        let o = super::super::select::fit_effects(&dr, &prep, &cfgs)?;
        let flat: Vec<Option<f64>> = o.params.iter().flatten().map(|p| p.sigma).collect();
        if flat.len() != pred.params.len() {
            return Err(LabError::Data(format!(
                "the lab's fit gave {} parameters where the design has {}",
                flat.len(),
                pred.params.len()
            )));
        }
        for (v, s) in sig.iter_mut().zip(flat) {
            v.push(s.filter(|x| x.is_finite()));
        }
    }
    pred.undetermined.clear();
    for (p, v) in pred.params.iter_mut().zip(sig) {
        let mut ok: Vec<f64> = v.into_iter().flatten().collect();
        p.sigma = if 2 * ok.len() > n {
            ok.sort_by(f64::total_cmp);
            Some(ok[ok.len() / 2])
        } else {
            None
        };
        if p.sigma.is_none() {
            pred.undetermined.push(format!("{}: {}", p.effect, p.name));
        }
    }
    pred.confounded = pred
        .params
        .iter()
        .filter(|p| p.sigma.is_some() && !p.determined_alone())
        .map(|p| format!("{}: {}", p.effect, p.name))
        .collect();
    pred.method = "lab fit".into();
    pred.replicates = n;
    Ok(pred)
}
