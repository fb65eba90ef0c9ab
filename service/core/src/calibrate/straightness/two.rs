//! The sequential two-probe method ([`two_probe`]): no pitch; also the shear stage's form
//! when every station has the shears {0, step}.

use super::shared::*;
use super::*;

/// Sequential two-probe separation (probes A, B at 0, l): no pitch.
pub fn two_probe(
    mount: &ProbeMount,
    stations: &[StationReading],
) -> Result<Separation, ProcedureError> {
    let l = spacing(mount)?;
    let main = flatten("measurement", stations, 2, TWO_PROBE)?;
    check_steps("measurement", &main.xs, l)?;
    two_probe_core(l, &main, TWO_PROBE.to_string())
}

fn two_probe_raw(m: &[f64], n: usize) -> Raw {
    let mut y = vec![0.0; n + 1];
    let mut x = vec![0.0; n];
    for k in 0..n {
        y[k + 1] = y[k] + m[2 * k + 1] - m[2 * k];
        x[k] = y[k] - m[2 * k];
    }
    Raw {
        part: y,
        guide: x,
        pitch: None,
    }
}

pub(super) fn two_probe_core(
    l: f64,
    main: &Flat,
    method: String,
) -> Result<Separation, ProcedureError> {
    let n = main.xs.len();
    let lay = Layout {
        part_pos: (0..=n).map(|i| main.xs[0] + i as f64 * l).collect(),
        stations: main.xs.clone(),
    };
    let estimate = two_probe_raw(&main.values, n);
    let mut unit = vec![0.0; main.values.len()];
    let (est, sig) = propagate(&lay, estimate, &main.u, 1.0, |r| {
        unit[r] = 1.0;
        let out = two_probe_raw(&unit, n);
        unit[r] = 0.0;
        out
    });
    let notes = vec![
        "guide: the carriage's lateral motion at probe A, listed at the carriage positions \
         x_K; part positions x_0 + i·l, i = 0 … N"
            .to_string(),
        "the pitch is not separated: a station's pitch θ_K adds −θ_K·l to the part's step \
         from x_K to x_K + l, so the part profile carries −l·Σ_{k<i} θ_k and the guide the \
         same at its stations — use three probes, or three shears on the stage, to separate \
         it"
        .to_string(),
        "a difference of the probes' zero offsets adds a constant to every step: a line, \
         removed"
            .to_string(),
    ];
    output(
        method,
        lay,
        est,
        sig,
        &["line", "pitch"],
        None,
        vec![],
        notes,
    )
}
