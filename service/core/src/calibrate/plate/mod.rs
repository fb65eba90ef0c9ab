//! The plate procedure: the features (holes) of a plate measured against their nominal
//! positions. What the errors hold, model by model, each parameter with its standard
//! uncertainty:
//!
//! * (a) **similarity** nominal → measured: `m = t + s·R(θ)·n` — offset, rotation, one scale;
//! * (b) **+ anisotropic scale / shear**, the whole linear map: `m = t + (I + Q)·s·R(θ)·n`
//!   with `Q = q·[[cos 2φ, sin 2φ], [sin 2φ, −cos 2φ]]` symmetric and traceless (a
//!   "quadrupole" of magnitude q and angle φ: it moves a hole at polar angle α radially by
//!   q·r·cos 2(α − φ) and tangentially by −q·r·sin 2(α − φ)). A CMM engineer reads the same
//!   map as a scale per axis (the images of the nominal X and Y axes stretched by e_x, e_y),
//!   the X axis's rotation, and squareness (the angle between the axes' images less 90°,
//!   positive when they open beyond 90°); both parametrisations are reported;
//! * (c) **what lies beyond**, chosen by cross-validation over holes: leave one hole out
//!   (exact for a linear least squares: the hole's 2×2 block of the hat matrix,
//!   `e₋ᵢ = (I − Hᵢᵢ)⁻¹·rᵢ`), its radial RMS the model's CV figure. The anisotropic term is
//!   the first move (it completes the linear map); then, one at a time, the best of the
//!   second- and third-order polynomial distortions of each axis (X or Y error ∝ x², xy, y²,
//!   x³, x²y, xy², y³ in the nominal coordinates over the plate's radius R, each coefficient
//!   the error at the plate's edge). A move is kept only when it lowers the CV residual
//!   significantly: the per-hole decrease of the squared left-out error has a paired
//!   t ≥ [`Options::t_min`] (3: about 0.1 % one-sided per candidate). Every candidate's CV
//!   figure is reported, and the first move kept is named as the effect the similarity
//!   model lacks.
//!
//! Each fit is an ordinary least squares over both coordinates of every hole (no weights),
//! σ from the residuals: the covariance scaled by the reduced χ² (RSS/(2n − p)); derived
//! quantities (scale, angles, per-axis terms) propagated through their Jacobian. The radial
//! residual of a hole is |m − fit| (the distance, not a projection), the radial RMS
//! √(mean |m − fit|²) over the holes. Nothing undetermined is given a value: a model the
//! holes cannot determine (too few, collinear) is named, never a NaN.
//!
//! [`OriginalTool`] reproduces the fit of the program whose output files plug-plate shops
//! keep (fitPlugPlateMeas, the University of Washington shop's SDSS plug plates), read off
//! its output: the similarity nominal → measured and then its "quadrupole" — a purely radial
//! factor `F·(1 + q·cos 2(α_F − φ))` on the similarity's fitted positions F, α_F their polar
//! angle — each fitted by MINPACK's `lmdif` (forward-difference Levenberg–Marquardt,
//! scipy's `leastsq` defaults) on the **squared** radial errors of the holes (so it
//! minimises Σ r⁴, stopped by lmdif's step-size test before that minimum: near the least
//! squares one for the similarity, at it for the quadrupole). Its `ResidRadErrRMS` is the
//! radial RMS over the small holes, the large ones (measured diameter > 3 mm, SDSS-IV
//! MaNGA holes) apart; their nominal diameter is taken as 3.28 mm for the diameter errors;
//! `QPResidRadErrRMS` is over every hole. All holes enter both fits. Pure logic: no files.

use super::{Param, ProcedureError};
use nalgebra::{DMatrix, DVector};
use serde::Serialize;

mod minpack;
mod model;
mod tool;

use model::*;
pub use tool::{original_tool, LARGE_HOLE_MM, LARGE_NOMINAL_MM};

/// One feature (hole) of the plate.
#[derive(Debug, Clone, PartialEq)]
pub struct Feature {
    /// Its name (a row number where the file names none).
    pub id: String,
    /// Nominal position, mm.
    pub nominal_mm: [f64; 2],
    /// Measured position, mm.
    pub measured_mm: [f64; 2],
    /// Nominal diameter, mm, where known.
    pub nominal_d_mm: Option<f64>,
    /// Measured diameter, mm, where known.
    pub measured_d_mm: Option<f64>,
}

/// How the procedure chooses.
#[derive(Debug, Clone, Copy)]
pub struct Options {
    /// The paired t a move needs (per-hole decrease of the squared left-out error).
    pub t_min: f64,
    /// Reproduce the original tool's fit as well.
    pub original_tool: bool,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            t_min: 3.0,
            original_tool: true,
        }
    }
}

/// Residuals of a model.
#[derive(Debug, Clone, Serialize)]
pub struct Residual {
    /// √(mean |m − fit|²) over the holes, µm.
    pub rms_radial_um: f64,
    /// RMS of the X residuals, µm.
    pub rms_x_um: f64,
    /// RMS of the Y residuals, µm.
    pub rms_y_um: f64,
    /// Largest radial residual, µm.
    pub max_radial_um: f64,
    /// The radial RMS of the leave-one-hole-out errors, µm (`None`: undetermined, see
    /// `cv_undetermined`).
    pub cv_rms_um: Option<f64>,
    /// Why the CV figure is undetermined.
    pub cv_undetermined: Option<String>,
    /// Parameters of the model.
    pub parameters: usize,
    /// Degrees of freedom left (2·holes − parameters).
    pub dof: usize,
}

/// (a) Offset, rotation and one scale, nominal → measured.
#[derive(Debug, Clone, Serialize)]
pub struct Similarity {
    /// Offset at the nominal origin, µm.
    pub offset_x_um: Param,
    /// Offset at the nominal origin, µm.
    pub offset_y_um: Param,
    /// Rotation, µrad (counter-clockwise positive).
    pub rotation_urad: Param,
    /// The same rotation, degrees.
    pub rotation_deg: Param,
    /// Scale factor.
    pub scale: Param,
    /// Scale − 1, ppm.
    pub scale_ppm: Param,
    /// What it leaves.
    pub residual: Residual,
}

/// (b) The whole linear map, in both parametrisations.
#[derive(Debug, Clone, Serialize)]
pub struct Affine {
    /// Offset at the nominal origin, µm.
    pub offset_x_um: Param,
    /// Offset at the nominal origin, µm.
    pub offset_y_um: Param,
    /// Rotation (of the polar decomposition), µrad.
    pub rotation_urad: Param,
    /// The same, degrees.
    pub rotation_deg: Param,
    /// Mean scale factor.
    pub scale: Param,
    /// Mean scale − 1, ppm.
    pub scale_ppm: Param,
    /// Quadrupole magnitude q, ppm (the original tool's terms).
    pub quadrupole_ppm: Param,
    /// Quadrupole angle φ, degrees in (−90, 90] (`None` when q is not significant: the angle
    /// of nothing).
    pub quadrupole_angle_deg: Option<Param>,
    /// Scale error of the X axis (the image of a nominal X length), ppm (a CMM engineer's
    /// terms).
    pub scale_x_ppm: Param,
    /// Scale error of the Y axis, ppm.
    pub scale_y_ppm: Param,
    /// Squareness: the angle between the axes' images less 90°, µrad (positive: wider).
    pub squareness_urad: Param,
    /// Rotation of the X axis's image, µrad.
    pub x_axis_rotation_urad: Param,
    /// What it leaves.
    pub residual: Residual,
}

/// One candidate move of the selection.
#[derive(Debug, Clone, Serialize)]
pub struct Candidate {
    /// Its id (`quadrupole`, `dx_y3`, …).
    pub term: String,
    /// What it is, in words.
    pub description: String,
    /// CV radial RMS with it, µm.
    pub cv_rms_um: Option<f64>,
    /// Paired t of the per-hole decrease of the squared left-out error.
    pub t: Option<f64>,
    /// It lowers the CV residual significantly.
    pub significant: bool,
    /// Why it cannot be judged.
    pub undetermined: Option<String>,
}

/// One round of the selection: every candidate on the model so far.
#[derive(Debug, Clone, Serialize)]
pub struct Round {
    /// The model so far.
    pub base: String,
    /// Its CV radial RMS, µm.
    pub base_cv_um: f64,
    /// Every candidate tried.
    pub candidates: Vec<Candidate>,
    /// The move kept (the best significant one).
    pub kept: Option<String>,
}

/// (c) The model chosen by cross-validation.
#[derive(Debug, Clone, Serialize)]
pub struct Selection {
    /// The rounds, in order.
    pub rounds: Vec<Round>,
    /// The terms kept beyond the similarity, in order.
    pub kept: Vec<String>,
    /// The chosen model, as a sum of terms.
    pub model: String,
    /// What it leaves.
    pub residual: Residual,
    /// Coefficients of the kept higher-order terms: the error at the plate's edge, µm.
    pub terms: Vec<Param>,
    /// Quadrupole of the chosen model (when kept), ppm.
    pub quadrupole_ppm: Option<Param>,
    /// Its angle, degrees.
    pub quadrupole_angle_deg: Option<Param>,
}

/// One hole's residuals in the original tool's fit, mm.
#[derive(Debug, Clone, Serialize)]
pub struct ToolHole {
    /// The feature's id.
    pub id: String,
    /// Measured − similarity fit, X.
    pub resid_x_mm: f64,
    /// Measured − similarity fit, Y.
    pub resid_y_mm: f64,
    /// Its length.
    pub resid_rad_mm: f64,
    /// Measured − quadrupole fit, X (the similarity's where the quadrupole is not
    /// determined).
    pub qp_resid_x_mm: f64,
    /// Measured − quadrupole fit, Y.
    pub qp_resid_y_mm: f64,
    /// Its length.
    pub qp_resid_rad_mm: f64,
}

/// The original tool's fit (fitPlugPlateMeas), its names and units.
#[derive(Debug, Clone, Serialize)]
pub struct OriginalTool {
    /// FitOffset, mm.
    pub fit_offset_mm: [f64; 2],
    /// FitScale.
    pub fit_scale: f64,
    /// FitRotAngle, degrees.
    pub fit_rot_angle_deg: f64,
    /// QPMagnitude (`None`: its fit failed).
    pub qp_magnitude: Option<f64>,
    /// QPAngle, degrees in [−90, 90].
    pub qp_angle_deg: Option<f64>,
    /// ResidRadErrRMS: the small holes' radial RMS, mm (`None`: no small hole).
    pub resid_rad_err_rms_mm: Option<f64>,
    /// The large (MaNGA) holes' radial RMS, mm.
    pub large_resid_rad_err_rms_mm: Option<f64>,
    /// DiaErrRMS of the small holes, mm.
    pub dia_err_rms_mm: Option<f64>,
    /// DiaErrRMS of the large holes (nominal 3.28 mm), mm.
    pub large_dia_err_rms_mm: Option<f64>,
    /// MaxDiaErr, mm.
    pub max_dia_err_mm: Option<f64>,
    /// QPResidRadErrRMS over every hole, mm.
    pub qp_resid_rad_err_rms_mm: Option<f64>,
    /// Radial RMS over every hole after the similarity, mm.
    pub all_resid_rad_err_rms_mm: f64,
    /// Holes counted large (measured diameter > 3 mm).
    pub large_holes: usize,
    /// lmdif's function evaluations and exit code (similarity, quadrupole).
    pub lmdif: [(usize, i32); 2],
    /// Per hole.
    pub holes: Vec<ToolHole>,
}

/// What the procedure found.
#[derive(Debug, Clone, Serialize)]
pub struct Outcome {
    /// Holes used.
    pub holes: usize,
    /// The plate's radius (largest nominal distance from the origin), mm: the scale of the
    /// higher-order terms.
    pub radius_mm: f64,
    /// (a).
    pub similarity: Similarity,
    /// (b) (`None`: undetermined, see `undetermined`).
    pub affine: Option<Affine>,
    /// (c).
    pub selection: Selection,
    /// The effect the similarity model lacks, named (the first move kept).
    pub missing_effect: Option<String>,
    /// What lies beyond it (the further moves kept), each named.
    pub beyond: Vec<String>,
    /// The original tool's fit.
    pub original_tool: Option<OriginalTool>,
    /// What the holes cannot determine.
    pub undetermined: Vec<String>,
    /// Remarks.
    pub notes: Vec<String>,
}

// ---------------------------------------------------------------------------------------
// The procedure

fn check(features: &[Feature]) -> Result<f64, ProcedureError> {
    for f in features {
        let all = [
            f.nominal_mm[0],
            f.nominal_mm[1],
            f.measured_mm[0],
            f.measured_mm[1],
        ];
        if all.iter().any(|v| !v.is_finite())
            || f.nominal_d_mm.is_some_and(|d| !d.is_finite())
            || f.measured_d_mm.is_some_and(|d| !d.is_finite())
        {
            return Err(ProcedureError::Missing(format!(
                "feature {}: a coordinate or diameter is not a finite number",
                f.id
            )));
        }
    }
    if features.len() < 3 {
        return Err(ProcedureError::Missing(format!(
            "{} feature(s): a plate fit needs at least 3 holes (offset, rotation and scale \
             are 4 parameters, and their σ needs residuals beyond them)",
            features.len()
        )));
    }
    let r = features
        .iter()
        .map(|f| f.nominal_mm[0].hypot(f.nominal_mm[1]))
        .fold(0.0, f64::max);
    if r <= 0.0 {
        return Err(ProcedureError::IllConditioned(
            "every hole is at the nominal origin: rotation and scale are not determined \
             (measure holes away from the centre)"
                .into(),
        ));
    }
    Ok(r)
}

/// Paired t of the per-hole decrease of the squared left-out error, base → new.
fn paired_t(base: &[[f64; 2]], new: &[[f64; 2]]) -> Option<f64> {
    let n = base.len();
    if n < 2 {
        return None;
    }
    let d: Vec<f64> = base
        .iter()
        .zip(new)
        .map(|(a, b)| (a[0] * a[0] + a[1] * a[1]) - (b[0] * b[0] + b[1] * b[1]))
        .collect();
    let mean = d.iter().sum::<f64>() / n as f64;
    let var = d.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
    let se = (var / n as f64).sqrt();
    (se > 0.0).then(|| mean / se)
}

/// Runs the plate procedure.
pub fn run(features: &[Feature], opts: &Options) -> Result<Outcome, ProcedureError> {
    let r = check(features)?;
    let n = features.len();
    let y = DVector::from_iterator(
        2 * n,
        features
            .iter()
            .flat_map(|f| [f.measured_mm[0], f.measured_mm[1]]),
    );
    let mut undetermined = Vec::new();
    let mut notes = Vec::new();

    // (a)
    let sim = fit(&[Term::Similarity], features, r, &y).map_err(|_| {
        ProcedureError::IllConditioned(
            "the holes coincide: rotation and scale are not determined (measure holes apart)"
                .into(),
        )
    })?;
    let v = propagate(&sim.s.theta, &sim.s.cov, similarity_values, &[]);
    let similarity = Similarity {
        offset_x_um: param("offset_x_um", v[0]),
        offset_y_um: param("offset_y_um", v[1]),
        rotation_urad: param("rotation_urad", v[2]),
        rotation_deg: param("rotation_deg", v[3]),
        scale: param("scale", v[4]),
        scale_ppm: param("scale_ppm", v[5]),
        residual: sim.residual(features),
    };

    // (b)
    let aff_terms = [Term::Similarity, Term::Quadrupole];
    let affine = match fit(&aff_terms, features, r, &y) {
        Err(_) => {
            undetermined.push(
                "anisotropic scale/shear (quadrupole; scale per axis and squareness): the holes \
                 are collinear — measure holes off the line"
                    .into(),
            );
            None
        }
        Ok(m) if m.s.dof == 0 => {
            undetermined.push(format!(
                "anisotropic scale/shear: {n} holes leave no residual to give it a σ (measure \
                 at least 4)"
            ));
            None
        }
        Ok(m) => {
            let v = propagate(&m.s.theta, &m.s.cov, |t| affine_values(t, 4), &[7]);
            let q = param("quadrupole_ppm", v[6]);
            let angle = if q.value > 2.0 * q.sigma {
                Some(param("quadrupole_angle_deg", v[7]))
            } else {
                notes.push(format!(
                    "the quadrupole's magnitude ({:.2} ± {:.2} ppm) is below 2σ: its angle is \
                     not determined",
                    q.value, q.sigma
                ));
                None
            };
            Some(Affine {
                offset_x_um: param("offset_x_um", v[0]),
                offset_y_um: param("offset_y_um", v[1]),
                rotation_urad: param("rotation_urad", v[2]),
                rotation_deg: param("rotation_deg", v[3]),
                scale: param("scale", v[4]),
                scale_ppm: param("scale_ppm", v[5]),
                quadrupole_ppm: q,
                quadrupole_angle_deg: angle,
                scale_x_ppm: param("scale_x_ppm", v[8]),
                scale_y_ppm: param("scale_y_ppm", v[9]),
                squareness_urad: param("squareness_urad", v[10]),
                x_axis_rotation_urad: param("x_axis_rotation_urad", v[11]),
                residual: m.residual(features),
            })
        }
    };

    // (c)
    let selection = select(features, r, &y, sim, opts, &mut undetermined);
    let first = selection.rounds.iter().find_map(|rd| {
        let k = rd.kept.as_ref()?;
        let c = rd.candidates.iter().find(|c| &c.term == k)?;
        Some((rd.base_cv_um, c))
    });
    let missing_effect = if selection.kept.is_empty() {
        match similarity.residual.cv_rms_um {
            Some(cv) => notes.push(format!(
                "no move lowers the cross-validated residual significantly: the similarity \
                 model leaves {:.2} µm radial RMS (CV {:.2} µm), what the holes' scatter is",
                similarity.residual.rms_radial_um, cv
            )),
            None => notes.push(
                "the cross-validated residual is undetermined: no move was judged".to_string(),
            ),
        }
        None
    } else {
        first.map(|(base_cv, c)| {
            format!(
                "the similarity model leaves {:.1} µm radial RMS; adding {} removes it: CV RMS \
                 {:.2} → {:.2} µm",
                similarity.residual.rms_radial_um,
                c.description,
                base_cv,
                c.cv_rms_um.unwrap_or(base_cv)
            )
        })
    };
    let mut beyond = Vec::new();
    for rd in selection
        .rounds
        .iter()
        .skip_while(|rd| rd.kept.is_none())
        .skip(1)
    {
        if let Some(k) = &rd.kept {
            if let Some(c) = rd.candidates.iter().find(|c| &c.term == k) {
                beyond.push(format!(
                    "then {}: CV RMS {:.2} → {:.2} µm (t {:.1})",
                    c.description,
                    rd.base_cv_um,
                    c.cv_rms_um.unwrap_or(rd.base_cv_um),
                    c.t.unwrap_or(0.0)
                ));
            }
        }
    }

    let original_tool = if opts.original_tool {
        match original_tool(features) {
            Ok(o) => {
                if o.qp_magnitude.is_none() {
                    notes.push(
                        "the original tool's quadrupole is not determined (its fit failed, or \
                         the holes lie on one line through the centre)"
                            .into(),
                    );
                }
                Some(o)
            }
            Err(why) => {
                notes.push(format!("the original tool's fit: {why}"));
                None
            }
        }
    } else {
        None
    };
    Ok(Outcome {
        holes: n,
        radius_mm: r,
        similarity,
        affine,
        selection,
        missing_effect,
        beyond,
        original_tool,
        undetermined,
        notes,
    })
}

/// Forward selection by leave-one-hole-out CV, the quadrupole first.
fn select(
    f: &[Feature],
    r: f64,
    y: &DVector<f64>,
    sim: Fitted,
    opts: &Options,
    undetermined: &mut Vec<String>,
) -> Selection {
    let mut cur = sim;
    let mut rounds = Vec::new();
    let mut kept = Vec::new();
    let mut pool: Vec<Term> = monomials();
    let mut first = true;
    // The quadrupole was judged on the current model and not kept.
    let mut quad_judged = false;
    while let Ok(base_loo) = &cur.loo {
        let base_loo = base_loo.clone();
        let base_cv = rms_of(&base_loo) * 1e3;
        let mut cands: Vec<Term> = Vec::new();
        if !cur.terms.contains(&Term::Quadrupole) && !quad_judged {
            cands.push(Term::Quadrupole);
        }
        if !first {
            cands.extend(pool.iter().copied());
        }
        first = false;
        if cands.is_empty() {
            break;
        }
        let mut out = Vec::new();
        let mut best: Option<(f64, Term, Fitted)> = None;
        for c in cands {
            let mut terms = cur.terms.clone();
            terms.push(c);
            let mut cand = Candidate {
                term: c.id(),
                description: c.describe(),
                cv_rms_um: None,
                t: None,
                significant: false,
                undetermined: None,
            };
            match fit(&terms, f, r, y) {
                Err(col) => {
                    let t = term_of_column(&terms, col);
                    cand.undetermined = Some(if t == c {
                        "the holes do not separate it from the model (collinear or too few \
                         holes)"
                            .into()
                    } else {
                        format!("it makes {} undetermined", t.describe())
                    });
                }
                Ok(m) if m.s.dof < 2 => {
                    cand.undetermined = Some("too few holes: no residual left".into());
                }
                Ok(m) => match &m.loo {
                    Err(h) => {
                        cand.undetermined = Some(format!("hole {} alone determines it", f[*h].id));
                    }
                    Ok(l) => {
                        let cv = rms_of(l) * 1e3;
                        let t = paired_t(&base_loo, l);
                        cand.cv_rms_um = Some(cv);
                        cand.t = t;
                        cand.significant = cv < base_cv && t.is_some_and(|t| t >= opts.t_min);
                        if cand.significant && best.as_ref().is_none_or(|b| cv < b.0) {
                            best = Some((cv, c, m));
                        }
                    }
                },
            }
            out.push(cand);
        }
        let kept_now = best.as_ref().map(|b| b.1.id());
        rounds.push(Round {
            base: model_name(&cur.terms),
            base_cv_um: base_cv,
            candidates: out,
            kept: kept_now,
        });
        match best {
            Some((_, t, m)) => {
                kept.push(t.id());
                pool.retain(|p| *p != t);
                cur = m;
                quad_judged = false;
            }
            // The quadrupole not kept: the polynomials next, on the similarity.
            None if rounds.len() == 1 => quad_judged = true,
            None => break,
        }
    }
    if cur.loo.is_err() {
        undetermined.push(
            "the cross-validated residual: a hole alone determines a parameter of the \
             similarity (too few holes)"
                .into(),
        );
    }
    let quad = quad_params(&cur);
    let mut terms = Vec::new();
    let mut c = 0;
    for t in &cur.terms {
        if let Term::Mono { .. } = t {
            terms.push(Param {
                name: format!("{}_um", t.id()),
                value: cur.s.theta[c] * 1e3,
                sigma: cur.s.cov[(c, c)].max(0.0).sqrt() * 1e3,
            });
        }
        c += t.columns();
    }
    Selection {
        rounds,
        kept,
        model: model_name(&cur.terms),
        residual: cur.residual(f),
        terms,
        quadrupole_ppm: quad.as_ref().map(|q| q.0.clone()),
        quadrupole_angle_deg: quad.and_then(|q| q.1),
    }
}

#[cfg(test)]
mod tests;
