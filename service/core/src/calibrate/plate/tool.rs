//! The original tool's fit reproduced ([`original_tool`]): similarity and quadrupole by
//! MINPACK's `lmdif`, as scipy's `leastsq` ran it.

use super::*;

// ---------------------------------------------------------------------------------------
// The original tool

/// Holes whose measured diameter exceeds this are the large (MaNGA) ones, mm.
pub const LARGE_HOLE_MM: f64 = 3.0;
/// The nominal diameter the original tool gives the large holes, mm.
pub const LARGE_NOMINAL_MM: f64 = 3.28;

pub(super) fn tool_sim(c: &[f64], p: [f64; 2]) -> [f64; 2] {
    // numpy's order: offset + (p·Mᵀ), M = [[c3, −c2], [c2, c3]].
    [
        c[0] + (p[0] * c[3] + p[1] * -c[2]),
        c[1] + (p[0] * c[2] + p[1] * c[3]),
    ]
}

pub(super) fn tool_quad(c: &[f64], p: [f64; 2]) -> [f64; 2] {
    let r2 = p[0] * p[0] + p[1] * p[1];
    let k = if r2 > 0.0 {
        1.0 + c[0] * 1e-3 * (2.0 * (p[1].atan2(p[0]) - c[1])).cos()
    } else {
        1.0
    };
    [p[0] * k, p[1] * k]
}

pub(super) fn rms_opt(v: impl Iterator<Item = f64>) -> Option<f64> {
    let (mut s, mut k) = (0.0, 0usize);
    for x in v {
        s += x * x;
        k += 1;
    }
    (k > 0).then(|| (s / k as f64).sqrt())
}

/// The original tool's fit (see the module's documentation).
pub fn original_tool(f: &[Feature]) -> Result<OriginalTool, String> {
    if f.len() < 4 {
        return Err(format!(
            "{} holes: its fit needs at least 4 (lmdif: no fewer functions than parameters)",
            f.len()
        ));
    }
    let meas: Vec<[f64; 2]> = f.iter().map(|h| h.measured_mm).collect();
    let nom: Vec<[f64; 2]> = f.iter().map(|h| h.nominal_mm).collect();
    let mut c = vec![0.0, 0.0, 0.0, 1.0];
    let (info, nfev) = minpack::lmdif(
        |x, fv| {
            for (k, (m, n)) in meas.iter().zip(&nom).enumerate() {
                let p = tool_sim(x, *n);
                fv[k] = (m[0] - p[0]).powi(2) + (m[1] - p[1]).powi(2);
            }
        },
        f.len(),
        &mut c,
        1000,
    );
    if !(1..=4).contains(&info) {
        return Err(format!("its similarity fit failed (lmdif info {info})"));
    }
    let fitp: Vec<[f64; 2]> = nom.iter().map(|n| tool_sim(&c, *n)).collect();
    let mut q = vec![0.01, 0.0];
    let (qinfo, qnfev) = minpack::lmdif(
        |x, fv| {
            for (k, (m, p)) in meas.iter().zip(&fitp).enumerate() {
                let g = tool_quad(x, *p);
                fv[k] = (m[0] - g[0]).powi(2) + (m[1] - g[1]).powi(2);
            }
        },
        f.len(),
        &mut q,
        5000,
    );
    // Its quadrupole is linear in (q·cos 2φ, q·sin 2φ): undetermined where the holes do not
    // separate those two (all at one polar angle modulo 90°), or lie on one line (where no
    // anisotropic term is determined).
    let qcols = DMatrix::from_fn(2 * f.len(), 2, |row, col| {
        let p = nom[row / 2];
        let a = 2.0 * p[1].atan2(p[0]);
        p[row % 2] * if col == 0 { a.cos() } else { a.sin() }
    });
    let zeros = DVector::zeros(2 * f.len());
    let determined = solve(&qcols, &zeros).is_ok()
        && solve(
            &design(&[Term::Similarity, Term::Quadrupole], f, 1.0),
            &zeros,
        )
        .is_ok();
    let qok = (1..=4).contains(&qinfo) && determined;
    if qok {
        // Magnitude positive, angle wrapped into [−π/2, π/2] (the tool's normalisation).
        if q[0] < 0.0 {
            q[0] = -q[0];
            q[1] += std::f64::consts::FRAC_PI_2;
        }
        let mut a = q[1].rem_euclid(2.0 * std::f64::consts::PI);
        if a > std::f64::consts::PI {
            a -= std::f64::consts::PI;
        }
        if a > std::f64::consts::FRAC_PI_2 {
            a -= std::f64::consts::PI;
        }
        q[1] = a;
    }
    let large: Vec<bool> = f
        .iter()
        .map(|h| h.measured_d_mm.is_some_and(|d| d > LARGE_HOLE_MM))
        .collect();
    let mut holes = Vec::with_capacity(f.len());
    for (k, h) in f.iter().enumerate() {
        let e = [meas[k][0] - fitp[k][0], meas[k][1] - fitp[k][1]];
        let g = if qok { tool_quad(&q, fitp[k]) } else { fitp[k] };
        let eq = [meas[k][0] - g[0], meas[k][1] - g[1]];
        holes.push(ToolHole {
            id: h.id.clone(),
            resid_x_mm: e[0],
            resid_y_mm: e[1],
            resid_rad_mm: e[0].hypot(e[1]),
            qp_resid_x_mm: eq[0],
            qp_resid_y_mm: eq[1],
            qp_resid_rad_mm: eq[0].hypot(eq[1]),
        });
    }
    let dia_err = |k: usize| -> Option<f64> {
        let md = f[k].measured_d_mm?;
        let nd = if large[k] {
            LARGE_NOMINAL_MM
        } else {
            f[k].nominal_d_mm?
        };
        Some(md - nd)
    };
    let dia: Vec<Option<f64>> = (0..f.len()).map(dia_err).collect();
    Ok(OriginalTool {
        fit_offset_mm: [c[0], c[1]],
        fit_scale: c[2].hypot(c[3]),
        fit_rot_angle_deg: c[2].atan2(c[3]).to_degrees(),
        qp_magnitude: qok.then(|| q[0] * 1e-3),
        qp_angle_deg: qok.then(|| q[1].to_degrees()),
        resid_rad_err_rms_mm: rms_opt(
            holes
                .iter()
                .zip(&large)
                .filter(|(_, l)| !**l)
                .map(|(h, _)| h.resid_rad_mm),
        ),
        large_resid_rad_err_rms_mm: rms_opt(
            holes
                .iter()
                .zip(&large)
                .filter(|(_, l)| **l)
                .map(|(h, _)| h.resid_rad_mm),
        ),
        dia_err_rms_mm: rms_opt(
            dia.iter()
                .zip(&large)
                .filter(|(_, l)| !**l)
                .filter_map(|(d, _)| *d),
        ),
        large_dia_err_rms_mm: rms_opt(
            dia.iter()
                .zip(&large)
                .filter(|(_, l)| **l)
                .filter_map(|(d, _)| *d),
        ),
        max_dia_err_mm: dia.iter().flatten().copied().reduce(f64::max),
        qp_resid_rad_err_rms_mm: if qok {
            rms_opt(holes.iter().map(|h| h.qp_resid_rad_mm))
        } else {
            None
        },
        all_resid_rad_err_rms_mm: rms_opt(holes.iter().map(|h| h.resid_rad_mm)).unwrap_or(0.0),
        large_holes: large.iter().filter(|l| **l).count(),
        lmdif: [(nfev, info), (qnfev, qinfo)],
        holes,
    })
}
