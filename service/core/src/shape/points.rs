//! ASCII point files (`x y z` or `x y` rows) parsed into points.

use super::*;

/// Parses an ASCII point file: one `x y z` row per point — or `x y` rows (z = 0), as a
/// roundness profile comes — the numbers separated by whitespace and/or commas; the first
/// point row fixes which. Blank lines and `#` comments (to the end of the line) are ignored.
/// The first row may hold only the number of points (an integer), which is then checked
/// against the rows that follow. Errors name the one-based line.
pub fn parse_points(text: &str) -> Result<Vec<Vec3>, ShapeError> {
    let mut points = Vec::new();
    let mut declared: Option<(usize, usize)> = None;
    let mut first = true;
    let mut width: Option<usize> = None;
    for (i, raw) in text.lines().enumerate() {
        let line = i + 1;
        let content = raw.split('#').next().unwrap_or("");
        let tokens: Vec<&str> = content
            .split(|c: char| c.is_whitespace() || c == ',')
            .filter(|t| !t.is_empty())
            .collect();
        if tokens.is_empty() {
            continue;
        }
        if first {
            first = false;
            if tokens.len() == 1 {
                let count = tokens[0].parse::<usize>().map_err(|_| ShapeError::Parse {
                    line,
                    message: format!(
                        "`{}` is neither a point count (a whole number alone on the first \
                         line) nor an `x y z` row",
                        tokens[0]
                    ),
                })?;
                declared = Some((line, count));
                continue;
            }
        }
        let want = *width.get_or_insert(if tokens.len() == 2 { 2 } else { 3 });
        if tokens.len() != want {
            return Err(ShapeError::Parse {
                line,
                message: format!(
                    "expected {want} numbers ({}{}), found {} field(s): `{}`",
                    if want == 2 { "x y" } else { "x y z" },
                    if points.is_empty() {
                        ""
                    } else {
                        ", as the rows before"
                    },
                    tokens.len(),
                    content.trim()
                ),
            });
        }
        let mut xyz = [0.0; 3];
        for (v, t) in xyz.iter_mut().zip(&tokens) {
            let x = t.parse::<f64>().map_err(|_| ShapeError::Parse {
                line,
                message: format!("`{t}` is not a number"),
            })?;
            if !x.is_finite() {
                return Err(ShapeError::Parse {
                    line,
                    message: format!("`{t}` is not a finite number"),
                });
            }
            *v = x;
        }
        points.push(Vec3::new(xyz[0], xyz[1], xyz[2]));
    }
    if let Some((line, count)) = declared {
        if count != points.len() {
            return Err(ShapeError::CountMismatch {
                line,
                declared: count,
                found: points.len(),
            });
        }
    }
    Ok(points)
}
