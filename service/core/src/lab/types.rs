//! The lab's shared types: the dataset prepared for fitting ([`Prepared`], made by
//! [`prepare`]), a fit's outcome ([`FitOutcome`]) and its parameters ([`Param`]), and a change
//! to the model ([`Move`], [`Candidate`]). Used by `analysis`, `select`, `structure`,
//! `discover` and `plan`; it depends on none of them.

use super::dataset::Dataset;
use super::fit::{fit_artifacts, nuisance_row, ArtifactFit, Normal};
use super::LabError;
use crate::effects::EffectConfig;
use crate::sample::Vec3;
use serde::Serialize;

/// The dataset prepared for fitting: artifact fit, masks, baseline figures.
#[derive(Debug, Clone)]
pub struct Prepared {
    /// Artifact fit on all points.
    pub art: ArtifactFit,
    /// Points used for fitting.
    pub fit_mask: Vec<bool>,
    /// Held-out points.
    pub held_mask: Vec<bool>,
    /// Residual RMS on the fit set after refitting placements, µm.
    pub rms_fit_um: f64,
    /// Same on the held-out set (its own placements), µm.
    pub rms_held_um: f64,
    /// Lag-1 autocorrelation of the residuals (for the effective number of points).
    pub rho: f64,
}

pub(crate) fn nuisance_ss(
    ds: &Dataset,
    art: &ArtifactFit,
    y: &[f64],
    mask: &[bool],
) -> (f64, usize) {
    let mut ne = Normal::new(art.n_cols);
    let mut row = vec![];
    for (i, p) in ds.points.iter().enumerate() {
        if mask[i] && art.features[p.feature].is_some() {
            nuisance_row(art, p, &p.surface, &mut row);
            ne.add(&[], &row, y[i]);
        }
    }
    let n = ne.n;
    if n == 0 {
        return (0.0, 0);
    }
    (ne.solve().ss, n)
}

pub(crate) fn rms_um(ss: f64, n: usize) -> f64 {
    if n == 0 {
        0.0
    } else {
        (ss / n as f64).sqrt() * 1e3
    }
}

/// Fits the artifacts and the baseline.
pub fn prepare(ds: &Dataset) -> Result<Prepared, LabError> {
    let surfaces: Vec<Vec3> = ds.points.iter().map(|p| p.surface).collect();
    let all = vec![true; ds.points.len()];
    let art = fit_artifacts(ds, &surfaces, &all);
    if art.features.iter().all(|f| f.is_none()) {
        return Err(LabError::Data(
            "no artifact could be fitted: a circle needs at least 3 points around its circumference, a face 3 points along it".into(),
        ));
    }
    let fit_mask: Vec<bool> = ds
        .points
        .iter()
        .map(|p| !p.held_out && art.features[p.feature].is_some())
        .collect();
    let held_mask: Vec<bool> = ds
        .points
        .iter()
        .map(|p| p.held_out && art.features[p.feature].is_some())
        .collect();
    if fit_mask.iter().filter(|m| **m).count() < 50 {
        return Err(LabError::Data("too few points to fit (fewer than 50 scan points in contact): scan the artifact longer".into()));
    }
    let (ssf, nf) = nuisance_ss(ds, &art, &art.residual, &fit_mask);
    let (ssh, nh) = nuisance_ss(ds, &art, &art.residual, &held_mask);
    let mut num = 0.0;
    let mut den = 0.0;
    for i in 1..ds.points.len() {
        if ds.points[i].segment == ds.points[i - 1].segment
            && ds.points[i].bag == ds.points[i - 1].bag
        {
            num += art.residual[i] * art.residual[i - 1];
            den += art.residual[i] * art.residual[i];
        }
    }
    let rho = if den > 0.0 {
        (num / den).clamp(0.0, 0.99)
    } else {
        0.0
    };
    Ok(Prepared {
        art,
        fit_mask,
        held_mask,
        rms_fit_um: rms_um(ssf, nf),
        rms_held_um: rms_um(ssh, nh),
        rho,
    })
}

/// A fitted parameter.
///
/// `sigma` is honest about what moved the value:
/// σ² = s² + shift² + model², s = max(σ_stat, σ_scan) or the spread where it is above twice
/// that (one draw: see `select::statistical`), with σ_stat from the penalised normal
/// matrix (scaled by the residual, inflated for correlated residuals), σ_scan the same
/// covariance with the residual's scatter taken scan by scan (the cluster-robust "sandwich"
/// (AᵀA)⁻¹ Σ_c s_c s_cᵀ (AᵀA)⁻¹, s_c = A_cᵀ r_c the score of scan c: a model error that
/// differs between scans — speeds, positions, directions — does not average away with the
/// number of points, Liang & Zeger 1986), spread half the difference of the two folds' own
/// fits, shift the change the penalties (ridge, smoothness) make against the
/// least-penalised fit of their ladders — a ridge estimator's covariance omits its bias —
/// and model the largest change of the value among the models the data scores near-equal to
/// this one (a move within the significance threshold: what the choice of model moves; set
/// by [`super::analysis::widen_by_alternatives`]; a near-equal model without the parameter —
/// its effect dropped or swapped for another kind or a variant without that term — counts
/// it as 0, Burnham & Anderson 2002 §4.3); in `lab discover`'s final model, model also
/// carries, in quadrature, the change when each commanded arc is taken from the estimated
/// path instead (the corrector's two descriptions of one arc; set by
/// [`super::analysis::widen_by_arc_source`]). σ_stat from the penalised matrix (A + λP)⁻¹ is
/// the Bayesian σ of a smoothing spline (Wahba 1983), which carries the smoothing's bias on
/// average over the table; the shift carries it where λ was raised above the ladder's least.
/// A parameter the data does not determine has no σ and is listed in `unidentifiable`: a
/// column the normal matrix leaves in its null space, and a table knot no scan sees (its
/// column weaker than 10⁻³ of its table group's strongest: a z straightness under
/// horizontal rings), whose value is the smoothness penalty's alone.
#[derive(Debug, Clone, Serialize)]
pub struct Param {
    /// Name with unit.
    pub name: String,
    /// Value.
    pub value: f64,
    /// Standard uncertainty (see above); absent when not identifiable.
    pub sigma: Option<f64>,
    /// Its statistical part from the normal matrix alone.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sigma_stat: Option<f64>,
    /// |value − least-penalised value| (when a penalty above the ladders' least was used).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub penalty_shift: Option<f64>,
    /// Half the difference of the two folds' fits.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fold_spread: Option<f64>,
    /// The scan-clustered (sandwich) σ: the residual's scatter taken scan by scan.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sigma_scan: Option<f64>,
    /// The largest change among near-equal models (see above).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub model_spread: Option<f64>,
    /// What determines it, when not the data alone: a penalty, only its correlation with
    /// other parameters, or nothing (not determined).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
}

/// The fitted parameters of one effect.
#[derive(Debug, Clone, Serialize)]
pub struct EffectParams {
    /// The effect's id.
    pub effect: String,
    /// Its parameters, in the effect's order.
    pub params: Vec<Param>,
}

/// The outcome of fitting some effects' parameters jointly with the artifact placements.
#[derive(Debug, Clone, Serialize)]
pub struct FitOutcome {
    /// Fitted configs (parameters = current + fitted change).
    #[serde(skip)]
    pub configs: Vec<EffectConfig>,
    /// Parameters of each config.
    pub params: Vec<Vec<Param>>,
    /// Parameters this data cannot determine (given the minimum-norm value).
    pub unidentifiable: Vec<String>,
    /// Number of fitted parameters.
    pub k: usize,
    /// RMS on the fit set before and after, µm.
    pub rms_before_um: f64,
    /// After.
    pub rms_after_um: f64,
    /// RMS on held-out data before and after (placements refitted there), µm.
    pub heldout_rms_before_um: f64,
    /// After.
    pub heldout_rms_after_um: f64,
    /// Fraction of the held-out residual's sum of squares explained.
    pub explained: f64,
    /// RMS of the residual component removed on held-out data, µm.
    pub explained_component_um: f64,
    /// Cross-validated RMS (alternate scans predicted from the others) before, µm.
    pub cv_rms_before_um: f64,
    /// After.
    pub cv_rms_after_um: f64,
    /// Change of the Bayesian information criterion on the fit set (negative: better).
    pub delta_bic: f64,
    /// Fitted correction per point (for confounding checks), projected on the normal.
    #[serde(skip)]
    pub predicted: Vec<f64>,
}

impl FitOutcome {
    /// The parameters of each fitted effect, by id.
    pub fn by_effect(&self) -> Vec<EffectParams> {
        self.configs
            .iter()
            .zip(&self.params)
            .map(|(c, p)| EffectParams {
                effect: c.id(),
                params: p.clone(),
            })
            .collect()
    }
}

/// A change to the model: what `lab diagnose` proposes and `lab add` / `lab remove` make.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Move {
    /// Add a library effect (with variant).
    Add,
    /// Replace a model effect (by id) with another variant.
    Swap,
    /// Take a model effect (by id) out.
    Drop,
}

/// A candidate move with the configuration it brings in.
#[derive(Debug, Clone)]
pub struct Candidate {
    /// The move.
    pub action: Move,
    /// The effect brought in (name with variant) or dropped (id).
    pub effect: String,
    /// The model effect replaced or dropped (its id).
    pub replaces: Option<String>,
    /// The configuration brought in (zero parameters); none for a drop.
    pub config: Option<EffectConfig>,
}
