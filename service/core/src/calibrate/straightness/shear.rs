//! One probe on a shear micro-stage ([`shear_stage`]): the two-point form for shears
//! {0, step}, otherwise one least squares on a grid of part nodes.

use super::shared::*;
use super::two::two_probe_core;
use super::*;

/// Single-probe separation on a shear micro-stage: the sequential two-point form when every
/// station has the shears {0, step}, otherwise the least squares on a grid (pitch separated
/// when every station has ≥ 3 distinct shears).
pub fn shear_stage(
    readings: &[ShearReading],
    options: &ShearOptions,
) -> Result<Separation, ProcedureError> {
    for (i, r) in readings.iter().enumerate() {
        let fields = [r.x_mm, r.shear_mm, r.value_mm, r.u_mm];
        if fields.iter().any(|v| !v.is_finite()) {
            return Err(ProcedureError::Missing(format!(
                "shear reading {i} (x = {} mm, shear = {} mm) is not finite (value {}, u {}): \
                 re-measure it or leave it out",
                r.x_mm, r.shear_mm, r.value_mm, r.u_mm
            )));
        }
        if r.u_mm <= 0.0 {
            return Err(ProcedureError::Missing(format!(
                "shear reading {i} (x = {:.4} mm, shear = {:.4} mm) has standard error {} mm: \
                 it must be positive (at least the probe's resolution/√12)",
                r.x_mm, r.shear_mm, r.u_mm
            )));
        }
    }
    let mut order: Vec<usize> = (0..readings.len()).collect();
    order.sort_by(|&a, &b| {
        (readings[a].x_mm, readings[a].shear_mm)
            .partial_cmp(&(readings[b].x_mm, readings[b].shear_mm))
            .unwrap_or(std::cmp::Ordering::Equal)
    });
    // Stations: runs of carriage positions within STATION_TOLERANCE_MM.
    let mut groups: Vec<Vec<usize>> = vec![];
    for &i in &order {
        match groups.last_mut() {
            Some(g) if (readings[i].x_mm - readings[g[0]].x_mm).abs() <= STATION_TOLERANCE_MM => {
                g.push(i)
            }
            _ => groups.push(vec![i]),
        }
    }
    let ns = groups.len();
    if ns < MIN_STATIONS {
        return Err(ProcedureError::Missing(format!(
            "the shear-stage separation needs at least {MIN_STATIONS} carriage stations (the \
             line of part and guide is removed, the guide needs a third), the readings have \
             {ns}: measure more stations along the travel"
        )));
    }
    let xs: Vec<f64> = groups
        .iter()
        .map(|g| g.iter().map(|&i| readings[i].x_mm).sum::<f64>() / g.len() as f64)
        .collect();
    let steps: Vec<f64> = xs.windows(2).map(|w| w[1] - w[0]).collect();
    let step = median(&steps);
    let h = options.grid_mm.unwrap_or(step);
    if !(h.is_finite() && h > 0.0) {
        return Err(ProcedureError::IllConditioned(format!(
            "the grid pitch must be a positive length, got {h} mm: give `grid_mm` or leave it \
             to the station step"
        )));
    }
    let tol = SHEAR_TOLERANCE * h;
    let mut distinct = vec![];
    for (g, x) in groups.iter().zip(&xs) {
        let mut s: Vec<f64> = g.iter().map(|&i| readings[i].shear_mm).collect();
        s.sort_by(f64::total_cmp);
        s.dedup_by(|a, b| (*a - *b).abs() <= tol);
        if s.len() < 2 {
            return Err(ProcedureError::Missing(format!(
                "station x = {x:.4} mm has readings at a single shear ({:.4} mm): the \
                 single-probe method needs at least two shears per station (three to \
                 separate the pitch)",
                s[0]
            )));
        }
        distinct.push(s.len());
    }
    // (a) The sequential two-point form: shears {0, step}, the carriage stepping by it.
    let two_point = groups.iter().all(|g| g.len() == 2)
        && steps
            .iter()
            .all(|s| (s - step).abs() <= SHEAR_TOLERANCE * step)
        && groups.iter().all(|g| {
            let (a, b) = (readings[g[0]].shear_mm, readings[g[1]].shear_mm);
            a.abs() <= SHEAR_TOLERANCE * step && (b - step).abs() <= SHEAR_TOLERANCE * step
        });
    if two_point {
        let flat = Flat {
            xs: xs.clone(),
            values: groups
                .iter()
                .flat_map(|g| g.iter().map(|&i| readings[i].value_mm))
                .collect(),
            u: groups
                .iter()
                .flat_map(|g| g.iter().map(|&i| readings[i].u_mm))
                .collect(),
        };
        let mut sep = two_probe_core(
            step,
            &flat,
            "shear stage, sequential two-point (shear = step)".to_string(),
        )?;
        sep.notes[0] = "guide: the carriage's lateral motion at the probe's zero shear; part \
                        positions x_0 + i·l, i = 0 … N"
            .to_string();
        sep.notes.push(
            "the stage's perpendicular error e adds e·l to every step of the part: a line, \
             removed"
                .to_string(),
        );
        return Ok(sep);
    }
    let pitch = distinct.iter().all(|&d| d >= 3);
    let rows: Vec<(usize, f64, f64, f64)> = groups
        .iter()
        .enumerate()
        .flat_map(|(k, g)| {
            g.iter().map(move |&i| {
                let r = &readings[i];
                (k, r.shear_mm, r.value_mm, r.u_mm)
            })
        })
        .collect();
    shear_least_squares(&xs, &rows, h, pitch)
}

/// The shear stage's least squares: rows are (station, shear, value, u).
fn shear_least_squares(
    xs: &[f64],
    rows: &[(usize, f64, f64, f64)],
    h: f64,
    pitch: bool,
) -> Result<Separation, ProcedureError> {
    let ns = xs.len();
    let x0 = xs[0];
    let pos = |&(k, s, _, _): &(usize, f64, f64, f64)| xs[k] + s;
    let (qmin, qmax) = rows
        .iter()
        .map(pos)
        .fold((f64::MAX, f64::MIN), |a, q| (a.0.min(q), a.1.max(q)));
    // The end nodes: a position up to a quarter pitch beyond them (a shear the stage's own
    // scale error makes a little longer than commanded) is extrapolated from the last
    // interval rather than given a node that only it would touch, by a sliver.
    let lo = ((qmin - x0) / h + END_REACH).floor();
    let hi = ((qmax - x0) / h - END_REACH).ceil();
    let nodes_f = hi - lo + 1.0;
    let unknowns_f = nodes_f + (ns * if pitch { 2 } else { 1 }) as f64;
    if !(3.0..=MAX_UNKNOWNS as f64).contains(&nodes_f) || unknowns_f > MAX_UNKNOWNS as f64 {
        return Err(ProcedureError::IllConditioned(format!(
            "a grid of pitch {h} mm over the probe positions {qmin:.3} … {qmax:.3} mm has \
             {nodes_f} nodes and, with {ns} stations, {unknowns_f} unknowns: the dense least \
             squares takes 3 … {MAX_UNKNOWNS} — give a grid pitch near the shears' spacing, or \
             split the travel into overlapping parts"
        )));
    }
    let ny = nodes_f as usize;
    let nodes: Vec<f64> = (0..ny).map(|i| x0 + (lo + i as f64) * h).collect();
    let n = ny + ns + if pitch { ns } else { 0 };
    // Sparse rows of the design matrix; count readings between nodes.
    let mut between = 0usize;
    // Per reading: f·(1 − f) of its place in its interval, and its distance to a node, mm.
    let mut interp: Vec<(f64, f64)> = Vec::with_capacity(rows.len());
    let design: Vec<Vec<(usize, f64)>> = rows
        .iter()
        .map(|row| {
            let (k, s, _, _) = *row;
            let t = (pos(row) - nodes[0]) / h;
            let i0 = (t.floor().max(0.0) as usize).min(ny - 2);
            let f = t - i0 as f64;
            let mut e = vec![];
            if f.abs() > 1e-9 && (f - 1.0).abs() > 1e-9 {
                between += 1;
            }
            let fc = f.clamp(0.0, 1.0);
            interp.push((fc * (1.0 - fc), fc.min(1.0 - fc) * h));
            if (1.0 - f).abs() > 1e-12 {
                e.push((i0, 1.0 - f));
            }
            if f.abs() > 1e-12 {
                e.push((i0 + 1, f));
            }
            e.push((ny + k, -1.0));
            if pitch {
                e.push((ny + ns + k, -s));
            }
            e
        })
        .collect();
    let w: Vec<f64> = rows.iter().map(|r| 1.0 / (r.3 * r.3)).collect();
    let mut nm = DMatrix::<f64>::zeros(n, n);
    let mut atwm = vec![0.0; n];
    for ((e, wr), row) in design.iter().zip(&w).zip(rows) {
        for &(i, ci) in e {
            atwm[i] += wr * ci * row.2;
            for &(j, cj) in e {
                nm[(i, j)] += wr * ci * cj;
            }
        }
    }
    // The null space the model always has (the line), orthonormalised, penalised alone.
    let xc = xs.iter().sum::<f64>() / ns as f64;
    let mut gauge = vec![{
        let mut v = vec![0.0; n];
        v[..ny + ns].iter_mut().for_each(|a| *a = 1.0);
        v
    }];
    if pitch {
        let mut v = vec![0.0; n];
        for (i, p) in nodes.iter().enumerate() {
            v[i] = p - xc;
        }
        for (k, x) in xs.iter().enumerate() {
            v[ny + k] = x - xc;
            v[ny + ns + k] = 1.0;
        }
        gauge.push(v);
    }
    let mut basis: Vec<Vec<f64>> = vec![];
    for mut v in gauge {
        for b in &basis {
            let d: f64 = v.iter().zip(b).map(|(a, c)| a * c).sum();
            v.iter_mut().zip(b).for_each(|(a, c)| *a -= d * c);
        }
        let norm = v.iter().map(|a| a * a).sum::<f64>().sqrt();
        v.iter_mut().for_each(|a| *a /= norm);
        basis.push(v);
    }
    let lambda = nm.trace() / n as f64;
    let mut m = nm;
    for b in &basis {
        for i in 0..n {
            if b[i] == 0.0 {
                continue;
            }
            for j in 0..n {
                m[(i, j)] += lambda * b[i] * b[j];
            }
        }
    }
    let d: Vec<f64> = (0..n).map(|i| m[(i, i)].sqrt().max(1e-300)).collect();
    let scaled = DMatrix::from_fn(n, n, |i, j| m[(i, j)] / (d[i] * d[j]));
    let eig = scaled.symmetric_eigen();
    let top = eig.eigenvalues.iter().fold(0.0_f64, |a, &e| a.max(e));
    let weak: Vec<usize> = (0..n)
        .filter(|&i| eig.eigenvalues[i].is_nan() || eig.eigenvalues[i] <= EIGEN_FLOOR * top)
        .collect();
    if !weak.is_empty() {
        let i = weak
            .iter()
            .copied()
            .min_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]))
            .unwrap_or(weak[0]);
        let z = eig.eigenvectors.column(i);
        let (mut worst, mut at) = (0.0, nodes[0]);
        for (k, p) in nodes.iter().enumerate() {
            let v = (z[k] / d[k]).abs();
            if v > worst {
                worst = v;
                at = *p;
            }
        }
        let unequal = if pitch {
            start_values_hint(rows, xs, h)
        } else {
            String::new()
        };
        return Err(ProcedureError::IllConditioned(format!(
            "the shear readings leave {} pattern(s) of the part and guide undetermined (the \
             largest near x = {at:.3} mm): each station's shears ({}) must, with the {:.3} mm \
             step between stations, see every grid node (pitch {h:.3} mm) from more than one \
             station — add a shear per station{}, or step the carriage by less{unequal}",
            weak.len(),
            shear_list(rows, 0),
            xs[1] - xs[0],
            if pitch {
                ""
            } else {
                " (three or more shears also separate the pitch)"
            }
        )));
    }
    let mut q = eig.eigenvectors.clone();
    for (j, mut col) in q.column_iter_mut().enumerate() {
        col /= eig.eigenvalues[j];
    }
    let sinv = q * eig.eigenvectors.transpose();
    let minv = DMatrix::from_fn(n, n, |i, j| sinv[(i, j)] / (d[i] * d[j]));
    let sol: Vec<f64> = (0..n)
        .map(|i| (0..n).map(|j| minv[(i, j)] * atwm[j]).sum())
        .collect();
    let mut chi2 = 0.0;
    for ((e, wr), row) in design.iter().zip(&w).zip(rows) {
        let fit: f64 = e.iter().map(|&(i, c)| c * sol[i]).sum();
        chi2 += wr * (row.2 - fit).powi(2);
    }
    let rank = n - basis.len();
    let chi2_red = (rows.len() > rank).then(|| chi2 / (rows.len() - rank) as f64);
    let scale = chi2_red.unwrap_or(1.0).max(1.0);
    let split = |v: Vec<f64>| Raw {
        part: v[..ny].to_vec(),
        guide: v[ny..ny + ns].to_vec(),
        pitch: pitch.then(|| v[ny + ns..].to_vec()),
    };
    let lay = Layout {
        part_pos: nodes.clone(),
        stations: xs.to_vec(),
    };
    let u: Vec<f64> = rows.iter().map(|r| r.3).collect();
    let (est, sig) = propagate(&lay, split(sol), &u, scale, |r| {
        let mut col = vec![0.0; n];
        for &(i, c) in &design[r] {
            let f = w[r] * c;
            col.iter_mut()
                .enumerate()
                .for_each(|(a, v)| *v += f * minv[(a, i)]);
        }
        split(col)
    });
    // Interpolation between nodes: f·(1 − f)·h²/2·Y'' at most, Y'' from the fitted part.
    let curv = est
        .part
        .windows(3)
        .map(|w| (w[0] - 2.0 * w[1] + w[2]).abs())
        .fold(0.0, f64::max);
    let (fmax, dmax) = interp
        .iter()
        .fold((0.0_f64, 0.0_f64), |a, &(f, d)| (a.0.max(f), a.1.max(d)));
    let interp_bound = fmax / 2.0 * curv;
    let part_u = sig.part.iter().map(|v| v * v).sum::<f64>() / ny as f64;
    let mut notes = vec![
        "guide: the carriage's lateral motion at the probe's zero shear, listed at the \
         carriage positions x_K"
            .to_string(),
        if between == 0 {
            format!(
                "part on a grid of pitch {h:.4} mm, {:.3} … {:.3} mm; every one of the {} \
                 readings is on a node: the reconstruction is exact (nothing interpolated)",
                nodes[0],
                nodes[ny - 1],
                rows.len()
            )
        } else {
            format!(
                "part on a grid of pitch {h:.4} mm, {:.3} … {:.3} mm; {between} of {} readings \
                 fall between nodes (by up to {dmax:.4} mm: the stage's real shears, not the \
                 commanded ones) and use linear interpolation of the part there: an error of \
                 at most f·(1 − f)·h²/2·|Y''| = {:.5} µm (|Y''| the fitted part's largest, \
                 noise included), against the part's σ of {:.4} µm RMS",
                nodes[0],
                nodes[ny - 1],
                rows.len(),
                interp_bound * 1e3,
                part_u.sqrt() * 1e3
            )
        },
    ];
    // A curved stage path: readings c·s², c for 10 nm of sagitta over the shears.
    let (smin, smax) = rows
        .iter()
        .fold((f64::MAX, f64::MIN), |a, r| (a.0.min(r.1), a.1.max(r.1)));
    let span = smax - smin;
    let mut path_pv = (0.0, 0.0);
    if span > 0.0 {
        let c = 4.0 * PATH_SAGITTA_MM / (span * span);
        let mut atwv = vec![0.0; n];
        for ((e, wr), row) in design.iter().zip(&w).zip(rows) {
            for &(i, ci) in e {
                atwv[i] += wr * ci * c * row.1 * row.1;
            }
        }
        let resp: Vec<f64> = (0..n)
            .map(|i| (0..n).map(|j| minv[(i, j)] * atwv[j]).sum())
            .collect();
        let r = split(resp).finish(&lay);
        path_pv = (peak_to_valley(&r.part), peak_to_valley(&r.guide));
    }
    let path_seen = path_pv.0.max(path_pv.1) > 1e-3 * PATH_SAGITTA_MM;
    if pitch && path_seen {
        notes.push(format!(
            "the stage's path is taken as straight: a path bent by c·s² (its sagitta over the \
             shears {smin:.1} … {smax:.1} mm) adds c·s² to every reading, which no reading \
             tells from the part and guide bent by c·x² (and the pitch by 2c·x) — 0.01 µm of \
             sagitta is {:.3} µm peak-to-valley on the part and {:.3} µm on the guide over \
             this travel; calibrate the stage's path on an optical flat, or measure the \
             straightedge turned over",
            path_pv.0 * 1e3,
            path_pv.1 * 1e3
        ));
    } else if path_seen {
        notes.push(format!(
            "the stage's path is taken as straight: a path bent by c·s² over the shears \
             {smin:.1} … {smax:.1} mm is partly seen by the redundant readings (reduced χ²), \
             the rest bends the profiles — 0.01 µm of sagitta moves the part by {:.3} µm and \
             the guide by {:.3} µm peak-to-valley",
            path_pv.0 * 1e3,
            path_pv.1 * 1e3
        ));
    }
    if pitch {
        notes.push(
            "pitch separated about its mean: per station the readings give the slope \
             θ_K − e (e the stage's perpendicular error, a reading error e·s); e and a \
             constant pitch are one constant slope, taken out with the line"
                .to_string(),
        );
    } else {
        notes.push(
            "fewer than three shears at some station: the pitch is not separated; a station's \
             pitch adds −θ_K·s to its reading at shear s, so its variation enters part and \
             guide (a constant pitch and the stage's perpendicular error go out with the \
             line)"
                .to_string(),
        );
    }
    if let Some(c) = chi2_red {
        if c > 1.0 {
            notes.push(format!(
                "reduced χ² {c:.2}: the readings scatter more than their standard errors (or \
                 the part is not linear between nodes); uncertainties scaled by √χ²"
            ));
        }
    }
    let cannot: &[&str] = match (pitch, path_seen) {
        (true, true) => &["line", "pitch_constant", "parabola"],
        (true, false) => &["line", "pitch_constant"],
        (false, _) => &["line", "pitch"],
    };
    let method = format!(
        "shear stage, least squares {} ({})",
        if between == 0 {
            "on the grid nodes"
        } else {
            "with interpolation between grid nodes"
        },
        if pitch { "with pitch" } else { "no pitch" }
    );
    output(method, lay, est, sig, cannot, chi2_red, vec![], notes)
}

/// The sagitta of a curved stage path whose effect the output states, mm.
const PATH_SAGITTA_MM: f64 = 1e-5;

/// Peak-to-valley of a profile, mm.
fn peak_to_valley(v: &[f64]) -> f64 {
    v.iter().copied().fold(f64::MIN, f64::max) - v.iter().copied().fold(f64::MAX, f64::min)
}

/// With the pitch: which start station would fix the patterns the stations' shears leave
/// (two unequal shears, the module doc), for the message.
fn start_values_hint(rows: &[(usize, f64, f64, f64)], xs: &[f64], h: f64) -> String {
    let (smin, smax) = rows
        .iter()
        .fold((f64::MAX, f64::MIN), |a, r| (a.0.min(r.1), a.1.max(r.1)));
    let q = ((smax - smin) / h).round();
    if !(q > 2.0 && q <= 200.0) {
        return String::new();
    }
    let nodes: Vec<String> = (0..=q as usize)
        .map(|i| format!("{:.3}", smin + i as f64 * h))
        .collect();
    format!(
        "; with unequal shears spanning {q} grid steps each station gives one equation of a \
         recursion that needs {q} start values, the line two of them: read one station (the \
         first, x = {:.3} mm) also at every grid node of the shears, {} mm — the exact \
         reconstruction",
        xs[0],
        nodes.join(", ")
    )
}

/// The distinct shears of one station, for messages.
fn shear_list(rows: &[(usize, f64, f64, f64)], station: usize) -> String {
    let mut s: Vec<f64> = rows
        .iter()
        .filter(|r| r.0 == station)
        .map(|r| r.1)
        .collect();
    s.sort_by(f64::total_cmp);
    s.dedup_by(|a, b| (*a - *b).abs() < 1e-6);
    s.iter()
        .map(|v| format!("{v:.3}"))
        .collect::<Vec<_>>()
        .join(", ")
        + " mm"
}
