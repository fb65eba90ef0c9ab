//! `scales`: the scales' expansion coefficients from a length standard read at several
//! temperatures.
//!
//! Equations. A ball bar (two spheres whose centre distance L is certified: the features of
//! artifact `ball-bar`, taken in pairs in program order, L the distance of their nominal
//! centres as the certificate states them) lies along one axis i. Each visit v of a ball is
//! an orthogonal-distance sphere fit (free radius) of the points taken without the start's
//! scale correction; the k-th visits of the two balls give the measured distance D_k with its
//! σ from the two centres' covariances. A scale at temperature T reads the carriage's
//! position x (from its zero point o_i) as x / (1 + α_i·(T − 20 °C)), so with T_A, T_B the
//! mean temperatures of scale i over the two visits (the room drifts between them) and s_A,
//! s_B the balls' measured centres along axis i (u_i the bar's direction cosine)
//!
//! D_k / L − 1 = g_i − α_i·[(T_B − 20)·(s_B − o_i) − (T_A − 20)·(s_A − o_i)]·u_i / L,
//!
//! linear in α_i and g_i (the machine's length error between the balls at 20 °C: the scale's
//! own error, the geometry). Weighted least squares per bar, the covariance scaled by the
//! reduced χ² when it exceeds 1. α_i is determined by the change of D with T (the span of the
//! temperatures over the visits); g_i by the certificate. Written as the `scale_thermal`
//! effect (reference 20 °C, the start's sensors and zero points, which a length does not
//! determine: they enter only through the temperature change between a bar's two ends).
//!
//! Source idea: ISO 1 and ISO 10360-2's length-measurement test — a calibrated length
//! standard measured along each axis; here at several temperatures of the room's drift, so the
//! expansion is told from the machine's constant length error (the "ring at two temperatures"
//! form of the scale-expansion check of the patents' chain).

use super::tips::{center_cov, groups};
use super::{weighted_lsq, Param, ProcedureError};
use crate::calib::Calibration;
use crate::effects::{scale_thermal, EffectConfig};
use crate::lab::dataset::Dataset;
use crate::lab::program::FeatureKind;
use crate::sample::Vec3;
use crate::shape;
use serde::Serialize;
use std::collections::BTreeMap;

/// One measured length: the k-th visits of a bar's two balls.
#[derive(Debug, Clone, Serialize)]
pub struct Reading {
    /// Axis of the bar: `x`, `y` or `z`.
    pub axis: String,
    /// Measured centre distance less the certified one, µm.
    pub error_um: f64,
    /// Its standard uncertainty, µm.
    pub sigma_um: f64,
    /// Mean temperature of the axis's scale over the two visits, °C.
    pub temp_c: f64,
    /// What is left after the fit, µm.
    pub residual_um: f64,
}

/// One bar.
#[derive(Debug, Clone, Serialize)]
pub struct Bar {
    /// Axis.
    pub axis: String,
    /// Certified centre distance, mm.
    pub length_mm: f64,
    /// Span of the scale's temperature over its readings, K.
    pub temp_span_k: f64,
    /// Readings.
    pub readings: usize,
}

/// The outcome of `scales`.
#[derive(Debug, Clone, Serialize)]
pub struct Outcome {
    /// The calibration with the scales' expansion (unversioned).
    #[serde(skip)]
    pub calibration: Calibration,
    /// Fitted parameters with their σ (`scale_x.alpha_per_k`, `scale_x.length_error_ppm`, …).
    pub params: Vec<Param>,
    /// The bars measured.
    pub bars: Vec<Bar>,
    /// Every reading.
    pub readings: Vec<Reading>,
    /// RMS of the length errors with the start's scale correction left out, µm.
    pub rms_before_um: f64,
    /// RMS left after the fit, µm.
    pub rms_after_um: f64,
    /// What this measurement cannot determine, and why.
    pub undetermined: Vec<String>,
    /// Remarks.
    pub notes: Vec<String>,
}

const AXES: [&str; 3] = ["x", "y", "z"];

/// Measures the scales' expansion: `ds` built from the bags with `start` less its
/// `scale_thermal` (this procedure measures it).
pub fn run(ds: &Dataset, start: &Calibration) -> Result<Outcome, ProcedureError> {
    let balls: Vec<usize> = ds
        .features
        .iter()
        .enumerate()
        .filter(|(_, (_, f))| f.artifact == "ball-bar" && f.kind == FeatureKind::Boss)
        .map(|(i, _)| i)
        .collect();
    if balls.len() < 2 {
        return Err(ProcedureError::Missing(format!(
            "{} ball-bar spheres in the bags: `scales` needs a length standard — two spheres of \
             a certified centre distance (features of artifact `ball-bar`, in pairs) along each \
             axis, read several times as the room's temperature changes, e.g. `scancorr sim \
             --program scales`",
            balls.len()
        )));
    }
    if balls.len() % 2 != 0 {
        return Err(ProcedureError::Missing(format!(
            "{} ball-bar spheres: the balls come in pairs (a bar's two ends, in program order)",
            balls.len()
        )));
    }
    let radius: BTreeMap<usize, f64> = balls
        .iter()
        .map(|&i| {
            let f = &ds.features[i].1;
            (
                i,
                f.certificate_diameter_mm.unwrap_or(f.nominal_diameter_mm) / 2.0,
            )
        })
        .collect();
    let gs = groups(ds, &radius);
    // Each visit: its centre, covariance and mean time.
    struct Visit {
        center: Vec3,
        var: Vec3,
        idx: Vec<usize>,
    }
    let mut visits: BTreeMap<usize, Vec<Visit>> = BTreeMap::new();
    for g in &gs {
        let pts: Vec<Vec3> = g.idx.iter().map(|&i| ds.points[i].surface).collect();
        let fail = |why: String| {
            ProcedureError::IllConditioned(format!(
                "ball-bar sphere {} (visit {}): {why}",
                ds.features[g.feature].0,
                visits.get(&g.feature).map_or(0, |v| v.len()) + 1
            ))
        };
        let (zmin, zmax) = pts
            .iter()
            .fold((f64::MAX, f64::MIN), |a, p| (a.0.min(p.z), a.1.max(p.z)));
        if zmax - zmin < 0.2 * radius[&g.feature] {
            return Err(fail(
                "scanned at one height: its centre is undetermined along z; scan circles at ≥ 2 \
                 latitudes"
                    .into(),
            ));
        }
        let fit =
            shape::fit_sphere(&pts).map_err(|e| fail(format!("the sphere fit failed: {e}")))?;
        let cov = center_cov(&pts, &fit.center, fit.rms)
            .ok_or_else(|| fail(format!("too few points ({}) for a sphere", pts.len())))?;
        visits.entry(g.feature).or_default().push(Visit {
            center: fit.center,
            var: Vec3::new(cov[(0, 0)], cov[(1, 1)], cov[(2, 2)]),
            idx: g.idx.clone(),
        });
    }
    let mut undetermined = vec![
        "the scales' zero points: a length does not see them (kept from the start)".to_string(),
    ];
    let mut notes = vec![];
    let mut params = vec![];
    let mut bars = vec![];
    let mut readings = vec![];
    let mut alpha: [Option<(f64, f64)>; 3] = [None; 3];
    let (mut ss_before, mut ss_after) = (0.0, 0.0);
    for pair in balls.chunks(2) {
        let (fa, fb) = (pair[0], pair[1]);
        let na = Vec3::from(ds.features[fa].1.nominal_center);
        let nb = Vec3::from(ds.features[fb].1.nominal_center);
        let dir = nb - na;
        let length = dir.norm();
        let ax = (0..3)
            .max_by(|&i, &j| dir[i].abs().total_cmp(&dir[j].abs()))
            .expect("three axes");
        if length < 50.0 || dir[ax].abs() < 0.99 * length {
            return Err(ProcedureError::IllConditioned(format!(
                "ball-bar spheres {} and {}: {length:.1} mm apart, not along one axis (a bar \
                 along X, Y or Z of ≥ 50 mm)",
                ds.features[fa].0, ds.features[fb].0
            )));
        }
        let axis = AXES[ax];
        let slot = ds.sensors.find(&format!("scale_{axis}")).ok_or_else(|| {
            ProcedureError::Missing(format!(
                "the bags have no `scale_{axis}` temperature: the scale's expansion needs it"
            ))
        })?;
        let (va, vb) = (
            visits.get(&fa).map_or(&[][..], |v| &v[..]),
            visits.get(&fb).map_or(&[][..], |v| &v[..]),
        );
        let k = va.len().min(vb.len());
        if k < 2 {
            return Err(ProcedureError::Missing(format!(
                "the {axis} bar's balls were read {} and {} times: ≥ 2 readings of each, at \
                 different temperatures",
                va.len(),
                vb.len()
            )));
        }
        let u = dir / length;
        let (mut a, mut b, mut w, mut rows) = (vec![], vec![], vec![], vec![]);
        // The scale's zero point (a scale grows from it): the start's.
        let origin = match start.effects.iter().find(|e| e.kind() == "scale_thermal") {
            Some(EffectConfig::ScaleThermal(c)) => c.origin_mm[ax],
            _ => 0.0,
        };
        let temp_of = |v: &Visit| -> Result<f64, ProcedureError> {
            let t: Vec<f64> = v
                .idx
                .iter()
                .map(|&i| &ds.points[i].ctx)
                .filter(|c| c.temps_valid & (1 << slot) != 0)
                .map(|c| c.temps[slot])
                .collect();
            if t.is_empty() {
                return Err(ProcedureError::Missing(format!(
                    "the {axis} bar: no valid `scale_{axis}` temperature during a reading"
                )));
            }
            Ok(t.iter().sum::<f64>() / t.len() as f64)
        };
        for (x, y) in va.iter().zip(vb).take(k) {
            let (ta, tb) = (temp_of(x)?, temp_of(y)?);
            let d = y.center - x.center;
            let dist = d.norm();
            // σ of the distance: the centres' variances along the bar.
            let var: f64 = (0..3).map(|i| u[i] * u[i] * (x.var[i] + y.var[i])).sum();
            let e = dist / length - 1.0;
            // Each ball read by the scale at its own temperature, from the scale's zero:
            // the distance shrinks by α·[(T_B − 20)·(s_B − o) − (T_A − 20)·(s_A − o)]·u_i.
            let grow = ((tb - 20.0) * (y.center[ax] - origin)
                - (ta - 20.0) * (x.center[ax] - origin))
                * u[ax]
                / length;
            a.push(vec![1.0, -grow]);
            b.push(e);
            w.push(1.0 / (var.max(1e-12) / (length * length)));
            rows.push((dist - length, var.sqrt(), 0.5 * (ta + tb), grow));
        }
        let ts: Vec<f64> = rows.iter().map(|r| r.2).collect();
        let span = ts.iter().cloned().fold(f64::MIN, f64::max)
            - ts.iter().cloned().fold(f64::MAX, f64::min);
        bars.push(Bar {
            axis: axis.into(),
            length_mm: length,
            temp_span_k: span,
            readings: k,
        });
        let Some((theta, cov, _)) = weighted_lsq(&a, &b, &w) else {
            undetermined.push(format!(
                "scale_{axis}.alpha_per_k: the {axis} scale's temperature did not change over \
                 its readings ({span:.3} K): read the bar again as the room warms or cools"
            ));
            continue;
        };
        let (g, al) = (theta[0], theta[1]);
        let (sg, sa) = (cov[(0, 0)].sqrt(), cov[(1, 1)].sqrt());
        for (err, s, t, grow) in &rows {
            let fit = (g - al * grow) * length;
            ss_before += (err * 1e3).powi(2);
            ss_after += ((err - fit) * 1e3).powi(2);
            readings.push(Reading {
                axis: axis.into(),
                error_um: err * 1e3,
                sigma_um: s * 1e3,
                temp_c: *t,
                residual_um: (err - fit) * 1e3,
            });
        }
        params.push(Param {
            name: format!("scale_{axis}.alpha_per_k"),
            value: al,
            sigma: sa,
        });
        params.push(Param {
            name: format!("scale_{axis}.length_error_ppm"),
            value: g * 1e6,
            sigma: sg * 1e6,
        });
        if al.abs() > 2.0 * sa {
            alpha[ax] = Some((al, sa));
        } else {
            undetermined.push(format!(
                "scale_{axis}.alpha_per_k: {:.2} ± {:.2} ppm/K over a {span:.2} K span, not 2σ \
                 from zero (not stored): read the bar over a wider temperature change",
                al * 1e6,
                sa * 1e6
            ));
        }
    }
    let n = readings.len().max(1) as f64;
    for a in AXES {
        if !bars.iter().any(|b| b.axis == a) {
            undetermined.push(format!(
                "scale_{a}.alpha_per_k: no bar along {a} (kept from the start)"
            ));
        }
    }
    // The scales' expansion: the measured coefficients, the start's where not measured.
    let mut cal = start.clone();
    let old = cal.effects.iter().position(|e| e.kind() == "scale_thermal");
    let mut st = match old.map(|i| &cal.effects[i]) {
        Some(EffectConfig::ScaleThermal(c)) => c.clone(),
        _ => scale_thermal::Config::zeros(),
    };
    if st.reference_temp_c != 20.0 {
        notes.push(format!(
            "the start's scale correction referred to {:.2} °C: the new one to 20 °C",
            st.reference_temp_c
        ));
        st.reference_temp_c = 20.0;
    }
    let mut any = false;
    for (i, a) in alpha.iter().enumerate() {
        if let Some((v, _)) = a {
            st.alpha_per_k[i] = *v;
            any = true;
        }
    }
    if any {
        match old {
            Some(i) => cal.effects[i] = EffectConfig::ScaleThermal(st),
            None => cal.effects.push(EffectConfig::ScaleThermal(st)),
        }
    }
    params.sort_by(|a, b| a.name.cmp(&b.name));
    Ok(Outcome {
        calibration: cal,
        params,
        bars,
        readings,
        rms_before_um: (ss_before / n).sqrt(),
        rms_after_um: (ss_after / n).sqrt(),
        undetermined,
        notes,
    })
}
