//! The ridge regression on standardised columns and its forward-chaining cross-validation
//! over blocks of time (folds, the ridge weight chosen, held-out errors).

use super::*;

pub(super) fn block_bounds(n: usize, k: usize) -> Vec<(usize, usize)> {
    (0..k).map(|i| (i * n / k, (i + 1) * n / k)).collect()
}

/// The forward-chaining folds: (fit rows end, validation rows) per fold.
pub(super) fn folds(blocks: &[(usize, usize)]) -> Vec<(usize, (usize, usize))> {
    let k = blocks.len();
    let first = (2 * k).div_ceil(5).max(2);
    (first..=k.saturating_sub(3))
        .map(|m| (blocks[m].0, (blocks[m].0, blocks[m + 2].1)))
        .collect()
}

/// A ridge fit on standardised columns: prediction function data.
pub(super) struct Ridge {
    pub(super) mean: Vec<f64>,
    pub(super) sd: Vec<f64>,
    pub(super) ybar: f64,
    pub(super) b: DVector<f64>,
    pub(super) a_inv: DMatrix<f64>,
    pub(super) ztz: DMatrix<f64>,
}

impl Ridge {
    pub(super) fn fit(
        cols: &[&Vec<f64>],
        y: &[f64],
        rows: (usize, usize),
        lambda: f64,
    ) -> Option<Ridge> {
        let (r0, r1) = rows;
        let n = (r1 - r0) as f64;
        let p = cols.len();
        let mean: Vec<f64> = cols
            .iter()
            .map(|c| c[r0..r1].iter().sum::<f64>() / n)
            .collect();
        let sd: Vec<f64> = cols
            .iter()
            .zip(&mean)
            .map(|(c, m)| {
                let v = c[r0..r1].iter().map(|x| (x - m) * (x - m)).sum::<f64>() / n;
                v.sqrt()
            })
            .collect();
        let ybar = y[r0..r1].iter().sum::<f64>() / n;
        let mut ztz = DMatrix::<f64>::zeros(p, p);
        let mut zty = DVector::<f64>::zeros(p);
        let mut z = vec![0.0; p];
        for r in r0..r1 {
            for j in 0..p {
                z[j] = if sd[j] > 0.0 {
                    (cols[j][r] - mean[j]) / sd[j]
                } else {
                    0.0
                };
            }
            let yr = y[r] - ybar;
            for i in 0..p {
                zty[i] += z[i] * yr;
                for j in i..p {
                    ztz[(i, j)] += z[i] * z[j];
                }
            }
        }
        for i in 0..p {
            for j in 0..i {
                ztz[(i, j)] = ztz[(j, i)];
            }
        }
        let mut a = ztz.clone();
        for i in 0..p {
            // A column without variation gets a unit penalty: it cannot be determined.
            a[(i, i)] += lambda.max(1e-12) * n + if sd[i] > 0.0 { 0.0 } else { 1.0 };
        }
        let a_inv = a.cholesky()?.inverse();
        let b = &a_inv * zty;
        Some(Ridge {
            mean,
            sd,
            ybar,
            b,
            a_inv,
            ztz,
        })
    }

    pub(super) fn predict(&self, cols: &[&Vec<f64>], r: usize) -> f64 {
        let mut v = self.ybar;
        for (j, c) in cols.iter().enumerate() {
            if self.sd[j] > 0.0 {
                v += self.b[j] * (c[r] - self.mean[j]) / self.sd[j];
            }
        }
        v
    }

    /// Coefficient j in the column's own unit.
    pub(super) fn k(&self, j: usize) -> f64 {
        if self.sd[j] > 0.0 {
            self.b[j] / self.sd[j]
        } else {
            0.0
        }
    }
}

/// Cross-validated MAE of the columns at ridge weight λ, and each fold's coefficients.
pub(super) fn cv(
    cols: &[&Vec<f64>],
    y: &[f64],
    fl: &[(usize, (usize, usize))],
    lambda: f64,
) -> Option<(f64, Vec<Vec<f64>>)> {
    let (mut sum, mut count) = (0.0, 0usize);
    let mut ks = vec![];
    for &(end, (v0, v1)) in fl {
        let (mut s, mut c) = (0.0, 0usize);
        if cols.is_empty() {
            let ybar = y[..end].iter().sum::<f64>() / end as f64;
            for r in v0..v1 {
                s += (y[r] - ybar).abs();
                c += 1;
            }
        } else {
            let m = Ridge::fit(cols, y, (0, end), lambda)?;
            for r in v0..v1 {
                s += (y[r] - m.predict(cols, r)).abs();
                c += 1;
            }
            ks.push((0..cols.len()).map(|j| m.k(j)).collect());
        }
        sum += s;
        count += c;
    }
    Some((sum / count.max(1) as f64, ks))
}

/// The best ridge weight for the columns: (cv MAE, λ, the folds' coefficients).
pub(super) fn best_lambda(
    cols: &[&Vec<f64>],
    y: &[f64],
    fl: &[(usize, (usize, usize))],
    lambdas: &[f64],
) -> (f64, f64, Vec<Vec<f64>>) {
    let mut best: Option<(f64, f64, Vec<Vec<f64>>)> = None;
    for &l in lambdas {
        if let Some((e, ks)) = cv(cols, y, fl, l) {
            // Ties (within 0.1 %) go to the larger weight: the simpler model.
            if best.as_ref().is_none_or(|b| e < b.0 * 0.999) {
                best = Some((e, l, ks));
            }
        }
    }
    best.unwrap_or((f64::MAX, lambdas[lambdas.len() - 1], vec![]))
}

pub(super) fn errors(y: &[f64], pred: &[f64], rows: (usize, usize)) -> Errors {
    let (r0, r1) = rows;
    let n = (r1 - r0).max(1) as f64;
    let (mut a, mut s, mut m) = (0.0, 0.0, 0.0f64);
    for r in r0..r1 {
        let e = (y[r] - pred[r]).abs();
        a += e;
        s += e * e;
        m = m.max(e);
    }
    Errors {
        mae_um: a / n,
        rms_um: (s / n).sqrt(),
        max_um: m,
    }
}

pub(super) fn corr(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().max(1) as f64;
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        sab += (x - ma) * (y - mb);
        saa += (x - ma) * (x - ma);
        sbb += (y - mb) * (y - mb);
    }
    if saa > 0.0 && sbb > 0.0 {
        sab / (saa * sbb).sqrt()
    } else {
        0.0
    }
}
