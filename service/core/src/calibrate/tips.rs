//! `tips`: qualification of the styli on a master sphere.
//!
//! Equations. Each setting g (a tip at one head angle) measures the sphere at ≥ 2 latitudes;
//! an orthogonal-distance sphere fit gives its centre S_g and radius R_g. The corrector puts
//! the tip centre at scale + o_g, so S_g = C + o_g,cal − o_g,true (C the sphere's centre). The
//! reference tip (its offset defines the machine's zero) measures the sphere before and after
//! each other setting; its centre, interpolated linearly in time to the setting,
//! S_ref(t_g), carries everything common to all tips (the scales' expansion as the room warms,
//! the sphere's stand). With Δ_g = S_g − S_ref(t_g), τ_g = T_g − T_q (stylus temperature
//! against the mean temperature of the qualification T_q) and R_g the head's rotation:
//!
//! R_g·(l1·u_s + l2·u_b + l3·u_c) + α_k·τ_g·o_g,cal − α_ref·τ_g·o_ref,cal = o_g,cal − Δ_g,
//!
//! linear in the limb lengths of each non-reference stylus k (u_s, u_b, u_c the unit limbs of
//! its catalogue geometry: shank along −z, the bends at their trusted angles β1, β2), its
//! expansion coefficient α_k, and the reference stylus's α_ref (its growth along its own
//! direction moves the reference centre; the other styli's directions rotate with the head,
//! which separates the two). Three equations per setting: weighted least squares, with the
//! residual reported. Effective tip radius: r_k = r_k,cal + mean_g(R_g − R_cert) over the
//! settings of tip k (the radius the tip behaves as at the qualification's deflection).
//!
//! The lengths are those at T_q, which becomes the reference temperature of the stylus
//! thermal correction, with one coefficient per stylus (`alpha_per_tip`).
//!
//! Source idea: probe qualification on a reference sphere, the offset of each tip from the
//! reference tip's (s12 = S2 − S1) solved for the stylus lengths from the trusted head and
//! bend angles (the probe-unit thermal correction patent's qualification), with the
//! temperature at qualification as the reference of each tip's thermal correction.

use super::{weighted_lsq, Param, ProcedureError};
use crate::calib::Calibration;
use crate::effects::{stylus_thermal, EffectConfig};
use crate::lab::dataset::Dataset;
use crate::lab::program::FeatureKind;
use crate::sample::Vec3;
use crate::shape;
use serde::Serialize;
use std::collections::BTreeMap;

/// Least temperature range over the qualification for the expansion coefficients to be
/// fitted, K.
const MIN_TEMP_RANGE_K: f64 = 0.3;

/// One setting: a tip at one head angle, measuring the sphere.
#[derive(Debug, Clone, Serialize)]
pub struct Setting {
    /// Tip id.
    pub tip: u32,
    /// Head angles A1, A2, degrees.
    pub head_deg: [f64; 2],
    /// Points fitted.
    pub points: usize,
    /// Fitted centre, mm.
    pub center_mm: [f64; 3],
    /// Standard uncertainty of each centre coordinate, µm.
    pub center_sigma_um: [f64; 3],
    /// Fitted radius minus the certified radius, µm.
    pub radius_error_um: f64,
    /// Form (RMS of the fit residuals), µm.
    pub rms_um: f64,
    /// Mean time, s from the first point.
    pub t_s: f64,
    /// Mean stylus temperature, °C (absent without a stylus sensor).
    pub temp_c: Option<f64>,
    /// Offset from the reference tip's centre at the same time, µm (zero for the reference).
    pub offset_um: [f64; 3],
    /// What is left of the offset after the fit, µm.
    pub residual_um: [f64; 3],
}

/// The outcome of `tips`.
#[derive(Debug, Clone, Serialize)]
pub struct Outcome {
    /// The calibration with the qualified styli (unversioned).
    #[serde(skip)]
    pub calibration: Calibration,
    /// Fitted parameters with their σ.
    pub params: Vec<Param>,
    /// The reference tip.
    pub reference_tip: u32,
    /// Qualification temperature (mean stylus temperature), °C.
    pub reference_temp_c: Option<f64>,
    /// Temperature range over the qualification, K.
    pub temp_range_k: f64,
    /// Every setting measured.
    pub settings: Vec<Setting>,
    /// Tip-to-tip consistency with the starting calibration: RMS of the settings' offsets
    /// from the reference, µm.
    pub consistency_before_um: f64,
    /// RMS of the offsets left after the fit, µm.
    pub residual_rms_um: f64,
    /// Rotation of the offsets at the sphere's position relative to the reference's (about
    /// x, y, z, rad): the machine's angular errors there (Abbe) or the head's angle offsets.
    /// Qualified lengths exclude it; a rigid-body or guide effect corrects it.
    pub rotation: Vec<Param>,
    /// What this measurement cannot determine, and why.
    pub undetermined: Vec<String>,
    /// Remarks (a setting outside the reference's time span, …).
    pub notes: Vec<String>,
}

/// Groups of consecutive points of one (feature, tip, head angle).
struct Group {
    feature: usize,
    tip: u32,
    head: [f64; 2],
    idx: Vec<usize>,
}

fn key(ds: &Dataset, i: usize) -> (usize, u32, [i64; 2]) {
    let p = &ds.points[i];
    (
        p.feature,
        p.ctx.tip_id,
        [
            (p.ctx.head_a1_deg * 1e3).round() as i64,
            (p.ctx.head_a2_deg * 1e3).round() as i64,
        ],
    )
}

/// The sphere's settings in time order.
fn groups(ds: &Dataset, spheres: &BTreeMap<usize, f64>) -> Vec<Group> {
    let mut order: Vec<usize> = (0..ds.points.len())
        .filter(|&i| spheres.contains_key(&ds.points[i].feature))
        .collect();
    order.sort_by_key(|&i| (ds.points[i].bag, ds.points[i].ctx.t_ns));
    let mut out: Vec<Group> = vec![];
    let mut last = None;
    for i in order {
        let k = (key(ds, i), ds.points[i].bag);
        if last != Some(k) {
            let p = &ds.points[i];
            out.push(Group {
                feature: p.feature,
                tip: p.ctx.tip_id,
                head: [p.ctx.head_a1_deg, p.ctx.head_a2_deg],
                idx: vec![],
            });
            last = Some(k);
        }
        out.last_mut().expect("pushed").idx.push(i);
    }
    out
}

/// Centre covariance of an orthogonal-distance sphere fit (free radius), mm².
fn center_cov(points: &[Vec3], center: &Vec3, rms: f64) -> Option<nalgebra::Matrix3<f64>> {
    let n = points.len();
    if n < 8 {
        return None;
    }
    let mut jtj = nalgebra::Matrix4::<f64>::zeros();
    for p in points {
        let u = (p - center).try_normalize(1e-12)?;
        let j = nalgebra::Vector4::new(-u.x, -u.y, -u.z, -1.0);
        jtj += j * j.transpose();
    }
    let s2 = rms * rms * n as f64 / (n - 4) as f64;
    let inv = jtj.try_inverse()? * s2;
    Some(inv.fixed_view::<3, 3>(0, 0).into_owned())
}

/// Qualifies the styli: `ds` built from the bags with `start` (its stylus thermal correction,
/// if any, taken out: this procedure measures it); `reference` the reference tip (default: the
/// lowest tip id measured at head angle 0, 0).
pub fn run(
    ds: &Dataset,
    start: &Calibration,
    reference: Option<u32>,
) -> Result<Outcome, ProcedureError> {
    let spheres: BTreeMap<usize, f64> = ds
        .features
        .iter()
        .enumerate()
        .filter(|(_, (_, f))| f.artifact == "sphere" && f.kind == FeatureKind::Boss)
        .filter_map(|(i, (_, f))| f.certificate_diameter_mm.map(|d| (i, d / 2.0)))
        .collect();
    if spheres.is_empty() {
        return Err(ProcedureError::Missing(
            "no master-sphere scans in the bags (a `sphere` feature with its certified \
             diameter): `tips` needs the master sphere measured by the reference tip and by \
             every other tip and head angle, e.g. `scancorr sim --program tips`"
                .into(),
        ));
    }
    let gs = groups(ds, &spheres);
    let t0 = gs
        .iter()
        .flat_map(|g| g.idx.iter())
        .map(|&i| ds.points[i].ctx.t_ns)
        .min()
        .unwrap_or(0);
    let slot = ds.sensors.find("stylus");
    let mut settings = vec![];
    for g in &gs {
        let pts: Vec<Vec3> = g.idx.iter().map(|&i| ds.points[i].surface).collect();
        let zs = pts.iter().map(|p| p.z);
        let (zmin, zmax) = zs.fold((f64::MAX, f64::MIN), |a, z| (a.0.min(z), a.1.max(z)));
        let r_cert = spheres[&g.feature];
        if zmax - zmin < 0.2 * r_cert {
            return Err(ProcedureError::IllConditioned(format!(
                "tip {} at head angles ({}, {})° scanned the sphere at one height: its centre \
                 is undetermined along z; scan circles at ≥ 2 latitudes (e.g. −30°, 0°, +30°)",
                g.tip, g.head[0], g.head[1]
            )));
        }
        let fit = shape::fit_sphere(&pts).map_err(|e| {
            ProcedureError::IllConditioned(format!(
                "tip {} at head angles ({}, {})°: the sphere fit failed: {e}",
                g.tip, g.head[0], g.head[1]
            ))
        })?;
        let cov = center_cov(&pts, &fit.center, fit.rms).ok_or_else(|| {
            ProcedureError::IllConditioned(format!(
                "tip {} at head angles ({}, {})°: too few points ({}) for a sphere",
                g.tip,
                g.head[0],
                g.head[1],
                pts.len()
            ))
        })?;
        let n = g.idx.len() as f64;
        let t_s = g
            .idx
            .iter()
            .map(|&i| (ds.points[i].ctx.t_ns - t0) as f64 * 1e-9)
            .sum::<f64>()
            / n;
        let temp_c = slot.and_then(|s| {
            let v: Vec<f64> = g
                .idx
                .iter()
                .map(|&i| &ds.points[i].ctx)
                .filter(|c| c.temps_valid & (1 << s) != 0)
                .map(|c| c.temps[s])
                .collect();
            (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
        });
        settings.push(Setting {
            tip: g.tip,
            head_deg: g.head,
            points: g.idx.len(),
            center_mm: fit.center.into(),
            center_sigma_um: [0, 1, 2].map(|k| cov[(k, k)].sqrt() * 1e3),
            radius_error_um: (fit.radius - r_cert) * 1e3,
            rms_um: fit.rms * 1e3,
            t_s,
            temp_c,
            offset_um: [0.0; 3],
            residual_um: [0.0; 3],
        });
    }
    let reference = reference.unwrap_or_else(|| {
        settings
            .iter()
            .filter(|s| s.head_deg == [0.0, 0.0])
            .map(|s| s.tip)
            .chain(settings.iter().map(|s| s.tip))
            .min()
            .expect("settings are not empty")
    });
    let refs: Vec<usize> = (0..settings.len())
        .filter(|&i| settings[i].tip == reference)
        .collect();
    if refs.is_empty() {
        return Err(ProcedureError::Missing(format!(
            "the reference tip {reference} did not measure the sphere"
        )));
    }
    let ref_head = settings[refs[0]].head_deg;
    if refs.iter().any(|&i| settings[i].head_deg != ref_head) {
        return Err(ProcedureError::IllConditioned(format!(
            "the reference tip {reference} measured the sphere at more than one head angle: \
             qualify the reference at one head angle and give the others as settings of it"
        )));
    }
    let others: Vec<usize> = (0..settings.len())
        .filter(|&i| settings[i].tip != reference)
        .collect();
    if others.is_empty() {
        return Err(ProcedureError::Missing(format!(
            "only the reference tip {reference} measured the sphere: measure it with every \
             other tip and head angle to qualify them"
        )));
    }
    let mut notes = vec![];
    // Reference centre at time t (linear between its measurements), with its covariance
    // (diagonal).
    let ref_at = |t: f64| -> (Vec3, Vec3) {
        let r: Vec<&Setting> = refs.iter().map(|&i| &settings[i]).collect();
        let c = |s: &Setting| Vec3::from(s.center_mm);
        let v = |s: &Setting| Vec3::from(s.center_sigma_um.map(|x| (x * 1e-3).powi(2)));
        if r.len() == 1 || t <= r[0].t_s {
            return (c(r[0]), v(r[0]));
        }
        for w in r.windows(2) {
            if t <= w[1].t_s {
                let f = (t - w[0].t_s) / (w[1].t_s - w[0].t_s);
                return (
                    c(w[0]) * (1.0 - f) + c(w[1]) * f,
                    v(w[0]) * (1.0 - f).powi(2) + v(w[1]) * f * f,
                );
            }
        }
        let last = r[r.len() - 1];
        (c(last), v(last))
    };
    let (t_first, t_last) = (settings[refs[0]].t_s, settings[refs[refs.len() - 1]].t_s);
    for &i in &others {
        let s = &settings[i];
        if s.t_s < t_first || s.t_s > t_last {
            notes.push(format!(
                "tip {} at head angles ({}, {})° was measured outside the reference's \
                 measurements ({:.0}–{:.0} s): the drift between them is not followed; measure \
                 the reference before and after every other tip",
                s.tip, s.head_deg[0], s.head_deg[1], t_first, t_last
            ));
        }
    }
    // Temperatures.
    let temps: Vec<f64> = settings.iter().filter_map(|s| s.temp_c).collect();
    let all_temps = temps.len() == settings.len();
    let (t_q, t_range) = if all_temps {
        let lo = temps.iter().cloned().fold(f64::MAX, f64::min);
        let hi = temps.iter().cloned().fold(f64::MIN, f64::max);
        (
            Some(temps.iter().sum::<f64>() / temps.len() as f64),
            hi - lo,
        )
    } else {
        (None, 0.0)
    };
    let fit_alpha = all_temps && t_range >= MIN_TEMP_RANGE_K;
    let mut undetermined = vec![format!(
        "tip{reference}.l1_mm: the reference stylus's length (its offset defines the machine's \
         zero: every other tip is qualified relative to it)"
    )];
    if !fit_alpha {
        undetermined.push(if all_temps {
            format!(
                "expansion coefficients per stylus: the stylus temperature spanned only \
                 {t_range:.2} K (≥ {MIN_TEMP_RANGE_K} K needed): qualify again at another \
                 temperature"
            )
        } else {
            "expansion coefficients per stylus: the bags have no `stylus` temperature".into()
        });
    }
    // The tips' geometry (catalogue or earlier qualification).
    let geom = |tip: u32| start.geometry.tips.iter().find(|t| t.id == tip);
    for s in &settings {
        if geom(s.tip).is_none() {
            return Err(ProcedureError::Missing(format!(
                "tip {} is not in the calibration's geometry",
                s.tip
            )));
        }
    }
    // Offsets from the reference and the calibrated offsets the corrector used.
    let offset_cal = |i: usize| -> Vec3 {
        let g = &gs[i];
        let n = g.idx.len() as f64;
        g.idx
            .iter()
            .map(|&k| ds.points[k].ctx.tip_offset())
            .sum::<Vec3>()
            / n
    };
    let rot = |i: usize| ds.points[gs[i].idx[0]].ctx.machine_from_probe;
    let o_ref = offset_cal(refs[0]);
    // Unknowns: per other stylus its limbs (those its catalogue geometry has) and α; α_ref.
    let mut styli: Vec<u32> = others.iter().map(|&i| settings[i].tip).collect();
    styli.sort();
    styli.dedup();
    let mut names = vec![];
    let mut col: BTreeMap<(u32, &'static str), usize> = BTreeMap::new();
    for &k in &styli {
        let g = geom(k).expect("checked");
        let mut limbs = vec!["l1_mm"];
        if g.l2_mm != 0.0 {
            limbs.push("l2_mm");
        }
        if g.l3_mm != 0.0 {
            limbs.push("l3_mm");
        }
        if fit_alpha {
            limbs.push("alpha_per_k");
        }
        for l in limbs {
            col.insert((k, l), names.len());
            names.push(format!("tip{k}.{l}"));
        }
    }
    if fit_alpha {
        col.insert((reference, "alpha_per_k"), names.len());
        names.push(format!("tip{reference}.alpha_per_k"));
    }
    // The orientation of the offsets at the sphere's position: a small rotation ω of every
    // offset relative to the reference's (the carriage's yaw, pitch and roll there — Abbe —
    // or the head's angle offsets). Not a stylus length: reported, not stored.
    let omega0 = names.len();
    for a in ["x", "y", "z"] {
        names.push(format!("rotation_{a}_rad"));
    }
    let (mut a, mut b, mut w) = (vec![], vec![], vec![]);
    let mut deltas = vec![];
    for &i in &others {
        let s = &settings[i];
        let (c_ref, v_ref) = ref_at(s.t_s);
        let delta = Vec3::from(s.center_mm) - c_ref;
        let var = Vec3::from(s.center_sigma_um.map(|x| (x * 1e-3).powi(2))) + v_ref;
        deltas.push(delta);
        let g = geom(s.tip).expect("checked");
        let r = rot(i);
        let unit = |l1: f64, l2: f64, l3: f64| {
            let mut u = g.clone();
            (u.l1_mm, u.l2_mm, u.l3_mm) = (l1, l2, l3);
            r * (u.shank_probe() + u.bent_probe())
        };
        let o_cal = offset_cal(i);
        let tau = match (s.temp_c, t_q) {
            (Some(t), Some(q)) => t - q,
            _ => 0.0,
        };
        for ax in 0..3 {
            let mut row = vec![0.0; names.len()];
            for (limb, u) in [
                ("l1_mm", unit(1.0, 0.0, 0.0)),
                ("l2_mm", unit(0.0, 1.0, 0.0)),
                ("l3_mm", unit(0.0, 0.0, 1.0)),
            ] {
                if let Some(&c) = col.get(&(s.tip, limb)) {
                    row[c] = u[ax];
                }
            }
            // ω × (o_g − o_ref): the component `ax` of the cross product.
            let d = o_cal - o_ref;
            let e = |k: usize| {
                let mut u = Vec3::zeros();
                u[k] = 1.0;
                u.cross(&d)[ax]
            };
            for k in 0..3 {
                row[omega0 + k] = e(k);
            }
            if fit_alpha {
                row[col[&(s.tip, "alpha_per_k")]] = tau * o_cal[ax];
                row[col[&(reference, "alpha_per_k")]] = -tau * o_ref[ax];
            }
            a.push(row);
            b.push(o_cal[ax] - delta[ax]);
            w.push(1.0 / var[ax].max(1e-12));
        }
    }
    let Some((theta, cov, _)) = weighted_lsq(&a, &b, &w) else {
        return Err(ProcedureError::IllConditioned(format!(
            "the settings do not separate {}: measure each stylus at ≥ 2 head angles \
             (its limbs point in different directions) and the reference before and after",
            names.join(", ")
        )));
    };
    // Residuals.
    let mut res_ss = 0.0;
    for (n_row, &i) in others.iter().enumerate() {
        for ax in 0..3 {
            let k = 3 * n_row + ax;
            let pred: f64 = a[k].iter().zip(&theta).map(|(x, t)| x * t).sum();
            let r = b[k] - pred;
            settings[i].residual_um[ax] = -r * 1e3;
            res_ss += r * r;
        }
        settings[i].offset_um = (deltas[n_row] * 1e3).into();
    }
    let residual_rms_um = (res_ss / (3 * others.len()) as f64).sqrt() * 1e3;
    let consistency_before_um =
        (deltas.iter().map(|d| d.norm_squared()).sum::<f64>() / deltas.len() as f64).sqrt() * 1e3;
    let all: Vec<Param> = names
        .iter()
        .enumerate()
        .map(|(i, n)| Param {
            name: n.clone(),
            value: theta[i],
            sigma: cov[(i, i)].max(0.0).sqrt(),
        })
        .collect();
    let rotation: Vec<Param> = all[omega0..omega0 + 3].to_vec();
    // A stylus's length along the reference's axis is measured from the reference's own
    // (the zero): it is printed as that difference, which is what the sphere determines.
    let l1_ref = geom(reference).map_or(0.0, |g| g.l1_mm);
    let mut params: Vec<Param> = all[..omega0]
        .iter()
        .chain(&all[omega0 + 3..])
        .cloned()
        .map(|mut p| {
            if let Some(k) = p.name.strip_suffix(".l1_mm") {
                p.name = format!("{k}.l1_from_tip{reference}_mm");
                p.value -= l1_ref;
            }
            p
        })
        .collect();
    // Effective radii.
    let mut tips_seen: Vec<u32> = settings.iter().map(|s| s.tip).collect();
    tips_seen.sort();
    tips_seen.dedup();
    let mut cal = start.clone();
    for &k in &tips_seen {
        let e: Vec<f64> = settings
            .iter()
            .filter(|s| s.tip == k)
            .map(|s| s.radius_error_um * 1e-3)
            .collect();
        let mean = e.iter().sum::<f64>() / e.len() as f64;
        let spread = if e.len() > 1 {
            (e.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (e.len() - 1) as f64).sqrt()
                / (e.len() as f64).sqrt()
        } else {
            0.0
        };
        // One fit's radius σ (a small share of the RMS) as the floor of the spread's.
        let fit_sigma = settings
            .iter()
            .filter(|s| s.tip == k)
            .map(|s| s.rms_um * 1e-3 / (s.points as f64).sqrt())
            .fold(0.0, f64::max);
        let g = cal
            .geometry
            .tips
            .iter_mut()
            .find(|t| t.id == k)
            .expect("checked");
        g.radius_mm += mean;
        // The radius the tip behaves as at this measurement's probing force and speed (the
        // probe's bending and the dynamics are in it until `probe-force` and `dynamics`
        // correct them): not the ball's physical radius.
        params.push(Param {
            name: format!("tip{k}.effective_radius_mm"),
            value: g.radius_mm,
            sigma: spread.max(fit_sigma),
        });
    }
    // The fitted values, by (tip, field) as the columns were laid out.
    for (&(tip, field), &c) in &col {
        if let Some(g) = cal.geometry.tips.iter_mut().find(|t| t.id == tip) {
            match field {
                "l1_mm" => g.l1_mm = theta[c],
                "l2_mm" => g.l2_mm = theta[c],
                "l3_mm" => g.l3_mm = theta[c],
                _ => {}
            }
        }
    }
    // The stylus thermal correction: the coefficients measured here, referred to T_q.
    if let Some(t_q) = t_q {
        let old = cal
            .effects
            .iter()
            .position(|e| e.kind() == "stylus_thermal");
        let mut th = match old.map(|i| &cal.effects[i]) {
            Some(EffectConfig::StylusThermal(c)) => c.clone(),
            _ => stylus_thermal::Config::zeros(false),
        };
        th.reference_temp_c = t_q;
        // A coefficient the measurement does not determine to better than its own size is
        // reported but not stored (the starting calibration's stays).
        for (&(tip, field), &c) in &col {
            if field == "alpha_per_k" {
                let sigma = cov[(c, c)].max(0.0).sqrt();
                if theta[c].abs() > sigma {
                    th.alpha_per_tip.insert(tip, theta[c]);
                } else {
                    undetermined.push(format!(
                        "tip{tip}.alpha_per_k: {:.1} ± {:.1} ppm/K, its uncertainty larger than \
                         itself (not stored): qualify again over a wider temperature range, with \
                         the machine's geometry corrected",
                        theta[c] * 1e6,
                        sigma * 1e6
                    ));
                }
            }
        }
        if fit_alpha || old.is_some() {
            match old {
                Some(i) => cal.effects[i] = EffectConfig::StylusThermal(th),
                None => cal.effects.push(EffectConfig::StylusThermal(th)),
            }
        }
    }
    params.sort_by(|a, b| a.name.cmp(&b.name));
    Ok(Outcome {
        calibration: cal,
        params,
        reference_tip: reference,
        reference_temp_c: t_q,
        temp_range_k: t_range,
        settings,
        consistency_before_um,
        residual_rms_um,
        rotation,
        undetermined,
        notes,
    })
}
