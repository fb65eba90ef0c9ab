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
//! What the settings determine, largest set first: limbs, rotation ω and the α's; then
//! without ω (one head angle per stylus — a head without rotary axes, the patent's own case —
//! cannot turn the offsets: ω stays in the lengths, named as not determined); then without the
//! α's. The expansion needs the stylus temperature to change between settings, and its signal
//! α·Δτ·|o| (0.6 µm for 10 ppm/K, 1 K and a 56 mm crank) must stand above what else differs
//! between the settings: the machine's geometry between the carriage positions of different
//! head angles (about 1 µm uncorrected) is constant per head angle, so when each stylus visits a
//! head angle ≥ 2 times the α's are fitted first from the visits' deviations from their own
//! head angle's mean (that constant projected out, with 3 degrees of freedom per head angle
//! taken from the χ² scale) and held in the lengths' fit. A coefficient is stored only when
//! more than 2σ from zero. Only the reference measured (re-qualifying it alone): its
//! effective radius; the rest is kept.
//!
//! What the settings cannot separate from the parameters is carried in their σ: the estimate
//! is linear in the offsets, θ = M·b (the structure chosen above), so an unknown term u·c in
//! b, u = 0 ± σ_u, adds σ_u²·(M·c)(M·c)ᵀ to the covariance.
//! - The scales' expansion, when the start has no `scale_thermal`: between the carriage
//!   positions of a tip and the reference the scales read α_s,j·(T_s,j − 20 °C)·(o − o_ref)_j
//!   less (ISO 1; T_s,j the scale's sensor, else the stylus's), which follows the room as the
//!   styli's growth does, and its constant part is in the lengths. α_s,j = 0 ± 12 ppm/K per
//!   axis (glass-ceramic to steel, aluminium at 2σ). A coefficient this leaves within 2σ of
//!   zero is named confounded with the scales' expansion, not stored: `calibrate scales`
//!   first, then `tips`, separates them.
//! - One head angle per stylus: the machine's geometry between the carriage positions of a
//!   tip and the reference is one constant per (tip, head angle), which the lengths take in
//!   the axes they span; σ_g² = Σ (group means' residuals)² / (3·groups − limbs), the size
//!   of what is left in the axes they do not span.
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
/// fitted at all, K (ten times the stylus sensor's noise): whether a range suffices is then
/// the fit's σ — what it takes is stated in the module's doc.
const MIN_TEMP_RANGE_K: f64 = 0.02;

/// The scales' expansion coefficient assumed when the starting calibration states none, per
/// K: 0 ± 12 ppm/K covers glass-ceramic (≈ 0), steel (11.5) and, at 2σ, aluminium (23).
pub(crate) const SCALE_ALPHA_PRIOR_PER_K: f64 = 12e-6;

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
    /// Only the reference tip measured the sphere: its radius re-qualified, no tip-to-tip
    /// consistency (the two figures above are zero).
    pub reference_alone: bool,
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
pub(super) struct Group {
    pub(super) feature: usize,
    pub(super) tip: u32,
    pub(super) head: [f64; 2],
    pub(super) idx: Vec<usize>,
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
pub(super) fn groups(ds: &Dataset, spheres: &BTreeMap<usize, f64>) -> Vec<Group> {
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
pub(super) fn center_cov(
    points: &[Vec3],
    center: &Vec3,
    rms: f64,
) -> Option<nalgebra::Matrix3<f64>> {
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
    // A sensor's mean over a setting's points (None without a valid reading).
    let mean_temp = |g: &Group, s: usize| -> Option<f64> {
        let v: Vec<f64> = g
            .idx
            .iter()
            .map(|&i| &ds.points[i].ctx)
            .filter(|c| c.temps_valid & (1 << s) != 0)
            .map(|c| c.temps[s])
            .collect();
        (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
    };
    let scale_slots = crate::effects::scale_thermal::SENSORS.map(|n| ds.sensors.find(n));
    // Each setting's scale temperatures (the stylus's stands in for a scale without a sensor:
    // both follow the room).
    let mut scale_temps: Vec<Option<[f64; 3]>> = vec![];
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
        let temp_c = slot.and_then(|s| mean_temp(g, s));
        let st = scale_slots.map(|s| s.and_then(|s| mean_temp(g, s)).or(temp_c));
        scale_temps.push(
            st.iter()
                .all(|t| t.is_some())
                .then(|| st.map(|t| t.unwrap_or(20.0))),
        );
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
    let mut notes = vec![];
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
    let mut undetermined = vec![format!(
        "tip{reference}.l1_mm: the reference stylus's length (its offset defines the machine's \
         zero: every other tip is qualified relative to it)"
    )];
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
    if others.is_empty() {
        // The reference re-qualified alone (a new ball, a crash): its effective radius; the
        // other styli keep the start's lengths, measured from the reference's zero.
        notes.push(format!(
            "only the reference tip {reference} measured the sphere: its effective radius is \
             re-qualified; the other styli keep the starting calibration's lengths (measure \
             them against it to qualify them again)"
        ));
        undetermined.push(
            "expansion coefficients: the reference's growth along its own axis and the \
             scales' are one drift of the sphere's centre without another stylus"
                .into(),
        );
        let mut params = vec![];
        let mut cal = start.clone();
        effective_radii(&settings, &mut cal, &mut params);
        return Ok(Outcome {
            calibration: cal,
            params,
            reference_tip: reference,
            reference_temp_c: t_q,
            temp_range_k: t_range,
            settings,
            consistency_before_um: 0.0,
            residual_rms_um: 0.0,
            reference_alone: true,
            rotation: vec![],
            undetermined,
            notes,
        });
    }
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
    let fit_alpha = all_temps && t_range >= MIN_TEMP_RANGE_K;
    if !fit_alpha {
        undetermined.push(if all_temps {
            format!(
                "expansion coefficients per stylus: the stylus temperature spanned only \
                 {t_range:.3} K, within its sensor's noise: qualify again as the room's \
                 temperature changes"
            )
        } else {
            "expansion coefficients per stylus: the bags have no `stylus` temperature".into()
        });
    }
    if fit_alpha && !start.effects.iter().any(|e| e.kind() == "scale_thermal") {
        notes.push(
            "the starting calibration has no scales' expansion (`scale_thermal`): the scales' \
             growth between the carriage positions of the tips (the offsets × α_scale × the \
             scales' temperature change) follows the room as the styli's does; the styli's \
             coefficients and lengths carry it in their σ (α_scale 0 ± 12 ppm/K) — measure \
             the scales first (`scancorr calibrate scales`) for the styli's own coefficients"
                .into(),
        );
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
    let alpha_cols: Vec<usize> = col
        .iter()
        .filter(|((_, f), _)| *f == "alpha_per_k")
        .map(|(_, &c)| c)
        .collect();
    let limb_cols: Vec<usize> = col
        .iter()
        .filter(|((_, f), _)| *f != "alpha_per_k")
        .map(|(_, &c)| c)
        .collect();
    let rot_cols: Vec<usize> = (omega0..omega0 + 3).collect();
    let n_all = names.len();
    let mut theta = vec![0.0; n_all];
    let mut cov = nalgebra::DMatrix::<f64>::zeros(n_all, n_all);
    let mut fitted = vec![false; n_all];
    // (1) The expansion coefficients from the settings repeated at one head angle, each
    // against its own mean: what the machine's geometry does between the carriage positions
    // of different head angles is constant per head angle and cancels; the lengths do too.
    let setting_key = |i: usize| {
        let s = &settings[i];
        (
            s.tip,
            (s.head_deg[0] * 1e3).round() as i64,
            (s.head_deg[1] * 1e3).round() as i64,
        )
    };
    let mut repeats: BTreeMap<(u32, i64, i64), Vec<usize>> = BTreeMap::new();
    for (n_row, &i) in others.iter().enumerate() {
        repeats.entry(setting_key(i)).or_default().push(n_row);
    }
    let every_stylus_repeated = styli.iter().all(|&k| {
        repeats
            .iter()
            .any(|((t, _, _), rows)| *t == k && rows.len() >= 2)
    });
    // The rows of (1) for a right-hand side `rhs`: each repeated group's deviations from its
    // own weighted mean (the group's offset projected out).
    let repeat_rows = |rhs: &[f64]| {
        let (mut ar, mut br, mut wr) = (vec![], vec![], vec![]);
        let mut groups_used = 0usize;
        for rows in repeats.values().filter(|r| r.len() >= 2) {
            groups_used += 1;
            for ax in 0..3 {
                let sw: f64 = rows.iter().map(|&r| w[3 * r + ax]).sum();
                let mean = |f: &dyn Fn(usize) -> f64| {
                    rows.iter()
                        .map(|&r| w[3 * r + ax] * f(3 * r + ax))
                        .sum::<f64>()
                        / sw
                };
                let mean_a: Vec<f64> = alpha_cols.iter().map(|&c| mean(&|k| a[k][c])).collect();
                let mean_b = mean(&|k| rhs[k]);
                for &r in rows {
                    let k = 3 * r + ax;
                    ar.push(
                        alpha_cols
                            .iter()
                            .zip(&mean_a)
                            .map(|(&c, mu)| a[k][c] - mu)
                            .collect::<Vec<_>>(),
                    );
                    br.push(rhs[k] - mean_b);
                    wr.push(w[k]);
                }
            }
        }
        (ar, br, wr, groups_used)
    };
    let mut alpha_from_repeats = false;
    if fit_alpha && every_stylus_repeated {
        let (ar, br, wr, groups_used) = repeat_rows(&b);
        if let Some((t, c, rms)) = weighted_lsq(&ar, &br, &wr) {
            // The χ² scale with the degrees of freedom the group offsets took (3 per group).
            let (m, n) = (ar.len() as f64, alpha_cols.len() as f64);
            let chi2 = rms * rms * m;
            let used = (chi2 / (m - n).max(1.0)).max(1.0);
            let right = (chi2 / (m - n - 3.0 * groups_used as f64).max(1.0)).max(1.0);
            for (i, &ci) in alpha_cols.iter().enumerate() {
                theta[ci] = t[i];
                fitted[ci] = true;
                for (j, &cj) in alpha_cols.iter().enumerate() {
                    cov[(ci, cj)] = c[(i, j)] / used * right;
                }
            }
            alpha_from_repeats = true;
        }
    }
    // (2) The lengths (with the rotation and the expansion when the settings determine them):
    // the largest set of unknowns the settings separate.
    let b_fix: Vec<f64> = if alpha_from_repeats {
        a.iter()
            .zip(&b)
            .map(|(row, y)| y - alpha_cols.iter().map(|&c| row[c] * theta[c]).sum::<f64>())
            .collect()
    } else {
        b.clone()
    };
    let alpha_joint: &[usize] = if fit_alpha && !alpha_from_repeats {
        &alpha_cols
    } else {
        &[]
    };
    let tries: &[(bool, bool)] = if alpha_joint.is_empty() {
        &[(true, false), (false, false)]
    } else {
        &[(true, true), (false, true), (true, false), (false, false)]
    };
    let mut solved = None;
    for &(with_rot, with_alpha) in tries {
        let cols: Vec<usize> = limb_cols
            .iter()
            .copied()
            .chain(if with_rot { rot_cols.clone() } else { vec![] })
            .chain(if with_alpha {
                alpha_joint.to_vec()
            } else {
                vec![]
            })
            .collect();
        let sub: Vec<Vec<f64>> = a
            .iter()
            .map(|r| cols.iter().map(|&c| r[c]).collect())
            .collect();
        if let Some(s) = weighted_lsq(&sub, &b_fix, &w) {
            solved = Some((cols, s, with_rot, with_alpha));
            break;
        }
    }
    let Some((cols, (t, c, _), with_rot, with_alpha)) = solved else {
        return Err(ProcedureError::IllConditioned(format!(
            "the settings do not separate {}: measure each stylus at a head angle where its \
             limbs point along different axes, and the reference before and after",
            names[..omega0]
                .iter()
                .filter(|n| !n.ends_with("alpha_per_k"))
                .cloned()
                .collect::<Vec<_>>()
                .join(", ")
        )));
    };
    for (i, &ci) in cols.iter().enumerate() {
        theta[ci] = t[i];
        fitted[ci] = true;
        for (j, &cj) in cols.iter().enumerate() {
            cov[(ci, cj)] = c[(i, j)];
        }
    }
    if !with_rot {
        undetermined.push(
            "the rotation of the offsets at the sphere's position (the machine's angular \
             errors there, the head's angle offsets): one head angle per stylus does not turn \
             the offsets; it stays in the lengths"
                .into(),
        );
    }
    if fit_alpha && !alpha_from_repeats && !with_alpha {
        undetermined.push(
            "expansion coefficients per stylus: the settings do not separate them from the \
             lengths — measure a head angle again later in the room's drift"
                .into(),
        );
    }
    // What the data cannot tell from the parameters, propagated into their covariance: the
    // estimate is linear in the right-hand side (θ = M·b, the structure chosen above), so an
    // unknown term σ·c in b moves θ by σ·M·c.
    let replay = |rhs: &[f64]| -> Vec<f64> {
        let mut th = vec![0.0; n_all];
        if alpha_from_repeats {
            let (ar, br, wr, _) = repeat_rows(rhs);
            if let Some((t, _, _)) = weighted_lsq(&ar, &br, &wr) {
                for (i, &ci) in alpha_cols.iter().enumerate() {
                    th[ci] = t[i];
                }
            }
        }
        let bf: Vec<f64> = a
            .iter()
            .zip(rhs)
            .map(|(row, y)| y - alpha_cols.iter().map(|&c| row[c] * th[c]).sum::<f64>())
            .collect();
        let sub: Vec<Vec<f64>> = a
            .iter()
            .map(|r| cols.iter().map(|&c| r[c]).collect())
            .collect();
        if let Some((t, _, _)) = weighted_lsq(&sub, &bf, &w) {
            for (i, &ci) in cols.iter().enumerate() {
                th[ci] = t[i];
            }
        }
        th
    };
    let mut add_nuisance = |sigma: f64, column: &[f64]| -> Vec<f64> {
        let m = replay(column);
        for i in 0..n_all {
            for j in 0..n_all {
                cov[(i, j)] += sigma * sigma * m[i] * m[j];
            }
        }
        m
    };
    // (a) The scales' expansion, when the start has none: between the carriage positions of
    // a tip and the reference the scales read α_s,j·(T_s,j − 20 °C)·(o − o_ref)_j less, which
    // follows the room as the styli's growth does.
    let no_scale_thermal = !start.effects.iter().any(|e| e.kind() == "scale_thermal");
    let mut scale_share = vec![0.0; n_all];
    if no_scale_thermal && others.iter().all(|&i| scale_temps[i].is_some()) {
        for j in 0..3 {
            let mut column = vec![0.0; a.len()];
            for (n_row, &i) in others.iter().enumerate() {
                let ts = scale_temps[i].expect("checked")[j];
                column[3 * n_row + j] = -(ts - 20.0) * (offset_cal(i) - o_ref)[j];
            }
            let m = add_nuisance(SCALE_ALPHA_PRIOR_PER_K, &column);
            for (v, mi) in scale_share.iter_mut().zip(&m) {
                *v += (SCALE_ALPHA_PRIOR_PER_K * mi).powi(2);
            }
        }
    }
    // (b) One head angle per stylus: the machine's geometry between the carriage positions
    // of a tip and the reference is one constant per (tip, head angle), taken by the lengths
    // in the axes they span; its size is what is left in the axes they do not (the group
    // means' residuals over their degrees of freedom).
    if !with_rot {
        let mut ss = 0.0;
        for rows in repeats.values() {
            for ax in 0..3 {
                let (mut sw, mut sr) = (0.0, 0.0);
                for &r in rows {
                    let k = 3 * r + ax;
                    let pred: f64 = a[k].iter().zip(&theta).map(|(x, t)| x * t).sum();
                    sw += w[k];
                    sr += w[k] * (b[k] - pred);
                }
                ss += (sr / sw).powi(2);
            }
        }
        let dof = 3 * repeats.len() as i64 - limb_cols.len() as i64;
        if dof >= 1 {
            let sigma_g = (ss / dof as f64).sqrt();
            for rows in repeats.values() {
                for ax in 0..3 {
                    let mut column = vec![0.0; a.len()];
                    for &r in rows {
                        column[3 * r + ax] = 1.0;
                    }
                    add_nuisance(sigma_g, &column);
                }
            }
        } else {
            undetermined.push(
                "the machine's geometry between the tips' carriage positions: one head angle \
                 per stylus and as many limbs as axes leave nothing to measure it by; it is in \
                 the lengths, not in their σ"
                    .into(),
            );
        }
    }
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
    let rotation: Vec<Param> = if with_rot {
        all[omega0..omega0 + 3].to_vec()
    } else {
        vec![]
    };
    // A stylus's length along the reference's axis is measured from the reference's own
    // (the zero): it is printed as that difference, which is what the sphere determines.
    let l1_ref = geom(reference).map_or(0.0, |g| g.l1_mm);
    let mut params: Vec<Param> = all[..omega0]
        .iter()
        .enumerate()
        .filter(|(i, _)| fitted[*i])
        .map(|(_, p)| p.clone())
        .map(|mut p| {
            if let Some(k) = p.name.strip_suffix(".l1_mm") {
                p.name = format!("{k}.l1_from_tip{reference}_mm");
                p.value -= l1_ref;
            }
            p
        })
        .collect();
    let mut cal = start.clone();
    effective_radii(&settings, &mut cal, &mut params);
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
            if field == "alpha_per_k" && fitted[c] {
                let sigma = cov[(c, c)].max(0.0).sqrt();
                let from_scales = scale_share[c].sqrt();
                if theta[c].abs() > 2.0 * sigma {
                    th.alpha_per_tip.insert(tip, theta[c]);
                } else if from_scales > 0.5 * sigma {
                    undetermined.push(format!(
                        "tip{tip}.alpha_per_k: {:.1} ± {:.1} ppm/K, confounded with the \
                         scales' expansion (± {:.1} ppm/K of it from the scales' unknown \
                         0 ± {:.0} ppm/K: the start has no `scale_thermal`; not stored): measure \
                         the scales first (`scancorr calibrate scales`) and qualify again",
                        theta[c] * 1e6,
                        sigma * 1e6,
                        from_scales * 1e6,
                        SCALE_ALPHA_PRIOR_PER_K * 1e6
                    ));
                } else {
                    undetermined.push(format!(
                        "tip{tip}.alpha_per_k: {:.1} ± {:.1} ppm/K, not 2σ from zero (not \
                         stored): visit each head angle twice as the room's temperature \
                         changes (`sim --program tips-repeat`), or over a wider range",
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
        reference_alone: false,
        notes,
    })
}

/// Each tip's effective radius: the start's plus the mean over its settings of the sphere's
/// fitted radius less the certified one; written into `cal`, pushed onto `params`.
fn effective_radii(settings: &[Setting], cal: &mut Calibration, params: &mut Vec<Param>) {
    let mut tips_seen: Vec<u32> = settings.iter().map(|s| s.tip).collect();
    tips_seen.sort();
    tips_seen.dedup();
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
}
