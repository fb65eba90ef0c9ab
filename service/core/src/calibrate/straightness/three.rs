//! The sequential three-probe method with pitch ([`three_probe`]): second differences, the
//! probes' offsets' parabola separated by a reversal.

use super::shared::*;
use super::*;

/// Sequential three-probe separation with pitch (probes A, B, C at 0, l, 2l; pitch about B),
/// optionally with a reversal run (the straightedge turned over about its length, the same
/// stations) that removes the parabola of the probes' offsets.
pub fn three_probe(
    mount: &ProbeMount,
    stations: &[StationReading],
    reversal: Option<&[StationReading]>,
) -> Result<Separation, ProcedureError> {
    let l = spacing(mount)?;
    let main = flatten("measurement", stations, 3, THREE_PROBE)?;
    check_steps("measurement", &main.xs, l)?;
    let n = main.xs.len();
    let rev = match reversal {
        None => None,
        Some(r) => {
            let rv = flatten("reversal", r, 3, THREE_PROBE)?;
            if rv.xs.len() != n {
                return Err(ProcedureError::Missing(format!(
                    "the reversal has {} stations, the measurement {n}: the reversal must \
                     repeat every station of the measurement (the straightedge turned over \
                     about its length, the carriage at the same positions)",
                    rv.xs.len()
                )));
            }
            for (k, (a, b)) in main.xs.iter().zip(&rv.xs).enumerate() {
                if (a - b).abs() > STEP_TOLERANCE * l {
                    return Err(ProcedureError::IllConditioned(format!(
                        "reversal station {k} is at x = {b:.4} mm, the measurement's at \
                         {a:.4} mm: the reversal must repeat the measurement's stations \
                         (within {:.4} mm)",
                        STEP_TOLERANCE * l
                    )));
                }
            }
            Some(rv)
        }
    };
    let model = ThreeProbe::new(n, l, &main.u, rev.as_ref().map(|r| r.u.as_slice()));
    let mut values = main.values.clone();
    let mut u = main.u.clone();
    if let Some(r) = &rev {
        values.extend_from_slice(&r.values);
        u.extend_from_slice(&r.u);
    }
    let lay = Layout {
        part_pos: (0..n + 2).map(|i| main.xs[0] + i as f64 * l).collect(),
        stations: main.xs.clone(),
    };
    let (estimate, delta) = model.solve(&values);
    let mut notes = vec![
        "guide: the carriage's lateral motion at probe B (the pitch centre), listed at the \
         carriage positions x_K (probe A's); part positions x_0 + i·l, i = 0 … N+1"
            .to_string(),
        "pitch about its mean: a constant pitch is a tilt of the straightedge, or a slope \
         (o_C − o_A)/(2l) of the probes' zero offsets"
            .to_string(),
    ];
    let mut params = vec![];
    let (scale, chi2) = match &rev {
        None => {
            let span = (n + 1) as f64;
            notes.push(format!(
                "the probes' zero offsets are taken as zero: a second difference \
                 δ = o_A − 2o_B + o_C left in them adds δ/(2l²)·(x − x_0)² to part and guide \
                 alike, and δ/l²·(x − x_0) to the pitch (0.1 µm of δ is a bow of {:.3} µm \
                 peak-to-valley over this travel) — \
                 add a reversal measurement to separate it",
                0.1 * span * span / 8.0
            ));
            (1.0, None)
        }
        Some(_) => {
            let (chi2, dof, sigma) = model.reversal_fit(&values, delta);
            let red = chi2 / dof as f64;
            let scale = red.max(1.0);
            params.push(Param {
                name: "probe_offsets.second_difference_mm".into(),
                value: delta,
                sigma: sigma * scale.sqrt(),
            });
            notes.push(format!(
                "reversal: the probes' offsets' second difference δ = o_A − 2o_B + o_C = \
                 {:.5} ± {:.5} µm, removed (reduced χ² {red:.2} over {dof} degrees of freedom)",
                delta * 1e3,
                sigma * scale.sqrt() * 1e3
            ));
            (scale, Some(red))
        }
    };
    let mut unit = vec![0.0; values.len()];
    let (est, sig) = propagate(&lay, estimate, &u, scale, |r| {
        unit[r] = 1.0;
        let out = model.solve(&unit).0;
        unit[r] = 0.0;
        out
    });
    let mut cannot = vec!["line", "pitch_constant"];
    if rev.is_none() {
        cannot.push("parabola");
    }
    let method = if rev.is_some() {
        format!("{THREE_PROBE}, with reversal")
    } else {
        THREE_PROBE.to_string()
    };
    output(method, lay, est, sig, &cannot, chi2, params, notes)
}

/// The three-probe recursion with its fixed weights.
struct ThreeProbe {
    n: usize,
    l: f64,
    /// Main run's reading weights 1/u², station-major.
    w: Vec<f64>,
    /// Variance of each second difference, main run.
    v: Vec<f64>,
    /// Same, reversal run.
    v_rev: Option<Vec<f64>>,
}

fn second_difference_variances(u: &[f64]) -> Vec<f64> {
    u.chunks(3)
        .map(|c| c[0] * c[0] + 4.0 * c[1] * c[1] + c[2] * c[2])
        .collect()
}

fn second_differences(m: &[f64]) -> Vec<f64> {
    m.chunks(3).map(|c| c[0] - 2.0 * c[1] + c[2]).collect()
}

impl ThreeProbe {
    fn new(n: usize, l: f64, u: &[f64], u_rev: Option<&[f64]>) -> Self {
        ThreeProbe {
            n,
            l,
            w: u.iter().map(|v| 1.0 / (v * v)).collect(),
            v: second_difference_variances(u),
            v_rev: u_rev.map(second_difference_variances),
        }
    }

    /// The offsets' second difference from both runs (0 without a reversal).
    fn delta(&self, d: &[f64], dr: &[f64], vr: &[f64]) -> f64 {
        let (mut num, mut den) = (0.0, 0.0);
        for k in 0..self.n {
            let vv = self.v[k] + vr[k];
            num += (d[k] + dr[k]) / vv;
            den += 1.0 / vv;
        }
        num / (2.0 * den)
    }

    /// χ², degrees of freedom and σ of δ̂ of the reversal's redundancy.
    fn reversal_fit(&self, m: &[f64], delta: f64) -> (f64, usize, f64) {
        let vr = self.v_rev.as_ref().expect("reversal");
        let d = second_differences(&m[..3 * self.n]);
        let dr = second_differences(&m[3 * self.n..]);
        let (mut chi2, mut den) = (0.0, 0.0);
        for k in 0..self.n {
            let vv = self.v[k] + vr[k];
            chi2 += (d[k] + dr[k] - 2.0 * delta).powi(2) / vv;
            den += 1.0 / vv;
        }
        (chi2, self.n - 1, (1.0 / (4.0 * den)).sqrt())
    }

    /// Part (N+2 points), guide and pitch before the line comes out, and δ̂.
    fn solve(&self, m: &[f64]) -> (Raw, f64) {
        let n = self.n;
        let d = second_differences(&m[..3 * n]);
        let (s, delta) = match &self.v_rev {
            None => (d, 0.0),
            Some(vr) => {
                let dr = second_differences(&m[3 * n..]);
                let delta = self.delta(&d, &dr, vr);
                let s = (0..n)
                    .map(|k| {
                        let (a, b) = (1.0 / self.v[k], 1.0 / vr[k]);
                        ((d[k] - delta) * a - (dr[k] - delta) * b) / (a + b)
                    })
                    .collect();
                (s, delta)
            }
        };
        let mut y = vec![0.0; n + 2];
        for k in 0..n {
            y[k + 2] = 2.0 * y[k + 1] - y[k] + s[k];
        }
        let offsets = [0.0, -delta / 2.0, 0.0];
        let mut guide = Vec::with_capacity(n);
        let mut pitch = Vec::with_capacity(n);
        for k in 0..n {
            // m_j − Y_{K+j} − ô_j = −X − θ·(j − 1)·l, weighted least squares in (X, θ).
            let (mut s00, mut s01, mut s11, mut b0, mut b1) = (0.0, 0.0, 0.0, 0.0, 0.0);
            for j in 0..3 {
                let w = self.w[3 * k + j];
                let a = (j as f64 - 1.0) * self.l;
                let r = m[3 * k + j] - y[k + j] - offsets[j];
                s00 += w;
                s01 += w * a;
                s11 += w * a * a;
                b0 -= w * r;
                b1 -= w * a * r;
            }
            let det = s00 * s11 - s01 * s01;
            guide.push((s11 * b0 - s01 * b1) / det);
            pitch.push((s00 * b1 - s01 * b0) / det);
        }
        (
            Raw {
                part: y,
                guide,
                pitch: Some(pitch),
            },
            delta,
        )
    }
}
