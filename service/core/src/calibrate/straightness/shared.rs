//! What the three methods share: readings flattened and checked, profiles with their lines
//! removed, the exact propagation of the readings' σ and the result assembled.

use super::*;

/// Station readings flattened station-major.
pub(super) struct Flat {
    pub(super) xs: Vec<f64>,
    pub(super) values: Vec<f64>,
    pub(super) u: Vec<f64>,
}

/// Profiles of a linear estimate before (or after) the unseen line and constant are removed.
#[derive(Clone)]
pub(super) struct Raw {
    pub(super) part: Vec<f64>,
    pub(super) guide: Vec<f64>,
    pub(super) pitch: Option<Vec<f64>>,
}

/// Where the profiles live.
pub(super) struct Layout {
    pub(super) part_pos: Vec<f64>,
    pub(super) stations: Vec<f64>,
}

pub(super) fn spacing(mount: &ProbeMount) -> Result<f64, ProcedureError> {
    let l = mount.spacing_mm;
    if !(l.is_finite() && l > 0.0) {
        return Err(ProcedureError::IllConditioned(format!(
            "the probe spacing must be a positive length, got {l} mm: give the distance \
             between neighbouring probes"
        )));
    }
    Ok(l)
}

pub(super) fn flatten(
    run: &str,
    stations: &[StationReading],
    probes: usize,
    method: &str,
) -> Result<Flat, ProcedureError> {
    if stations.len() < MIN_STATIONS {
        return Err(ProcedureError::Missing(format!(
            "the {method} method needs at least {MIN_STATIONS} stations (the line of part and \
             guide is removed, the guide needs a third), the {run} has {}: measure more \
             stations along the travel",
            stations.len()
        )));
    }
    let mut flat = Flat {
        xs: vec![],
        values: vec![],
        u: vec![],
    };
    for (k, st) in stations.iter().enumerate() {
        if !st.x_mm.is_finite() {
            return Err(ProcedureError::Missing(format!(
                "{run} station {k}: its position is not finite ({}); give the carriage \
                 position",
                st.x_mm
            )));
        }
        if st.readings.len() != probes {
            return Err(ProcedureError::Missing(format!(
                "{run} station {k} (x = {:.4} mm) has {} probe readings; the {method} method \
                 needs {probes} (probes {}) at every station",
                st.x_mm,
                st.readings.len(),
                PROBES[..probes].join(", ")
            )));
        }
        for (j, r) in st.readings.iter().enumerate() {
            let Some(r) = r else {
                return Err(ProcedureError::Missing(format!(
                    "{run} station {k} (x = {:.4} mm): probe {} has no reading; the \
                     sequential method needs every probe at every station — re-measure it",
                    st.x_mm, PROBES[j]
                )));
            };
            if !(r.value_mm.is_finite() && r.u_mm.is_finite()) {
                return Err(ProcedureError::Missing(format!(
                    "{run} station {k} (x = {:.4} mm): probe {}'s reading is not finite \
                     (value {}, u {}) — re-measure it",
                    st.x_mm, PROBES[j], r.value_mm, r.u_mm
                )));
            }
            if r.u_mm <= 0.0 {
                return Err(ProcedureError::Missing(format!(
                    "{run} station {k} (x = {:.4} mm): probe {}'s standard error is {} mm; it \
                     must be positive (at least the probe's resolution/√12)",
                    st.x_mm, PROBES[j], r.u_mm
                )));
            }
            flat.values.push(r.value_mm);
            flat.u.push(r.u_mm);
        }
        flat.xs.push(st.x_mm);
    }
    Ok(flat)
}

pub(super) fn check_steps(run: &str, xs: &[f64], l: f64) -> Result<(), ProcedureError> {
    for k in 1..xs.len() {
        let step = xs[k] - xs[k - 1];
        if (step - l).abs() > STEP_TOLERANCE * l {
            return Err(ProcedureError::IllConditioned(format!(
                "the {run}'s stations must step by the probe spacing l = {l} mm (within \
                 {:.4} mm): station {k} at x = {:.4} mm is {step:.4} mm after station {} — \
                 without a stage sensor the sequential method needs the carriage to advance \
                 by one probe spacing per station; re-measure at steps of l (stations in \
                 increasing x), or use a shear stage whose sensor gives the true spacing",
                STEP_TOLERANCE * l,
                xs[k],
                k - 1
            )));
        }
    }
    Ok(())
}

/// Least-squares line removed (unweighted, the straightness reference line).
pub(super) fn detrend(pos: &[f64], y: &mut [f64]) {
    let n = pos.len() as f64;
    if pos.is_empty() {
        return;
    }
    let pm = pos.iter().sum::<f64>() / n;
    let ym = y.iter().sum::<f64>() / n;
    let sxx: f64 = pos.iter().map(|p| (p - pm).powi(2)).sum();
    let sxy: f64 = pos
        .iter()
        .zip(y.iter())
        .map(|(p, v)| (p - pm) * (v - ym))
        .sum();
    let b = if sxx > 0.0 { sxy / sxx } else { 0.0 };
    for (v, p) in y.iter_mut().zip(pos) {
        *v -= ym + b * (p - pm);
    }
}

impl Raw {
    /// Removes what the method cannot see: the part's and the guide's lines, the mean pitch.
    pub(super) fn finish(mut self, lay: &Layout) -> Raw {
        detrend(&lay.part_pos, &mut self.part);
        detrend(&lay.stations, &mut self.guide);
        if let Some(p) = &mut self.pitch {
            let m = p.iter().sum::<f64>() / p.len().max(1) as f64;
            p.iter_mut().for_each(|v| *v -= m);
        }
        self
    }
}

/// The finished estimate and its σ: `response(r)` is the (unfinished) estimate from a unit
/// reading r, the linear map's column.
pub(super) fn propagate(
    lay: &Layout,
    estimate: Raw,
    u: &[f64],
    scale: f64,
    mut response: impl FnMut(usize) -> Raw,
) -> (Raw, Raw) {
    let est = estimate.finish(lay);
    let mut var = Raw {
        part: vec![0.0; est.part.len()],
        guide: vec![0.0; est.guide.len()],
        pitch: est.pitch.as_ref().map(|p| vec![0.0; p.len()]),
    };
    let acc = |v: &mut [f64], g: &[f64], u2: f64| {
        v.iter_mut().zip(g).for_each(|(a, b)| *a += b * b * u2);
    };
    for (r, ur) in u.iter().enumerate() {
        let g = response(r).finish(lay);
        let u2 = ur * ur * scale;
        acc(&mut var.part, &g.part, u2);
        acc(&mut var.guide, &g.guide, u2);
        if let (Some(v), Some(gp)) = (&mut var.pitch, &g.pitch) {
            acc(v, gp, u2);
        }
    }
    let sqrt = |v: Vec<f64>| v.into_iter().map(f64::sqrt).collect::<Vec<_>>();
    let sig = Raw {
        part: sqrt(var.part),
        guide: sqrt(var.guide),
        pitch: var.pitch.map(sqrt),
    };
    (est, sig)
}

#[allow(clippy::too_many_arguments)]
pub(super) fn output(
    method: String,
    lay: Layout,
    est: Raw,
    sig: Raw,
    cannot_see: &[&str],
    chi2_reduced: Option<f64>,
    params: Vec<Param>,
    notes: Vec<String>,
) -> Result<Separation, ProcedureError> {
    let finite = est
        .part
        .iter()
        .chain(&est.guide)
        .chain(&sig.part)
        .chain(&sig.guide)
        .chain(est.pitch.iter().flatten())
        .chain(sig.pitch.iter().flatten())
        .all(|v| v.is_finite())
        && params
            .iter()
            .all(|p| p.value.is_finite() && p.sigma.is_finite());
    if !finite {
        return Err(ProcedureError::IllConditioned(format!(
            "the {method} separation gave non-finite values: the readings' standard errors \
             span too many orders of magnitude to be weighted — check their u"
        )));
    }
    Ok(Separation {
        method,
        stations_mm: lay.stations,
        guide_straightness_mm: est.guide,
        guide_straightness_mm_u: sig.guide,
        part_positions_mm: lay.part_pos,
        part_straightness_mm: est.part,
        part_straightness_mm_u: sig.part,
        pitch_rad: est.pitch,
        pitch_rad_u: sig.pitch,
        cannot_see: cannot_see.iter().map(|s| s.to_string()).collect(),
        chi2_reduced,
        params,
        notes,
    })
}
