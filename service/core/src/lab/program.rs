//! What a bag says about what was measured: features (artifacts) and scan segments.
//!
//! Written by the simulator (and by any recorder that knows its part program) as the JSON of
//! the `scancorr.program` metadata record; a bag without it can name its artifact on the
//! command line (`--artifact ring:d=50.0012`).

use crate::sample::Vec3;
use serde::{Deserialize, Serialize};

/// How a feature's surface meets the probe.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FeatureKind {
    /// Inside of a circle (ring gauge, bore).
    Bore,
    /// Outside of a sphere or circle (sphere, boss).
    Boss,
    /// A plane face (straightedge, part face).
    Face,
}

/// A measured feature.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FeatureSpec {
    /// Id within its bag.
    pub id: u32,
    /// `ring`, `sphere`, `straightedge`, `plane`, `part`.
    pub artifact: String,
    /// Bore, boss or face.
    pub kind: FeatureKind,
    /// Nominal position, mm.
    pub nominal_center: [f64; 3],
    /// Nominal diameter, mm (0 for faces).
    pub nominal_diameter_mm: f64,
    /// Certified diameter: the fit keeps it fixed, mm.
    pub certificate_diameter_mm: Option<f64>,
    /// Face normal, out of the material.
    pub normal: [f64; 3],
}

/// Kind of a segment.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SegmentKind {
    /// Measuring in contact.
    Scan,
    /// Positioning.
    Move,
    /// Standing in contact.
    Dwell,
}

/// A segment of the program.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SegmentSpec {
    /// Segment id (as in the command stream).
    pub id: u32,
    /// Kind.
    pub kind: SegmentKind,
    /// Feature scanned.
    pub feature: Option<u32>,
    /// Programmed speed, mm/s.
    pub speed: f64,
    /// +1 CCW, −1 CW, 0 not an arc.
    pub direction: i32,
    /// Tip.
    pub tip: u32,
    /// Head A1, degrees.
    pub a1_deg: f64,
    /// Head A2, degrees.
    pub a2_deg: f64,
    /// Programmed deflection, mm.
    pub deflection_mm: f64,
    /// Start, s.
    pub t0_s: f64,
    /// End, s.
    pub t1_s: f64,
}

/// A program: features and segments.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ProgramSpec {
    /// Program name.
    pub program: String,
    /// Features.
    pub features: Vec<FeatureSpec>,
    /// Segments.
    pub segments: Vec<SegmentSpec>,
}

/// The plane of a bore or boss whose axis (`normal`, the spec's) is not z — a ring standing on
/// its edge: (n, e1, e2) with n the unit axis, e1 = n × z normalised, e2 = e1 × n (rotation
/// from e1 towards e2 is about −n). None for an upright circle (axis zero or along z).
pub fn circle_plane(normal: [f64; 3]) -> Option<(Vec3, Vec3, Vec3)> {
    let n = Vec3::from(normal).try_normalize(1e-9)?;
    if n.z.abs() >= 1.0 - 1e-9 {
        return None;
    }
    let e1 = n.cross(&Vec3::z()).normalize();
    Some((n, e1, e1.cross(&n)))
}

/// Parses `ring:d=50.0012`, `sphere:d=25.0004`, `straightedge`, `plane` (a bag's only artifact,
/// for bags without a program record).
pub fn parse_artifact(s: &str) -> Result<FeatureSpec, String> {
    let (kind, rest) = s.split_once(':').unwrap_or((s, ""));
    let mut d = None;
    let mut normal = [0.0, -1.0, 0.0];
    let mut axis_given = false;
    for kv in rest.split(',').filter(|k| !k.is_empty()) {
        let (k, v) = kv
            .split_once('=')
            .ok_or_else(|| format!("`{kv}`: expected key=value"))?;
        let num = |v: &str| {
            v.parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| format!("`{kv}`: not a number"))
        };
        match k {
            "d" | "diameter" => d = Some(num(v)?),
            "nx" | "ny" | "nz" => {
                axis_given = true;
                let i = match k {
                    "nx" => 0,
                    "ny" => 1,
                    _ => 2,
                };
                normal[i] = num(v)?;
            }
            _ => return Err(format!("`{k}`: unknown key (use d=, nx=, ny=, nz=)")),
        }
    }
    let (fk, need_d) = match kind {
        "ring" => (FeatureKind::Bore, true),
        "sphere" => (FeatureKind::Boss, true),
        "straightedge" | "plane" => (FeatureKind::Face, false),
        _ => {
            return Err(format!(
                "unknown artifact `{kind}` (ring:d=…, sphere:d=…, straightedge, plane)"
            ))
        }
    };
    if need_d && d.is_none_or(|d| d <= 0.0) {
        return Err(format!(
            "{kind}: give the certified diameter, e.g. {kind}:d=50.0012"
        ));
    }
    Ok(FeatureSpec {
        id: 1,
        artifact: kind.to_string(),
        kind: fk,
        nominal_center: [0.0; 3],
        nominal_diameter_mm: d.unwrap_or(0.0),
        certificate_diameter_mm: d,
        // A ring's or sphere's axis only when stated (a ring standing on its edge); otherwise
        // upright (zero).
        normal: if fk == FeatureKind::Face || axis_given {
            normal
        } else {
            [0.0; 3]
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_artifacts_axis_only_when_stated() {
        // An upright ring: no axis (fitted in the horizontal plane).
        let up = parse_artifact("ring:d=50").unwrap();
        assert_eq!(up.normal, [0.0; 3]);
        assert!(circle_plane(up.normal).is_none());
        // A ring standing on its edge, its axis along y: fitted in the XZ plane.
        let edge = parse_artifact("ring:d=50,nx=0,ny=1,nz=0").unwrap();
        assert_eq!(edge.normal, [0.0, 1.0, 0.0]);
        let (n, e1, e2) = circle_plane(edge.normal).unwrap();
        assert!((n.dot(&e1)).abs() < 1e-12 && (n.dot(&e2)).abs() < 1e-12);
        assert!((e1.norm() - 1.0).abs() < 1e-12 && (e2.norm() - 1.0).abs() < 1e-12);
        // Each key sets its own component.
        assert_eq!(
            parse_artifact("ring:d=50,nz=0.5").unwrap().normal,
            [0.0, -1.0, 0.5]
        );
        assert!(parse_artifact("ring:d=50,nw=1").is_err());
        assert!(parse_artifact("ring:nz=1").is_err());
    }
}
