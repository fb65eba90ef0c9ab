//! The reports' SVG and HTML primitives: escaping, the page, polar plots of traces, bar
//! charts, x–y plots, their scales and colours, and a value with its σ as text.

use scancorr_core::lab::traces::Trace;
use std::fmt::Write;

pub(super) fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

pub(super) fn page(title: &str, body: &str) -> String {
    format!(
        "<!doctype html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>{t}</title><style>\
body{{font-family:system-ui,sans-serif;margin:2em;max-width:1100px;color:#222}}\
h1{{font-size:1.4em}}h2{{font-size:1.15em;margin-top:2em;border-bottom:1px solid #ccc}}\
figure{{display:inline-block;margin:0.5em;vertical-align:top}}figcaption{{font-size:0.85em;color:#555;max-width:420px}}\
table{{border-collapse:collapse;font-size:0.9em}}td,th{{border:1px solid #ddd;padding:3px 8px;text-align:right}}\
td:first-child,th:first-child{{text-align:left}}.fail{{color:#b00;font-weight:bold}}.muted{{color:#777}}\
</style></head><body><h1>{t}</h1>{body}</body></html>",
        t = esc(title)
    )
}

/// The runs of a plot that get a colour each: one per setting and speed (both directions of a
/// run share its hue), ordered by tip, head angles, deflection, then speed.
pub(super) fn colour_keys<'a>(all: &[&'a Trace]) -> Vec<&'a Trace> {
    let mut keys: Vec<&Trace> = vec![];
    for t in all {
        if !keys.iter().any(|k| k.same_setting_and_speed(t)) {
            keys.push(t);
        }
    }
    keys.sort_by(|a, b| {
        (
            a.tip,
            a.head_a1_deg,
            a.head_a2_deg,
            a.deflection_mm,
            a.speed_mm_s,
        )
            .partial_cmp(&(
                b.tip,
                b.head_a1_deg,
                b.head_a2_deg,
                b.deflection_mm,
                b.speed_mm_s,
            ))
            .unwrap_or(std::cmp::Ordering::Equal)
    });
    keys
}

/// The colour of run `k` of `n` in one plot: hues spread from blue (the first, e.g. the
/// slowest) through green and orange to crimson (the last), never the same twice in a plot;
/// counter-clockwise the lighter shade, clockwise the darker one (and drawn dashed).
pub(super) fn run_colour(k: usize, n: usize, ccw: bool) -> String {
    let span = if n <= 1 { 0.0 } else { 260.0 / (n - 1) as f64 };
    let hue = (230.0 - span * k as f64).rem_euclid(360.0);
    // Past ten runs the hues come close: alternate the lightness as well.
    let light = if n > 10 && k % 2 == 1 { 0.56 } else { 0.46 };
    let light = if ccw { light } else { light - 0.18 };
    hsl_hex(hue, 0.78, light)
}

/// `#rrggbb` of a hue (degrees), saturation and lightness (0…1).
pub(super) fn hsl_hex(h: f64, s: f64, l: f64) -> String {
    let c = (1.0 - (2.0 * l - 1.0).abs()) * s;
    let hp = h / 60.0;
    let x = c * (1.0 - (hp.rem_euclid(2.0) - 1.0).abs());
    let (r, g, b) = match hp as u32 {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    let m = l - c / 2.0;
    let q = |v: f64| ((v + m).clamp(0.0, 1.0) * 255.0).round() as u8;
    format!("#{:02x}{:02x}{:02x}", q(r), q(g), q(b))
}

/// A round scale for polar plots: 1, 2 or 5 × 10ᵏ µm per division, so that `maxdev` fits in
/// four divisions.
pub(super) fn um_per_div(maxdev: f64) -> f64 {
    let raw = (maxdev / 4.0).max(0.01);
    let e = 10f64.powf(raw.log10().floor());
    [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .map(|m| m * e)
        .find(|v| *v >= raw * (1.0 - 1e-9))
        .unwrap_or(10.0 * e)
}

pub(super) fn dir_name(d: i32) -> &'static str {
    if d > 0 {
        "CCW"
    } else {
        "CW"
    }
}

/// The scale of a polar plot: µm per division and, for an "after" plot magnified against its
/// "before", the before's µm per division.
#[derive(Debug, Clone, Copy)]
pub(super) struct PolarScale {
    pub upd: f64,
    pub against: Option<f64>,
}

impl PolarScale {
    /// The scale drawn in the plot's corner and stated in its caption.
    fn text(&self) -> String {
        match self.against {
            Some(b) if b > self.upd * 1.0001 => format!(
                "{} µm/div (magnified {}× against the before's {} µm/div)",
                fmt_scale(self.upd),
                fmt_scale(b / self.upd),
                fmt_scale(b)
            ),
            Some(b) => format!("{} µm/div (the before's scale)", fmt_scale(b)),
            None => format!("{} µm/div", fmt_scale(self.upd)),
        }
    }
}

/// Polar plot of one circle feature's traces (one per run: tip, head angles, deflection,
/// direction and speed), as a circular test draws them: the certified circle solid, ±4
/// divisions of `scale` dashed, +X to the right and +Y up, each trace de-centred (its own 1θ
/// taken out) with its circularity in the legend. `keys` fixes the colours (see
/// [`colour_keys`]; the same run, the same colour, in a feature's before and after plots).
pub(super) fn polar(
    title: &str,
    role: &str,
    traces: &[&Trace],
    scale: PolarScale,
    keys: &[&Trace],
) -> String {
    polar_over(title, role, traces, &[], scale, keys)
}

/// [`polar`] with `under` drawn first, faint, in the same colours: a prediction (`traces`)
/// drawn over the measurement (`under`), each legend line giving both circularities.
pub(super) fn polar_over(
    title: &str,
    role: &str,
    traces: &[&Trace],
    under: &[&Trace],
    scale: PolarScale,
    keys: &[&Trace],
) -> String {
    let (w, r0, div) = (400.0, 100.0, 20.0);
    let upd = scale.upd;
    let c = w / 2.0;
    let colour = |t: &Trace| {
        let k = keys
            .iter()
            .position(|x| x.same_setting_and_speed(t))
            .unwrap_or(keys.len());
        run_colour(k, keys.len().max(k + 1), t.direction > 0)
    };
    let mut svg = format!(
        "<svg data-plot=\"polar\" data-role=\"{role}\" data-um-per-div=\"{upd}\"{} xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{w}\" viewBox=\"0 0 {w} {w}\">",
        scale
            .against
            .map(|b| format!(" data-magnification=\"{}\"", fmt_scale(b / upd)))
            .unwrap_or_default()
    );
    let _ = write!(svg, "<line x1=\"8\" x2=\"{}\" y1=\"{c}\" y2=\"{c}\" stroke=\"#e4e4e4\"/><line x1=\"{c}\" x2=\"{c}\" y1=\"8\" y2=\"{}\" stroke=\"#e4e4e4\"/>", w - 8.0, w - 8.0);
    for k in -4i32..=4 {
        let rr = r0 + k as f64 * div;
        let (stroke, dash) = if k == 0 {
            ("#444", "")
        } else {
            ("#ccc", "3 3")
        };
        let _ = write!(svg, "<circle cx=\"{c}\" cy=\"{c}\" r=\"{rr}\" fill=\"none\" stroke=\"{stroke}\" stroke-dasharray=\"{dash}\"/>");
    }
    let _ = write!(
        svg,
        "<text x=\"{}\" y=\"{}\" font-size=\"11\">+X</text><text x=\"{}\" y=\"14\" font-size=\"11\">+Y</text>",
        w - 24.0,
        c - 4.0,
        c + 4.0
    );
    let corner = match scale.against {
        Some(b) if b > upd * 1.0001 => {
            format!("{} µm/div (×{})", fmt_scale(upd), fmt_scale(b / upd))
        }
        _ => format!("{} µm/div", fmt_scale(upd)),
    };
    let _ = write!(
        svg,
        "<text x=\"6\" y=\"14\" font-size=\"11\">{corner}</text><text x=\"6\" y=\"{}\" font-size=\"10\" fill=\"#444\">solid circle: certified Ø</text>",
        w - 6.0
    );
    let layers = under
        .iter()
        .map(|t| (t, true))
        .chain(traces.iter().map(|t| (t, false)));
    for (t, faint) in layers {
        let mut d = String::new();
        for (j, (th, e)) in t.theta_deg.iter().zip(&t.deviation_um).enumerate() {
            let r = (r0 + e / upd * div).clamp(2.0, c - 2.0);
            let th = th.to_radians();
            let _ = write!(
                d,
                "{}{:.1},{:.1} ",
                if j == 0 { "M" } else { "L" },
                c + r * th.cos(),
                c - r * th.sin()
            );
        }
        if t.theta_deg.len() >= 350 {
            d.push('Z');
        }
        let _ = write!(
            svg,
            "<path data-trace=\"{}\" data-layer=\"{}\" data-direction=\"{}\" data-speed-mm-s=\"{}\" data-tip=\"{}\" data-a1-deg=\"{}\" data-a2-deg=\"{}\" data-deflection-mm=\"{}\" data-circularity-um=\"{:.3}\" d=\"{d}\" fill=\"none\" stroke=\"{}\" stroke-width=\"{}\"{}{}/>",
            esc(&t.label()),
            if faint { "measured" } else { role },
            dir_name(t.direction).to_lowercase(),
            t.speed_mm_s,
            t.tip,
            t.head_a1_deg,
            t.head_a2_deg,
            t.deflection_mm,
            t.circularity_um,
            colour(t),
            if faint { "3" } else { "1.4" },
            if faint { " stroke-opacity=\"0.25\"" } else { "" },
            if t.direction < 0 { " stroke-dasharray=\"6 3\"" } else { "" }
        );
    }
    svg += "</svg>";
    let mut legend = String::from("<ul class=\"traces\">");
    for t in traces {
        let was = under
            .iter()
            .find(|u| u.same_run(t))
            .map(|u| format!("measured {:.2} µm → predicted ", u.circularity_um))
            .unwrap_or_default();
        let _ = write!(
            legend,
            "<li><span style=\"color:{}\">{}</span> {}: circularity {was}<b data-circularity-um=\"{:.3}\">{:.2} µm</b></li>",
            colour(t),
            if t.direction < 0 { "╌╌" } else { "━━" },
            esc(&t.label()),
            t.circularity_um,
            t.circularity_um
        );
    }
    legend += "</ul>";
    let what = if under.is_empty() {
        "deviation from the certified circle, one trace per run"
    } else {
        "predicted deviation (bold) drawn over the measured one (faint, same colour), one trace per run"
    };
    format!(
        "<figure>{svg}<figcaption><b>{}</b>: {what}; scale {}. A colour per setting and speed (tip, head angles, deflection, speed), never repeated in the plot; counter-clockwise lighter and solid, clockwise darker and dashed. 1° means, each trace's own centre taken out (the 1θ term is where the circle lies, not its form); circularity = range of the trace.{legend}</figcaption></figure>",
        esc(title),
        scale.text()
    )
}

/// One polar scale (µm per division) for every trace of `all`.
pub(super) fn scale_of(all: &[&Trace]) -> f64 {
    let maxdev = all
        .iter()
        .flat_map(|t| t.deviation_um.iter())
        .fold(0.0f64, |a, e| a.max(e.abs()));
    um_per_div(maxdev)
}

pub(super) fn fmt_scale(v: f64) -> String {
    if v >= 1.0 && (v - v.round()).abs() < 1e-9 * v {
        format!("{v:.0}")
    } else if v >= 1.0 {
        format!("{v:.1}")
    } else {
        // Round values of 1, 2, 5 × 10⁻ᵏ: no float noise (0.30000000000000004).
        let d = (-v.log10().floor()).clamp(0.0, 9.0) as usize;
        format!("{v:.d$}")
    }
}

/// Horizontal bar chart.
pub(super) fn bars(
    kind: &str,
    rows: &[(String, f64, bool)],
    unit: &str,
    reference: Option<(f64, &str)>,
) -> String {
    let h = 22.0 * rows.len() as f64 + 30.0;
    let max = rows
        .iter()
        .map(|r| r.1)
        .chain(reference.map(|r| r.0))
        .fold(1e-9f64, f64::max);
    // The labels' column as wide as the longest label (11 px text, ~6.3 px a character), so a
    // long candidate label (`stylus_thermal:split for …`) is not cut at the left edge.
    let longest = rows.iter().map(|r| r.0.chars().count()).max().unwrap_or(0);
    let (x0, wbar) = ((6.3 * longest as f64 + 12.0).max(230.0), 300.0);
    let width = x0 + wbar + 90.0;
    let mut svg = format!("<svg data-plot=\"{kind}\" xmlns=\"http://www.w3.org/2000/svg\" width=\"{width:.0}\" height=\"{h}\">");
    for (i, (label, v, hot)) in rows.iter().enumerate() {
        let y = 10.0 + 22.0 * i as f64;
        let _ = write!(
            svg,
            "<text x=\"{}\" y=\"{}\" font-size=\"11\" text-anchor=\"end\">{}</text><rect x=\"{x0}\" y=\"{y}\" width=\"{:.1}\" height=\"16\" fill=\"{}\" data-failing=\"{hot}\"/><text x=\"{:.1}\" y=\"{}\" font-size=\"11\">{v:.3} {unit}</text>",
            x0 - 6.0,
            y + 12.0,
            esc(label),
            (v / max * wbar).max(0.5),
            if *hot { "#cc3333" } else { "#6a8fc8" },
            x0 + (v / max * wbar).max(0.5) + 4.0,
            y + 12.0
        );
    }
    if let Some((r, name)) = reference {
        let x = x0 + r / max * wbar;
        let _ = write!(svg, "<line x1=\"{x:.1}\" x2=\"{x:.1}\" y1=\"4\" y2=\"{}\" stroke=\"#393\" stroke-dasharray=\"4 3\"/><text x=\"{:.1}\" y=\"{}\" font-size=\"10\" fill=\"#393\">{}</text>", h - 14.0, x + 3.0, h - 4.0, esc(name));
    }
    svg + "</svg>"
}

/// One series of an x–y chart: label, colour, points, drawn with a line.
pub(super) type Series = (String, &'static str, Vec<(f64, f64)>, bool);

/// An x–y chart with axes, ticks at round values, a zero line and a legend.
pub(super) fn xy(kind: &str, series: &[Series], xlabel: &str, ylabel: &str) -> String {
    let (w, h, l, r, t, b) = (560.0, 320.0, 62.0, 150.0, 14.0, 42.0);
    let pts = series.iter().flat_map(|s| s.2.iter());
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, 0.0f64, 0.0f64);
    for &(x, y) in pts {
        if x.is_finite() && y.is_finite() {
            (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
        }
    }
    if x0 > x1 {
        (x0, x1) = (0.0, 1.0);
    }
    if x1 - x0 < 1e-12 {
        x1 = x0 + 1.0;
    }
    if y1 - y0 < 1e-12 {
        y1 = y0 + 1.0;
    }
    let pad = 0.06 * (y1 - y0);
    let (y0, y1) = (y0 - pad, y1 + pad);
    let px = |x: f64| l + (x - x0) / (x1 - x0) * (w - l - r);
    let py = |y: f64| t + (y1 - y) / (y1 - y0) * (h - t - b);
    let mut svg = format!("<svg data-plot=\"{kind}\" xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" font-size=\"11\">");
    let _ = write!(
        svg,
        "<rect x=\"{l}\" y=\"{t}\" width=\"{}\" height=\"{}\" fill=\"none\" stroke=\"#999\"/>",
        w - l - r,
        h - t - b
    );
    let step = |span: f64| {
        let raw = span / 5.0;
        let m = 10f64.powf(raw.log10().floor());
        [1.0, 2.0, 5.0, 10.0]
            .iter()
            .map(|k| k * m)
            .find(|s| *s >= raw)
            .unwrap_or(m * 10.0)
    };
    let (sx, sy) = (step(x1 - x0), step(y1 - y0));
    let mut v = (x0 / sx).ceil() * sx;
    while v <= x1 + 1e-9 * sx {
        let _ = write!(svg, "<line x1=\"{0:.1}\" x2=\"{0:.1}\" y1=\"{1:.1}\" y2=\"{2:.1}\" stroke=\"#999\"/><text x=\"{0:.1}\" y=\"{3:.1}\" text-anchor=\"middle\">{4}</text>", px(v), h - b, h - b + 4.0, h - b + 16.0, fmt_tick(v, sx));
        v += sx;
    }
    let mut v = (y0 / sy).ceil() * sy;
    while v <= y1 + 1e-9 * sy {
        let _ = write!(svg, "<line x1=\"{0:.1}\" x2=\"{1:.1}\" y1=\"{2:.1}\" y2=\"{2:.1}\" stroke=\"#999\"/><text x=\"{3:.1}\" y=\"{4:.1}\" text-anchor=\"end\">{5}</text>", l - 4.0, l, py(v), l - 6.0, py(v) + 4.0, fmt_tick(v, sy));
        v += sy;
    }
    if y0 < 0.0 && y1 > 0.0 {
        let _ = write!(svg, "<line x1=\"{l}\" x2=\"{0:.1}\" y1=\"{1:.1}\" y2=\"{1:.1}\" stroke=\"#bbb\" stroke-dasharray=\"3 3\"/>", w - r, py(0.0));
    }
    let _ = write!(
        svg,
        "<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"middle\">{}</text>",
        l + 0.5 * (w - l - r),
        h - 8.0,
        esc(xlabel)
    );
    let _ = write!(
        svg,
        "<text transform=\"translate(14,{:.1}) rotate(-90)\" text-anchor=\"middle\">{}</text>",
        t + 0.5 * (h - t - b),
        esc(ylabel)
    );
    for (i, (label, colour, p, line)) in series.iter().enumerate() {
        let pts: Vec<String> = p
            .iter()
            .filter(|(x, y)| x.is_finite() && y.is_finite())
            .map(|(x, y)| format!("{:.1},{:.1}", px(*x), py(*y)))
            .collect();
        if *line && pts.len() > 1 {
            let _ = write!(
                svg,
                "<polyline points=\"{}\" fill=\"none\" stroke=\"{colour}\" stroke-width=\"1.2\"/>",
                pts.join(" ")
            );
        }
        for q in &pts {
            let (x, y) = q.split_once(',').unwrap_or(("0", "0"));
            let _ = write!(
                svg,
                "<circle cx=\"{x}\" cy=\"{y}\" r=\"2.5\" fill=\"{colour}\"/>"
            );
        }
        let ly = t + 12.0 + 14.0 * i as f64;
        let _ = write!(svg, "<rect x=\"{:.1}\" y=\"{:.1}\" width=\"10\" height=\"3\" fill=\"{colour}\"/><text x=\"{:.1}\" y=\"{:.1}\">{}</text>", w - r + 8.0, ly - 4.0, w - r + 22.0, ly, esc(label));
    }
    svg + "</svg>"
}

pub(super) fn fmt_tick(v: f64, step: f64) -> String {
    let d = (-step.log10().floor()).max(0.0) as usize;
    let s = format!("{v:.d$}");
    if s.trim_start_matches('-')
        .chars()
        .all(|c| c == '0' || c == '.')
    {
        "0".into()
    } else {
        s
    }
}

pub(super) const PALETTE: [&str; 8] = [
    "#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#17becf", "#8c564b", "#e377c2",
];

/// A value with its standard uncertainty in engineering form: both to the σ's second
/// significant digit, with a common power of ten outside 10⁻³…10⁴ (`(2.31 ± 0.04)e-6`);
/// without σ, four significant digits.
pub fn value_sigma(v: f64, sigma: Option<f64>) -> String {
    if !v.is_finite() {
        return "—".into();
    }
    let big = sigma
        .filter(|s| s.is_finite() && *s > 0.0)
        .map_or(v.abs(), |s| s.max(v.abs()));
    let e = if big > 0.0 {
        big.log10().floor() as i32
    } else {
        0
    };
    let (scale, suffix) = if (-3..4).contains(&e) {
        (1.0, String::new())
    } else {
        (10f64.powi(e), format!("e{e}"))
    };
    match sigma.filter(|s| s.is_finite() && *s > 0.0) {
        Some(s) => {
            let digits = (1 - (s / scale).log10().floor() as i32).clamp(0, 9) as usize;
            let body = format!("{:.digits$} ± {:.digits$}", v / scale, s / scale);
            if suffix.is_empty() {
                body
            } else {
                format!("({body}){suffix}")
            }
        }
        None if v == 0.0 => "0".into(),
        None => {
            let digits = (3 - (v.abs() / scale).log10().floor() as i32).clamp(0, 9) as usize;
            format!("{:.digits$}{suffix}", v / scale)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::value_sigma;

    #[test]
    fn values_carry_their_uncertainty_to_its_second_digit() {
        assert_eq!(value_sigma(2.3127e-6, Some(4.2e-8)), "(2.313 ± 0.042)e-6");
        assert_eq!(value_sigma(0.01234, Some(0.00051)), "0.01234 ± 0.00051");
        assert_eq!(value_sigma(12.34, Some(1.2)), "12.3 ± 1.2");
        assert_eq!(value_sigma(-1.5e-9, None), "-1.500e-9");
        assert_eq!(value_sigma(0.0, None), "0");
        assert_eq!(value_sigma(f64::NAN, Some(1.0)), "—");
        // A value far below its σ keeps σ's exponent.
        assert_eq!(value_sigma(1e-12, Some(3.0e-7)), "(0.0 ± 3.0)e-7");
    }
}
