//! The sequential three-probe method with pitch ([`three_probe`]): second differences, the
//! probes' offsets' parabola separated by a reversal, or — without one — estimated by least
//! squares from what the user states of the straightedge and the zeroing
//! ([`three_probe_with`]).
//!
//! Without a reversal. The probes' zero points lie on two lines, A–B and B–C, at an angle
//! β = (o_C − o_B)/l − (o_B − o_A)/l = δ/l to each other (the probe-spacing angle: the
//! kink of the zero line). The recursion's start values are Y_0, Y_1 (the line) and β: the
//! part it gives with β = 0, Y°, is the true part plus δ·i(i − 1)/2 at part point i, so the
//! least-squares parabola of Y° (coefficient q° of i², unweighted over i = 0 … N+1) is the
//! part's own, q, plus δ/2. The readings cannot tell q from δ/2 (a parabola common to part
//! and guide, its slope in the pitch, is the offsets' pattern); what the user knows can:
//!
//! * the straightedge's bow: its sag about its chord over the measured span is at most B
//!   (certificate or grade), read as a uniform prior on ±B: q = 0 ± σ_q,
//!   σ_q = (B/√3) / ((N+1)/2)², i.e. δ = 2q° ± σ_b, σ_b = 2σ_q;
//! * optionally, the zeroing: each offset within ±Z of zero (uniform), o_A − 2o_B + o_C =
//!   0 ± σ_z, σ_z = √6·Z/√3 = √2·Z.
//!
//! The least-squares start value is their weighted mean, δ̂ = w·2q°, w = σ_z²/(σ_z² + σ_b²)
//! (w = 1 without Z), linear in the readings; its σ² = σ_p² + σ_n², σ_p⁻² = σ_b⁻² + σ_z⁻²
//! (the priors) and σ_n the readings' noise through 2wq°. Every output then follows with
//! s_K = d_K − δ̂ and ô = (0, −δ̂/2, 0), as with a reversal, and its σ² adds
//! (∂out/∂δ)²·σ_p² to the propagated noise (∂out/∂δ after its line comes out). What is left
//! is the straightedge's true parabola, moved onto the guide with its sign changed: within
//! the stated σ when B bounds it.

use super::shared::*;
use super::*;

/// What a user states of a three-probe setup without a reversal: the bounds that fix the
/// probes' offsets' parabola by least squares (module doc). Both `None`: the parabola is
/// reported as unseen.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct ThreeProbeOptions {
    /// Bound B on the straightedge's sag about its chord over the measured span, mm (its
    /// certificate or grade; uniform on ±B).
    pub straightedge_bow_mm: Option<f64>,
    /// Bound Z on each probe's zero offset after zeroing, mm (uniform on ±Z); used only with
    /// `straightedge_bow_mm`.
    pub probe_zero_mm: Option<f64>,
}

/// Sequential three-probe separation with pitch (probes A, B, C at 0, l, 2l; pitch about B),
/// optionally with a reversal run (the straightedge turned over about its length, the same
/// stations) that removes the parabola of the probes' offsets.
pub fn three_probe(
    mount: &ProbeMount,
    stations: &[StationReading],
    reversal: Option<&[StationReading]>,
) -> Result<Separation, ProcedureError> {
    three_probe_with(mount, stations, reversal, &ThreeProbeOptions::default())
}

/// [`three_probe`], and without a reversal the offsets' parabola estimated by least squares
/// from the stated bounds (`opts`; module doc), with its σ in every output's.
pub fn three_probe_with(
    mount: &ProbeMount,
    stations: &[StationReading],
    reversal: Option<&[StationReading]>,
    opts: &ThreeProbeOptions,
) -> Result<Separation, ProcedureError> {
    let l = spacing(mount)?;
    for (what, v) in [
        ("the straightedge's bow bound", opts.straightedge_bow_mm),
        ("the probes' zero-offset bound", opts.probe_zero_mm),
    ] {
        if let Some(v) = v {
            if !(v.is_finite() && v > 0.0) {
                let got = if v.is_finite() {
                    format!("{v} mm")
                } else {
                    "a value that is not a finite number".into()
                };
                return Err(ProcedureError::IllConditioned(format!(
                    "{what} must be a positive length, got {got}"
                )));
            }
        }
    }
    if opts.probe_zero_mm.is_some() && opts.straightedge_bow_mm.is_none() {
        return Err(ProcedureError::Missing(
            "a bound on the probes' zero offsets alone does not fix the parabola better than \
             taking them as zero: give the straightedge's bow bound too"
                .into(),
        ));
    }
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
    let mut model = ThreeProbe::new(n, l, &main.u, rev.as_ref().map(|r| r.u.as_slice()));
    if rev.is_some() && opts.straightedge_bow_mm.is_some() {
        return Err(ProcedureError::IllConditioned(
            "a reversal separates the probes' offsets itself: give either the reversal or the \
             straightedge's bow bound, not both"
                .into(),
        ));
    }
    if let Some(b) = opts.straightedge_bow_mm {
        let half = (n + 1) as f64 / 2.0;
        let sb = 2.0 * b / 3f64.sqrt() / (half * half);
        let (w, sp) = match opts.probe_zero_mm {
            None => (1.0, sb),
            Some(z) => {
                let sz = 2f64.sqrt() * z;
                (
                    sz * sz / (sz * sz + sb * sb),
                    1.0 / (1.0 / (sb * sb) + 1.0 / (sz * sz)).sqrt(),
                )
            }
        };
        model.prior = Some(Prior { w, sigma: sp });
    }
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
        None if model.prior.is_some() => {
            let p = model.prior.expect("prior");
            // δ̂'s noise: its response to each reading.
            let mut unit = vec![0.0; values.len()];
            let mut var = 0.0;
            for (r, ur) in u.iter().enumerate() {
                unit[r] = 1.0;
                var += (model.solve(&unit).1 * ur).powi(2);
                unit[r] = 0.0;
            }
            let sigma = (var + p.sigma * p.sigma).sqrt();
            params.push(Param {
                name: "probe_offsets.second_difference_mm".into(),
                value: delta,
                sigma,
            });
            params.push(Param {
                name: "probe_offsets.beta_rad".into(),
                value: delta / l,
                sigma: sigma / l,
            });
            notes.push(format!(
                "no reversal: the probes' offsets' second difference δ = o_A − 2o_B + o_C \
                 (β = δ/l, the angle between their zero lines) estimated by least squares \
                 from the straightedge's stated bow{}: δ = {:.5} ± {:.5} µm (± {:.5} µm of it \
                 from the stated bounds), removed; the straightedge's own parabola \
                 is left on the guide with its sign changed, within the σ when the bound \
                 holds",
                if opts.probe_zero_mm.is_some() {
                    " and the zeroing's bound"
                } else {
                    ""
                },
                delta * 1e3,
                sigma * 1e3,
                p.sigma * 1e3
            ));
            (1.0, None)
        }
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
    let (est, mut sig) = propagate(&lay, estimate, &u, scale, |r| {
        unit[r] = 1.0;
        let out = model.solve(&unit).0;
        unit[r] = 0.0;
        out
    });
    if let Some(p) = model.prior {
        // The stated bounds' share: every output's response to δ, its line removed.
        let zeros = vec![0.0; values.len()];
        let dd = model.fixed(&zeros, 1.0).finish(&lay);
        let add = |s: &mut [f64], g: &[f64]| {
            s.iter_mut()
                .zip(g)
                .for_each(|(s, g)| *s = s.hypot(g * p.sigma));
        };
        add(&mut sig.part, &dd.part);
        add(&mut sig.guide, &dd.guide);
        if let (Some(s), Some(g)) = (&mut sig.pitch, &dd.pitch) {
            add(s, g);
        }
    }
    let mut cannot = vec!["line", "pitch_constant"];
    if rev.is_none() && model.prior.is_none() {
        cannot.push("parabola");
    }
    let method = if rev.is_some() {
        format!("{THREE_PROBE}, with reversal")
    } else if model.prior.is_some() {
        format!("{THREE_PROBE}, offsets' parabola from the straightedge's stated bow")
    } else {
        THREE_PROBE.to_string()
    };
    output(method, lay, est, sig, &cannot, chi2, params, notes)
}

/// The stated bounds' least squares (module doc): δ̂ = w·2q°, σ_p.
#[derive(Clone, Copy)]
struct Prior {
    w: f64,
    sigma: f64,
}

/// The three-probe recursion with its fixed weights.
struct ThreeProbe {
    /// Without a reversal: the offsets' second difference from the stated bounds.
    prior: Option<Prior>,
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
            prior: None,
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
            None => match self.prior {
                None => (d, 0.0),
                Some(p) => {
                    // Y° (β = 0), its least-squares parabola q°, δ̂ = w·2q°.
                    let delta = p.w * 2.0 * parabola(&recurse(&d));
                    (d.iter().map(|v| v - delta).collect(), delta)
                }
            },
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
        (self.profiles(m, &s, delta), delta)
    }

    /// The outputs with δ fixed (its response: `fixed(0, 1)`).
    fn fixed(&self, m: &[f64], delta: f64) -> Raw {
        let s: Vec<f64> = second_differences(&m[..3 * self.n])
            .iter()
            .map(|v| v - delta)
            .collect();
        self.profiles(m, &s, delta)
    }

    /// Part, guide and pitch from the second differences less δ, `s`.
    fn profiles(&self, m: &[f64], s: &[f64], delta: f64) -> Raw {
        let n = self.n;
        let y = recurse(s);
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
        Raw {
            part: y,
            guide,
            pitch: Some(pitch),
        }
    }
}

/// Y_{K+2} = 2Y_{K+1} − Y_K + s_K from Y_0 = Y_1 = 0.
fn recurse(s: &[f64]) -> Vec<f64> {
    let mut y = vec![0.0; s.len() + 2];
    for k in 0..s.len() {
        y[k + 2] = 2.0 * y[k + 1] - y[k] + s[k];
    }
    y
}

/// Coefficient of i² of the unweighted least-squares parabola through (i, y_i), i = 0, 1, ….
fn parabola(y: &[f64]) -> f64 {
    // Orthogonal polynomials on the points: centred i, then the centred i² less its line.
    let n = y.len() as f64;
    let c = (n - 1.0) / 2.0;
    let t: Vec<f64> = (0..y.len()).map(|i| i as f64 - c).collect();
    let t2m = t.iter().map(|t| t * t).sum::<f64>() / n;
    // t² − mean(t²) is already orthogonal to t (symmetric points).
    let (mut num, mut den) = (0.0, 0.0);
    for (t, y) in t.iter().zip(y) {
        let p = t * t - t2m;
        num += p * y;
        den += p * p;
    }
    if den > 0.0 {
        num / den
    } else {
        0.0
    }
}
