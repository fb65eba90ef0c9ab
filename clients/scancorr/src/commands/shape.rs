//! `scancorr shape fit --kind circle|sphere|line|plane --points FILE|- [--json]`: an
//! orthogonal-distance least-squares fit of a geometric feature to an ASCII point file or
//! standard input (`x y z` rows, or `x y` rows for a profile in the XY plane; whitespace or
//! comma separated, `#` comments, optional point count on the first line). Prints the form
//! too: the peak-to-valley of the residual about the fitted feature (for a circle its
//! roundness, for a plane its flatness, least-squares reference); `--json` adds each point's
//! residual.

use anyhow::{Context, Result};
use clap::Subcommand;
use scancorr_core::shape::{fit_circle, fit_line, fit_plane, fit_sphere, parse_points, ShapeKind};
use scancorr_core::Vec3;
use serde::Serialize;
use std::path::{Path, PathBuf};

#[derive(Subcommand)]
pub enum ShapeCmd {
    /// Orthogonal-distance least-squares fit of points (ASCII x y z rows; a first line with
    /// only the point count is accepted).
    Fit {
        /// circle, sphere, line or plane.
        #[arg(long)]
        kind: String,
        /// The points file (`x y z` or `x y` rows), or `-` for standard input.
        #[arg(long)]
        points: PathBuf,
        /// Print JSON (`center`, `normal`, `diameter`, `rms`).
        #[arg(long)]
        json: bool,
    },
}

/// Runs a `shape` command.
pub fn exec(cmd: ShapeCmd) -> Result<()> {
    match cmd {
        ShapeCmd::Fit { kind, points, json } => run(&kind, &points, json),
    }
}

/// The fit result common to all kinds, as printed.
struct Summary {
    kind: ShapeKind,
    points: usize,
    /// Centre (circle, sphere) or centroid (line, plane), mm.
    center: Vec3,
    /// Circle-plane normal, line direction or plane normal; none for a sphere.
    normal: Option<Vec3>,
    /// Diameter (circle, sphere), mm.
    diameter: Option<f64>,
    rms: f64,
    max_abs_residual: f64,
    /// Peak-to-valley of the residual, mm.
    form: f64,
    /// Each point's residual (as the core's fit defines it), mm, in input order.
    residuals: Vec<f64>,
}

fn peak_to_valley(r: &[f64]) -> f64 {
    let (lo, hi) = r
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| {
            (a.min(*x), b.max(*x))
        });
    if hi >= lo {
        hi - lo
    } else {
        0.0
    }
}

/// Runs `scancorr shape fit`: reads `points_file`, fits a feature of `kind` and prints the
/// result, as JSON when `json` is set.
pub fn run(kind: &str, points_file: &Path, json: bool) -> Result<()> {
    let kind: ShapeKind = kind.parse()?;
    let text = if points_file == Path::new("-") {
        let mut t = String::new();
        std::io::Read::read_to_string(&mut std::io::stdin(), &mut t)
            .context("cannot read the points from standard input")?;
        t
    } else {
        std::fs::read_to_string(points_file)
            .with_context(|| format!("cannot read the point file {}", points_file.display()))?
    };
    let points_file = if points_file == Path::new("-") {
        Path::new("standard input")
    } else {
        points_file
    };
    let points =
        parse_points(&text).with_context(|| format!("point file {}", points_file.display()))?;
    let summary =
        fit(kind, &points).with_context(|| format!("{kind} fit of {}", points_file.display()))?;
    if json {
        outln!("{}", serde_json::to_string_pretty(&to_json(&summary))?)?;
    } else {
        print_human(&summary, points_file)?;
    }
    Ok(())
}

fn fit(kind: ShapeKind, points: &[Vec3]) -> Result<Summary> {
    let n = points.len();
    Ok(match kind {
        ShapeKind::Circle => {
            let f = fit_circle(points)?;
            Summary {
                kind,
                points: n,
                center: f.center,
                normal: Some(f.normal),
                diameter: Some(f.diameter),
                rms: f.rms,
                max_abs_residual: f.max_abs_residual(),
                form: peak_to_valley(&f.residuals),
                residuals: f.residuals,
            }
        }
        ShapeKind::Sphere => {
            let f = fit_sphere(points)?;
            Summary {
                kind,
                points: n,
                center: f.center,
                normal: None,
                diameter: Some(f.diameter),
                rms: f.rms,
                max_abs_residual: f.max_abs_residual(),
                form: peak_to_valley(&f.residuals),
                residuals: f.residuals,
            }
        }
        ShapeKind::Line => {
            let f = fit_line(points)?;
            Summary {
                kind,
                points: n,
                center: f.centroid,
                normal: Some(f.direction),
                diameter: None,
                rms: f.rms,
                max_abs_residual: f.max_abs_residual(),
                // A line's residuals are distances (≥ 0): its straightness is the diameter of
                // the cylinder about the least-squares line that holds every point.
                form: 2.0 * f.max_abs_residual(),
                residuals: f.residuals,
            }
        }
        ShapeKind::Plane => {
            let f = fit_plane(points)?;
            Summary {
                kind,
                points: n,
                center: f.centroid,
                normal: Some(f.normal),
                diameter: None,
                rms: f.rms,
                max_abs_residual: f.max_abs_residual(),
                form: peak_to_valley(&f.residuals),
                residuals: f.residuals,
            }
        }
    })
}

fn xyz(v: &Vec3) -> [f64; 3] {
    [v.x, v.y, v.z]
}

/// The `--json` document, fields in this order.
#[derive(Serialize)]
struct JsonSummary {
    kind: &'static str,
    points: usize,
    center: [f64; 3],
    normal: Option<[f64; 3]>,
    diameter: Option<f64>,
    rms: f64,
    max_abs_residual: f64,
    /// Peak-to-valley of the residual (for a circle: roundness), mm.
    peak_to_valley: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    roundness: Option<f64>,
    /// A line's straightness: the diameter of the cylinder about the least-squares line that
    /// holds every point, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    straightness: Option<f64>,
    /// A plane's flatness: the peak-to-valley of its residuals, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    flatness: Option<f64>,
    /// Each point's residual, mm, in input order: signed radial in the circle's plane
    /// (circle) or from the centre (sphere), positive outside; signed along the normal
    /// (plane); the distance from the line (line, ≥ 0).
    residuals: Vec<f64>,
}

fn to_json(s: &Summary) -> JsonSummary {
    JsonSummary {
        kind: s.kind.name(),
        points: s.points,
        center: xyz(&s.center),
        normal: s.normal.as_ref().map(xyz),
        diameter: s.diameter,
        rms: s.rms,
        max_abs_residual: s.max_abs_residual,
        peak_to_valley: s.form,
        roundness: (s.kind == ShapeKind::Circle).then_some(s.form),
        straightness: (s.kind == ShapeKind::Line).then_some(s.form),
        flatness: (s.kind == ShapeKind::Plane).then_some(s.form),
        residuals: s.residuals.clone(),
    }
}

/// `x` with `decimals` decimals, right-aligned in 16 columns, without a sign on a zero.
fn fixed(x: f64, decimals: usize) -> String {
    let s = format!("{x:.decimals$}");
    let s = if s.bytes().all(|b| matches!(b, b'-' | b'0' | b'.')) {
        s.trim_start_matches('-').to_string()
    } else {
        s
    };
    format!("{s:>16}")
}

fn print_human(s: &Summary, file: &Path) -> Result<()> {
    outln!(
        "{} fit of {} points from {}",
        s.kind,
        s.points,
        file.display()
    )?;
    let center_label = match s.kind {
        ShapeKind::Circle | ShapeKind::Sphere => "center",
        ShapeKind::Line | ShapeKind::Plane => "centroid",
    };
    let v = |v: &Vec3, decimals: usize| {
        format!(
            "{} {} {}",
            fixed(v.x, decimals),
            fixed(v.y, decimals),
            fixed(v.z, decimals)
        )
    };
    outln!("  {center_label:<16} {}  mm", v(&s.center, 6))?;
    if let Some(n) = &s.normal {
        let label = match s.kind {
            ShapeKind::Line => "direction",
            _ => "normal",
        };
        outln!("  {label:<16} {}", v(n, 9))?;
    }
    if let Some(d) = s.diameter {
        outln!("  {:<16} {}  mm", "diameter", fixed(d, 6))?;
        outln!("  {:<16} {}  mm", "radius", fixed(d / 2.0, 6))?;
    }
    outln!("  {:<16} {}  mm", "rms residual", fixed(s.rms, 6))?;
    outln!(
        "  {:<16} {}  mm",
        "max |residual|",
        fixed(s.max_abs_residual, 6)
    )?;
    let (form, what) = match s.kind {
        ShapeKind::Circle => ("roundness", "peak-to-valley of the residual"),
        ShapeKind::Line => (
            "straightness",
            "Ø of the cylinder about the least-squares line holding every point",
        ),
        ShapeKind::Plane => ("flatness", "peak-to-valley of the residual"),
        _ => ("form (P−V)", "peak-to-valley of the residual"),
    };
    outln!("  {form:<16} {}  mm  ({what})", fixed(s.form, 6))?;
    Ok(())
}
