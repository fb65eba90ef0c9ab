//! P's term quadratic in X (P = P0 + P1·ξx + P2·ξx², the ring-gauge patent's example error):
//! whether the rings' positions determine it and whether the data ask for it (BIC on the
//! lag-corrected χ²; the equations are in [`super`]'s doc).

use super::{Param, MIN_SPREAD, P2_COLS};
use crate::lab::fit::{Normal, Solved};
use serde::Serialize;

/// P's term quadratic in X (P = P0 + P1·ξx + P2·ξx²): whether the data determine it and ask
/// for it.
#[derive(Debug, Clone, Serialize)]
pub struct Quadratic {
    /// `selected` (fitted and stored), `not significant` (fitted, below BIC's threshold: the
    /// linear P is stored) or `not determined` (the rings' X positions cannot separate it).
    pub decision: String,
    /// What the term takes out of the residual, χ² (lag-corrected; 0 when not determined).
    pub delta_chi2: f64,
    /// BIC's threshold q·ln(n_eff) in χ² (q its entries, n_eff the points over the lag
    /// correction).
    pub bic_threshold_chi2: f64,
    /// Why, and what would determine it.
    pub reason: String,
    /// P2's entries from the fit with the term, ± σ (in JSON under `quadratic.params` and
    /// `quadratic.uncertainty`, by the truth's names).
    #[serde(skip)]
    pub params: Vec<Param>,
    /// (column, value, σ) of each determined entry.
    #[serde(skip)]
    pub(super) cols: Vec<(usize, f64, f64)>,
}

impl Quadratic {
    /// A note for the engineer when the term is not stored.
    pub(super) fn say(&self) -> String {
        let vals: Vec<String> = self
            .params
            .iter()
            .map(|p| {
                format!(
                    "{} {:+.3} ± {:.3}",
                    p.name.trim_start_matches("dynamics."),
                    p.value * 1e6,
                    p.sigma * 1e6
                )
            })
            .collect();
        if vals.is_empty() {
            format!("P's term quadratic in X {}: {}", self.decision, self.reason)
        } else {
            format!(
                "P's term quadratic in X {}: {} ({} µm per m/s²)",
                self.decision,
                self.reason,
                vals.join(", ")
            )
        }
    }
}

/// Decides P's ξx² term on the joint fit `sol` of `all`: the term is kept when BIC asks for it
/// (Δχ² > q·ln(n_eff), χ² on the full fit's lag-corrected residual variance); otherwise the fit
/// without it is returned. Entries dropped as narrow (the rings' X positions cannot separate ξx²
/// from ξx) leave it not determined.
pub(super) fn quadratic_test(
    all: &Normal,
    sol: Solved,
    inflate: f64,
    narrow: &[usize],
) -> (Solved, Quadratic) {
    let n = all.n as f64;
    let cols: Vec<usize> = P2_COLS
        .filter(|c| all.m[(*c, *c)] > 0.0 && !sol.unidentifiable.contains(c))
        .collect();
    let mut q = Quadratic {
        decision: "not determined".into(),
        delta_chi2: 0.0,
        bic_threshold_chi2: 0.0,
        reason: String::new(),
        params: vec![],
        cols: vec![],
    };
    if cols.is_empty() {
        q.reason = if narrow.iter().any(|c| P2_COLS.contains(c)) {
            format!(
                "the rings' X positions cannot tell ξx² from a line in ξx (what is left of ξx² \
                after a line spreads by less than {MIN_SPREAD}): set the ring up at ≥ 3 \
                positions along X spread over most of the travel — both ends and the middle \
                (ξx² = (x/500 mm)² then bends away from the line by ≥ 0.05)"
            )
        } else {
            "no ring accelerates where P's ξx² term acts".into()
        };
        let mut red = all.clone();
        for c in P2_COLS {
            red.m.row_mut(c).fill(0.0);
            red.m.column_mut(c).fill(0.0);
            red.b[c] = 0.0;
        }
        return (red.solve(), q);
    }
    let mut red = all.clone();
    for &c in &cols {
        red.m.row_mut(c).fill(0.0);
        red.m.column_mut(c).fill(0.0);
        red.b[c] = 0.0;
    }
    let rsol = red.solve();
    let k = sol.rank.max(1) as f64;
    let s2 = sol.ss / (n - k).max(1.0) * inflate;
    let chi = ((rsol.ss - sol.ss) / s2).max(0.0);
    let n_eff = (n / inflate).max(2.0);
    let threshold = cols.len() as f64 * n_eff.ln();
    q.delta_chi2 = if chi.is_finite() { chi } else { 0.0 };
    q.bic_threshold_chi2 = threshold;
    q.cols = cols
        .iter()
        .map(|&c| {
            let sd = (sol.cov[(c, c)] * s2).max(0.0).sqrt();
            (c, sol.x[c], if sd.is_finite() { sd } else { 0.0 })
        })
        .collect();
    if q.delta_chi2 > threshold {
        q.decision = "selected".into();
        q.reason = format!(
            "Δχ² {:.1} above BIC's {:.1} for its {} entries: stored (position order 2, the ξx² \
                monomial)",
            q.delta_chi2,
            threshold,
            cols.len()
        );
        (sol, q)
    } else {
        q.decision = "not significant".into();
        q.reason = format!(
            "Δχ² {:.1} below BIC's {:.1} for its {} entries: the linear P is stored; the values \
                fitted with it",
            q.delta_chi2,
            threshold,
            cols.len()
        );
        (rsol, q)
    }
}
