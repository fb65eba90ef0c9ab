//! The calibration procedures' reports: dynamics, probe force, tips, straightness, dynamic map.

use super::svg::{bars, esc, page, value_sigma, xy, Series, PALETTE};
use scancorr_core::Calibration;
use std::fmt::Write;

/// `calibrate dynamics --report`: ΔR against V² and acceleration per position before and
/// after, the fitted diagonal compliance along each line of positions, every parameter.
pub fn dynamics(
    start: &Calibration,
    o: &scancorr_core::calibrate::dynamics::Outcome,
    noise_floor_um: f64,
) -> String {
    let mut body = format!(
        "<p>Start: v{} of {}. {} ring positions; residual after each position's static pattern {:.3} → <b>{:.3} µm</b> (noise floor {:.3} µm). Servo gain: <b>{}</b> form (held-out ring positions: theoretical {:.3} µm, polynomial in f {:.3} µm).</p>",
        start.version,
        esc(&start.machine_id),
        o.positions.len(),
        o.residual_before_um,
        o.residual_after_um,
        noise_floor_um,
        esc(&o.gain.chosen),
        o.gain.heldout_theoretical_um,
        o.gain.heldout_polynomial_um
    );
    // ΔR against acceleration: one series per position (mean of both directions per speed)
    // while every position has a colour of its own; beyond the palette, every position's
    // points in one colour and their mean per speed as the line (the table below the ΔR
    // along X and Y has each position's slope).
    let mean_by_speed = |p: &scancorr_core::calibrate::dynamics::Position, after: bool| {
        let mut by: std::collections::BTreeMap<i64, (f64, f64, usize)> = Default::default();
        for s in &p.scans {
            let e = by.entry((s.accel_mm_s2 * 10.0).round() as i64).or_default();
            e.0 = s.accel_mm_s2;
            e.1 += if after {
                s.delta_r_after_um
            } else {
                s.delta_r_um
            };
            e.2 += 1;
        }
        by
    };
    let each = o.positions.len() <= PALETTE.len();
    let per_pos = |after: bool| -> Vec<Series> {
        if !each {
            let mut all: std::collections::BTreeMap<i64, (f64, f64, usize)> = Default::default();
            let mut pts = vec![];
            for p in &o.positions {
                for (k, (a, d, n)) in mean_by_speed(p, after) {
                    pts.push((a, d / n as f64));
                    let e = all.entry(k).or_default();
                    e.0 = a;
                    e.1 += d / n as f64;
                    e.2 += 1;
                }
            }
            return vec![
                (
                    format!("each of {} positions", o.positions.len()),
                    PALETTE[0],
                    pts,
                    false,
                ),
                (
                    "mean over positions".into(),
                    PALETTE[1],
                    all.values().map(|(a, d, n)| (*a, d / *n as f64)).collect(),
                    true,
                ),
            ];
        }
        o.positions
            .iter()
            .enumerate()
            .map(|(i, p)| {
                (
                    format!(
                        "({:.0}, {:.0}, {:.0})",
                        p.center_mm[0], p.center_mm[1], p.center_mm[2]
                    ),
                    PALETTE[i],
                    mean_by_speed(p, after)
                        .values()
                        .map(|(a, d, n)| (*a, d / *n as f64))
                        .collect(),
                    true,
                )
            })
            .collect()
    };
    let whose = if each {
        "each position's mean radius change per speed"
    } else {
        "every position's mean radius change per speed (points; more positions than colours) and their mean (line)"
    };
    let _ = write!(
        body,
        "<h2>ΔR against acceleration</h2><figure>{}<figcaption>Before: {whose} against the centripetal acceleration v²/r (v² on the same axis scaled by 1/r), relative to its static pattern. A straight line through zero is compliance and the gain's f² term; curvature the f¹ term.</figcaption></figure><figure>{}<figcaption>After the fit: what is left per position and speed.</figcaption></figure>",
        xy("delta-r-before", &per_pos(false), "acceleration v²/r (mm/s²)", "ΔR (µm)"),
        xy("delta-r-after", &per_pos(true), "acceleration v²/r (mm/s²)", "ΔR (µm)")
    );
    // ΔR along X and along Y per scan, as the patent reports it, and ΔR/a per position.
    let _ = write!(
        body,
        "<h2>ΔR along X and along Y</h2><figure>{}<figcaption>Before the fit: each scan's radius change along X (θ = 0, π) and along Y (θ = ±π/2) against the centripetal acceleration v²/r, every position's scans as points (for a ring standing on its edge, along its plane's first and second axes). Unequal slopes are an unequal compliance along the two axes; each position's slopes are tabled below with σ.</figcaption></figure>",
        xy("delta-r-xy", &delta_r_xy(o), "acceleration v²/r (mm/s²)", "ΔR (µm)")
    );
    body += "<table><tr><th>position (mm)</th><th>plane</th><th>ΔR/a along X (µm per m/s²)</th><th>ΔR/a along Y (µm per m/s²)</th></tr>";
    for p in &o.positions {
        let _ = write!(
            body,
            "<tr><td>({:.0}, {:.0}, {:.0})</td><td>{}</td><td>{}</td><td>{}</td></tr>",
            p.center_mm[0],
            p.center_mm[1],
            p.center_mm[2],
            esc(&p.plane),
            value_sigma(
                p.dr_x_per_accel_um_per_m_s2,
                Some(p.dr_x_per_accel_sigma_um_per_m_s2)
            ),
            value_sigma(
                p.dr_y_per_accel_um_per_m_s2,
                Some(p.dr_y_per_accel_sigma_um_per_m_s2)
            )
        );
    }
    body += "</table>";
    // The fitted compliance's diagonal and cross terms along each line of positions.
    let val = |n: &str| {
        o.params
            .iter()
            .find(|p| p.name == n)
            .map_or(0.0, |p| p.value)
    };
    let base = o.positions.first().map(|p| p.center_mm).unwrap_or([0.0; 3]);
    let mut figs = String::new();
    for (axis, name) in ["x", "y", "z"].iter().enumerate() {
        let mut along: Vec<f64> = o.positions.iter().map(|p| p.center_mm[axis]).collect();
        along.sort_by(f64::total_cmp);
        along.dedup_by(|a, b| (*a - *b).abs() < 1.0);
        if along.len() < 2 {
            continue;
        }
        let series: Vec<Series> = [
            ("xx", PALETTE[0]),
            ("yy", PALETTE[1]),
            ("xy", PALETTE[2]),
            ("yx", PALETTE[3]),
        ]
        .iter()
        .map(|(ij, c)| {
            let pts = along
                .iter()
                .map(|&q| {
                    let mut pos = base;
                    pos[axis] = q;
                    let xi = pos.map(|v| v / 500.0);
                    let p = val(&format!("dynamics.P_{ij}.1"))
                        + xi[0] * val(&format!("dynamics.P_{ij}.x"))
                        + xi[1] * val(&format!("dynamics.P_{ij}.y"))
                        + xi[2] * val(&format!("dynamics.P_{ij}.z"));
                    (q, p * 1e6)
                })
                .collect();
            (format!("P_{ij}"), *c, pts, true)
        })
        .collect();
        let _ = write!(
            figs,
            "<figure>{}<figcaption>The fitted compliance along {} (the other coordinates at the first position's), µm per m/s². P_xx and P_yy include what of the gain's f² term the spin-up could not separate (see below).</figcaption></figure>",
            xy(&format!("p-along-{name}"), &series, &format!("{} (mm)", name.to_uppercase()), "P (µm per m/s²)"),
            name.to_uppercase()
        );
    }
    let _ = write!(body, "<h2>Coefficients against position</h2>{figs}");
    body += "<h2>Parameters</h2><table><tr><th>parameter</th><th>value</th><th>standard uncertainty</th></tr>";
    for p in &o.params {
        let _ = write!(
            body,
            "<tr><td>{}</td><td>{:.6e}</td><td>{:.2e}</td></tr>",
            esc(&p.name),
            p.value,
            p.sigma
        );
    }
    body += "</table><p class=\"muted\">Units: τ in s; P in mm per mm/s², per monomial 1, x, y, z of the position over 500 mm; phase b0 rad, b1 rad/Hz, b2 rad/Hz²; gain f¹ 1/Hz, f² 1/Hz².</p>";
    for c in &o.confounded {
        let _ = write!(body, "<p><b>Barely separated:</b> {}</p>", esc(c));
    }
    for u in &o.undetermined {
        let _ = write!(body, "<p><b>Not determined:</b> {}</p>", esc(u));
    }
    for n in &o.notes {
        let _ = write!(body, "<p class=\"muted\">{}</p>", esc(n));
    }
    page("scancorr calibrate dynamics", &body)
}

/// `calibrate probe-force --report`: each setting's sphere radius against the deflection
/// before and after the force correction (a line to zero force), every parameter.
pub fn probe_force(
    start: &Calibration,
    o: &scancorr_core::calibrate::probe_force::Outcome,
    noise_floor_um: f64,
) -> String {
    let mut body = format!(
        "<p>Start: v{} of {}. {} settings on the master sphere; residual about each circle's static map {:.3} → <b>{:.3} µm</b> (noise floor {:.3} µm); reduced χ² of the circles × deflections {:.2}.</p>",
        start.version,
        esc(&start.machine_id),
        o.settings.len(),
        o.rms_before_um,
        o.rms_after_um,
        noise_floor_um,
        o.cell_chi2
    );
    let series = |after: bool| -> Vec<Series> {
        o.settings
            .iter()
            .enumerate()
            .map(|(i, s)| {
                let r = if after {
                    &s.radius_error_after_um
                } else {
                    &s.radius_error_before_um
                };
                let mut pts: Vec<(f64, f64)> = vec![(0.0, s.radius_error_at_zero_um[0])];
                pts.extend(s.deflections_mm.iter().zip(r).map(|(d, e)| (*d, *e)));
                (
                    format!(
                        "tip {} A1 {:.0}° A2 {:.0}°",
                        s.tip, s.head_deg[0], s.head_deg[1]
                    ),
                    PALETTE[i % PALETTE.len()],
                    pts,
                    true,
                )
            })
            .collect()
    };
    let _ = write!(
        body,
        "<h2>Radius against deflection</h2><figure>{}<figcaption>Before: the sphere's radius less its certified radius per deflection, measured without a force correction; the first point of each line is the fitted value at zero force. The slope is the stylus bending.</figcaption></figure><figure>{}<figcaption>After the fitted force coefficients: flat. The first point, the fitted zero-force value, can differ from the flat line by a few tenths of a µm: the circles' drift with the measured temperatures shares that much with the radius.</figcaption></figure>",
        xy("radius-before", &series(false), "deflection (mm)", "R − R_cert (µm)"),
        xy("radius-after", &series(true), "deflection (mm)", "R − R_cert (µm)")
    );
    body += "<h2>Parameters</h2><table><tr><th>parameter</th><th>unit</th><th>value ± standard uncertainty</th></tr>";
    for p in &o.params {
        // Each value in the unit its name states (the units table of the core).
        let unit = scancorr_core::units::key_unit(&p.name)
            .or_else(|| scancorr_core::units::name_unit(&p.name))
            .unwrap_or("—");
        let _ = write!(
            body,
            "<tr><td>{}</td><td>{}</td><td>{}</td></tr>",
            esc(&p.name),
            esc(unit),
            super::svg::value_sigma(p.value, Some(p.sigma))
        );
    }
    body += "</table>";
    for s in &o.settings {
        let _ = write!(
            body,
            "<p class=\"muted\">tip {} at ({}, {})°: {} points; at zero force R − R_cert = {:+.2} ± {:.2} µm; the static error map's form (harmonics 2 and up, common to every deflection) {:.3} µm RMS; left after the fit {:.3} µm RMS.</p>",
            s.tip, s.head_deg[0], s.head_deg[1], s.points, s.radius_error_at_zero_um[0], s.radius_error_at_zero_um[1], s.static_form_um, s.fit_rms_um
        );
    }
    for u in &o.undetermined {
        let _ = write!(body, "<p><b>Not determined:</b> {}</p>", esc(u));
    }
    for n in &o.notes {
        let _ = write!(body, "<p class=\"muted\">{}</p>", esc(n));
    }
    page("scancorr calibrate probe-force", &body)
}

/// `calibrate tips --report`: each setting's offset from the reference before and what the
/// qualification leaves, the reference's drift in time, every parameter.
pub fn tips(
    start: &Calibration,
    o: &scancorr_core::calibrate::tips::Outcome,
    consistency_after_um: Option<f64>,
    noise_floor_um: f64,
) -> String {
    let mut body = format!(
        "<p>Start: v{} of {}. Reference tip {}; {} settings on the master sphere{}. Tip-to-tip consistency <b>{:.3} µm</b> with the starting calibration, <b>{}</b> with the qualified one (noise floor {:.3} µm); fit residual {:.3} µm.</p>",
        start.version,
        esc(&start.machine_id),
        o.reference_tip,
        o.settings.len(),
        o.reference_temp_c
            .map_or(String::new(), |t| format!(", at {t:.2} °C (range {:.2} K)", o.temp_range_k)),
        o.consistency_before_um,
        consistency_after_um.map_or("—".into(), |a| format!("{a:.3} µm")),
        noise_floor_um,
        o.residual_rms_um
    );
    let others: Vec<_> = o
        .settings
        .iter()
        .filter(|s| s.tip != o.reference_tip)
        .collect();
    // Before and after on one scale, each setting's pair together.
    let norm = |v: [f64; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    let rows: Vec<(String, f64, bool)> = others
        .iter()
        .flat_map(|s| {
            let name = format!(
                "tip {} A1 {:.0}° A2 {:.0}°",
                s.tip, s.head_deg[0], s.head_deg[1]
            );
            [
                (format!("{name} before"), norm(s.offset_um), false),
                (format!("{name} after"), norm(s.residual_um), false),
            ]
        })
        .collect();
    let _ = write!(
        body,
        "<h2>Each setting against the reference</h2><figure>{}<figcaption>|S − S_ref| per setting, µm: before with the starting calibration's styli (catalogue lengths show here), after what the fitted lengths, expansion coefficients and rotation leave; one scale (dashed: 2× the noise floor).</figcaption></figure>",
        bars("tips-offsets", &rows, "µm", Some((2.0 * noise_floor_um, "2× noise floor")))
    );
    // The reference's centre in time: the drift every setting is referred to.
    let refs: Vec<_> = o
        .settings
        .iter()
        .filter(|s| s.tip == o.reference_tip)
        .collect();
    if refs.len() > 1 {
        let c0 = refs[0].center_mm;
        let series: Vec<Series> = ["x", "y", "z"]
            .iter()
            .enumerate()
            .map(|(i, a)| {
                (
                    format!("centre {a}"),
                    PALETTE[i],
                    refs.iter()
                        .map(|s| (s.t_s, (s.center_mm[i] - c0[i]) * 1e3))
                        .collect(),
                    true,
                )
            })
            .collect();
        let _ = write!(
            body,
            "<h2>The reference in time</h2><figure>{}<figcaption>The reference tip's sphere centre against time (µm from its first measurement): the drift (the scales' and the stand's growth as the room warms) that each setting is referred to, interpolated in time.</figcaption></figure>",
            xy("reference-drift", &series, "time (s)", "centre drift (µm)")
        );
    }
    body += "<h2>Settings</h2><table><tr><th>setting</th><th>points</th><th>radius − certified µm</th><th>form µm</th><th>offset µm (x, y, z)</th><th>left µm (x, y, z)</th></tr>";
    for s in &o.settings {
        let _ = write!(
            body,
            "<tr><td>tip {} A1 {:.0}° A2 {:.0}°</td><td>{}</td><td>{:.3}</td><td>{:.3}</td><td>{:.3}, {:.3}, {:.3}</td><td>{:.3}, {:.3}, {:.3}</td></tr>",
            s.tip, s.head_deg[0], s.head_deg[1], s.points, s.radius_error_um, s.rms_um,
            s.offset_um[0], s.offset_um[1], s.offset_um[2],
            s.residual_um[0], s.residual_um[1], s.residual_um[2]
        );
    }
    body += "</table><h2>Parameters</h2><table><tr><th>parameter</th><th>value</th><th>standard uncertainty</th></tr>";
    for p in o.params.iter().chain(&o.rotation) {
        let _ = write!(
            body,
            "<tr><td>{}</td><td>{:.6}</td><td>{:.2e}</td></tr>",
            esc(&p.name),
            p.value,
            p.sigma
        );
    }
    body += "</table><p class=\"muted\">Lengths and radii in mm, expansion coefficients in 1/K, the rotation at the sphere (the last three) in rad.</p>";
    for u in &o.undetermined {
        let _ = write!(body, "<p><b>Not determined:</b> {}</p>", esc(u));
    }
    for n in &o.notes {
        let _ = write!(body, "<p class=\"muted\">{}</p>", esc(n));
    }
    page("scancorr calibrate tips", &body)
}

/// `calibrate straightness --report`: the guide's and the part's straightness with their
/// uncertainty bands (±2σ), the pitch where the method separates it, what it cannot see.
pub fn straightness(
    start: &Calibration,
    o: &scancorr_core::calibrate::separation::Outcome,
    warnings: &[String],
) -> String {
    let s = &o.separation;
    let mut body = format!(
        "<p>Start: v{} of {}. <b>{}</b>: straightness of the {} guide towards {}, {} stations ({:.0}–{:.0} mm), {} readings averaged per probe and station. Straightness is each profile's deviation from its least-squares line; the pitch is about its mean. <b>Cannot see:</b> {}.</p>",
        start.version,
        esc(&start.machine_id),
        esc(&s.method),
        o.axis.name(),
        o.toward.name(),
        s.stations_mm.len(),
        s.stations_mm.first().copied().unwrap_or(0.0),
        s.stations_mm.last().copied().unwrap_or(0.0),
        o.samples_per_reading,
        esc(&s.cannot_see.join(", "))
    );
    let band = |label: &str, colour: &'static str, x: &[f64], v: &[f64], u: &[f64], k: f64| {
        let line = |sign: f64| -> Vec<(f64, f64)> {
            x.iter()
                .zip(v.iter().zip(u))
                .map(|(x, (v, u))| (*x, (v + sign * 2.0 * u) * k))
                .collect()
        };
        vec![
            (
                label.to_string(),
                colour,
                x.iter().zip(v).map(|(x, v)| (*x, v * k)).collect(),
                true,
            ),
            ("+2σ".to_string(), "#bbbbbb", line(1.0), true),
            ("−2σ".to_string(), "#bbbbbb", line(-1.0), true),
        ]
    };
    let _ = write!(
        body,
        "<p data-straightness=\"1\">Straightness, peak-to-valley about the least-squares line (ISO 12780): guide <b data-pv-um=\"guide\">{}</b>, part <b data-pv-um=\"part\">{}</b>.</p>",
        pv_text(&s.stations_mm, &s.guide_straightness_mm),
        pv_text(&s.part_positions_mm, &s.part_straightness_mm)
    );
    let _ = write!(
        body,
        "<h2>Guide</h2><figure>{}<figcaption>The carriage's lateral motion towards {} at the carriage positions the scales read, with ±2σ (the sequential methods integrate: the band widens along the travel).</figcaption></figure>",
        xy(
            "guide",
            &band("guide", PALETTE[0], &s.stations_mm, &s.guide_straightness_mm, &s.guide_straightness_mm_u, 1e3),
            &format!("{} (mm)", o.axis.name()),
            "straightness (µm)"
        ),
        o.toward.name()
    );
    let _ = write!(
        body,
        "<h2>Part (straightedge)</h2><figure>{}<figcaption>The straightedge's own form, with ±2σ.</figcaption></figure>",
        xy(
            "part",
            &band("part", PALETTE[1], &s.part_positions_mm, &s.part_straightness_mm, &s.part_straightness_mm_u, 1e3),
            &format!("{} (mm)", o.axis.name()),
            "straightness (µm)"
        )
    );
    match (&s.pitch_rad, &s.pitch_rad_u) {
        (Some(p), Some(u)) => {
            let _ = write!(
                body,
                "<h2>Pitch</h2><figure>{}<figcaption>The carriage's rotation about the third axis, about its mean, with ±2σ.</figcaption></figure>",
                xy(
                    "pitch",
                    &band("pitch", PALETTE[2], &s.stations_mm, p, u, 1e6),
                    &format!("{} (mm)", o.axis.name()),
                    "pitch (µrad)"
                )
            );
        }
        _ => {
            body += "<p><b>Pitch:</b> not separated by this method.</p>";
        }
    }
    if let Some(f) = o.flatness_mm {
        let series: Vec<Series> = o
            .lines
            .iter()
            .enumerate()
            .map(|(i, l)| {
                (
                    format!("{} = {:.0} mm", "line", l.step_mm),
                    PALETTE[i % PALETTE.len()],
                    l.positions_mm
                        .iter()
                        .zip(&l.height_mm)
                        .map(|(x, h)| (*x, h * 1e3))
                        .collect(),
                    true,
                )
            })
            .collect();
        let _ = write!(
            body,
            "<h2>Flatness</h2><p>{} lines stepped across: <b>{:.3} µm</b> peak-to-valley about the least-squares plane.</p><figure>{}<figcaption>Each line's height about the plane of all of them; the lines are tied by one probe's readings at the same carriage position (the guide cancels), so the stepping axis's own straightness between the lines is in them.</figcaption></figure>",
            o.lines.len(),
            f * 1e3,
            xy("flatness", &series, &format!("{} (mm)", o.axis.name()), "height (µm)")
        );
    }
    for p in &s.params {
        let _ = write!(
            body,
            "<p>{}: {:.6} ± {:.6}</p>",
            esc(&p.name),
            p.value,
            p.sigma
        );
    }
    for n in &s.notes {
        let _ = write!(body, "<p class=\"muted\">{}</p>", esc(n));
    }
    for w in warnings {
        let _ = write!(body, "<p><b>Warning:</b> {}</p>", esc(w));
    }
    page("scancorr calibrate straightness", &body)
}

/// `calibrate dynamic-map --report`: per map the three scans' radial deviations, the two
/// extrapolations to zero deflection, and e2 (the fast scan's error the map removes) with its
/// uncertainty band.
pub fn dynamic_map(
    start: &Calibration,
    o: &scancorr_core::calibrate::dynamic_map::Outcome,
    noise_floor_um: f64,
) -> String {
    let mut body = format!(
        "<p>Start: v{} of {}. {} map(s); noise floor {:.3} µm.</p>",
        start.version,
        esc(&start.machine_id),
        o.maps.len(),
        noise_floor_um
    );
    for m in &o.maps {
        let line = |v: &[f64]| -> Vec<(f64, f64)> {
            m.theta_deg.iter().copied().zip(v.iter().copied()).collect()
        };
        let band = |s: f64| -> Vec<(f64, f64)> {
            m.theta_deg
                .iter()
                .zip(m.e2_um.iter().zip(&m.e2_u_um))
                .map(|(t, (e, u))| (*t, e + s * 2.0 * u))
                .collect()
        };
        let scans: Vec<Series> = vec![
            ("S1 (slow, d1)".into(), PALETTE[0], line(&m.s1_um), true),
            ("F1 (fast, d2)".into(), PALETTE[1], line(&m.f1_um), true),
            ("F2 (fast, d1)".into(), PALETTE[2], line(&m.f2_um), true),
        ];
        let zero: Vec<Series> = vec![
            ("LSZD".into(), PALETTE[0], line(&m.lszd_um), true),
            ("HSZD".into(), PALETTE[2], line(&m.hszd_um), true),
        ];
        let e2: Vec<Series> = vec![
            (
                "e2 = F2 − LSZD".into(),
                PALETTE[3 % PALETTE.len()],
                line(&m.e2_um),
                true,
            ),
            ("e2 + 2σ".into(), "#bbb", band(1.0), true),
            ("e2 − 2σ".into(), "#bbb", band(-1.0), true),
        ];
        let _ = write!(
            body,
            "<h2>{}: {:.0} mm/s (slow {:.0} mm/s), d1 {:.3} mm, d2 {:.3} mm, segments {:?}</h2>\
             <figure>{}<figcaption>Before: the radial deviation of each scan from the slow scan's circle, per bin (positive away from the centre).</figcaption></figure>\
             <figure>{}<figcaption>Extrapolated to zero deflection: at low speed (LSZD, the reference) and at high speed (HSZD).</figcaption></figure>\
             <figure>{}<figcaption>After: e2, what the map removes from a fast scan at d1 (RMS {:.3} µm, its σ {:.3} µm RMS); the dynamic part at zero deflection {:.3} µm RMS, the deflection's e1 {:.3} µm RMS.</figcaption></figure>",
            esc(&m.feature),
            m.speed_mm_s,
            m.slow_speed_mm_s,
            m.d1_mm,
            m.d2_mm,
            m.segments,
            xy("dynamic-map-scans", &scans, "θ (°)", "radial deviation (µm)"),
            xy("dynamic-map-zero", &zero, "θ (°)", "radial deviation (µm)"),
            xy("dynamic-map-e2", &e2, "θ (°)", "e2 (µm)"),
            m.e2_rms_um,
            m.e2_u_rms_um,
            m.dynamic_rms_um,
            m.e1_rms_um
        );
    }
    body += "<h2>Parameters</h2><table><tr><th>parameter</th><th>value (µm, µm/mm)</th><th>standard uncertainty</th></tr>";
    for p in &o.params {
        let _ = write!(
            body,
            "<tr><td>{}</td><td>{:.4}</td><td>{:.4}</td></tr>",
            esc(&p.name),
            p.value * 1e3,
            p.sigma * 1e3
        );
    }
    body += "</table>";
    for s in &o.speed_search {
        let _ = write!(
            body,
            "<h2>Speed search: {} (tolerance {:.3} µm)</h2><table><tr><th>speed (mm/s)</th><th>slow/fast difference, RMS of F2 − S1 (µm)</th><th>σ (µm)</th><th>map</th></tr>",
            esc(&s.feature),
            s.tolerance_um
        );
        for x in &s.steps {
            let _ = write!(
                body,
                "<tr><td>{:.0}</td><td>{:.3}</td><td>{:.3}</td><td>{}</td></tr>",
                x.speed_mm_s,
                x.difference_um,
                x.difference_u_um,
                if x.mapped { "stored" } else { "not needed" }
            );
        }
        let _ = write!(
            body,
            "</table><p>No map needed up to {}.</p>",
            s.fastest_within_mm_s.map_or(
                "— (the slowest fast speed already leaves the tolerance)".into(),
                |v| format!("{v:.0} mm/s")
            )
        );
    }
    for s in &o.skipped {
        let _ = write!(body, "<p><b>Not mapped:</b> {}</p>", esc(s));
    }
    for n in &o.notes {
        let _ = write!(body, "<p class=\"muted\">{}</p>", esc(n));
    }
    page("scancorr calibrate dynamic-map", &body)
}

/// Peak-to-valley of a profile (mm) about its least-squares line, µm; `None` with fewer than
/// three finite points.
pub fn straightness_pv_um(x: &[f64], v: &[f64]) -> Option<f64> {
    let pts: Vec<(f64, f64)> = x
        .iter()
        .zip(v)
        .filter(|(x, v)| x.is_finite() && v.is_finite())
        .map(|(x, v)| (*x, *v))
        .collect();
    if pts.len() < 3 {
        return None;
    }
    let n = pts.len() as f64;
    let (mx, my) = pts
        .iter()
        .fold((0.0, 0.0), |a, p| (a.0 + p.0 / n, a.1 + p.1 / n));
    let sxx: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
    let sxy: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    let b = if sxx > 0.0 { sxy / sxx } else { 0.0 };
    let (lo, hi) = pts.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, p| {
        let r = p.1 - my - b * (p.0 - mx);
        (a.0.min(r), a.1.max(r))
    });
    Some((hi - lo) * 1e3)
}

fn pv_text(x: &[f64], v: &[f64]) -> String {
    straightness_pv_um(x, v).map_or("— (too few points)".into(), |p| format!("{p:.2} µm"))
}

#[cfg(test)]
mod pv_tests {
    #[test]
    fn a_tilted_bow_keeps_its_bow_and_loses_its_tilt() {
        let x: Vec<f64> = (0..=10).map(|i| i as f64 * 100.0).collect();
        // 2 µm of bow (a parabola) on a 5 µm/m tilt, in mm.
        let v: Vec<f64> = x
            .iter()
            .map(|x| 5e-6 * x + 2e-3 * (1.0 - ((x - 500.0) / 500.0).powi(2)))
            .collect();
        let pv = super::straightness_pv_um(&x, &v).unwrap();
        assert!((pv - 2.0).abs() < 1e-6, "{pv}");
        assert!(super::straightness_pv_um(&x[..2], &v[..2]).is_none());
    }
}

/// ΔR along X and along Y per scan against v²/r: one series per direction, every position's
/// scans in it (the table beside gives each position's slope).
fn delta_r_xy(o: &scancorr_core::calibrate::dynamics::Outcome) -> Vec<Series> {
    type Pick = fn(&scancorr_core::calibrate::dynamics::Scan) -> f64;
    let along: [(&str, Pick); 2] = [("X", |s| s.delta_r_x_um), ("Y", |s| s.delta_r_y_um)];
    along
        .iter()
        .enumerate()
        .map(|(k, (axis, pick))| {
            let mut pts: Vec<(f64, f64)> = o
                .positions
                .iter()
                .flat_map(|p| p.scans.iter().map(|s| (s.accel_mm_s2, pick(s))))
                .collect();
            pts.sort_by(|a, b| a.0.total_cmp(&b.0));
            (format!("along {axis}"), PALETTE[k], pts, false)
        })
        .collect()
}
