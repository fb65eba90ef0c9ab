//! The measured artifact, stored as the `scancorr.artifact` metadata record.
use crate::BagError;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt;

/// Metadata record name of the measured artifact.
pub const ARTIFACT_METADATA: &str = "scancorr.artifact";

/// What kind of artifact was measured. Serialized as its lowercase name (`ring`, `sphere`,
/// `straightedge`, `plane`, `part`); any other name is kept as [`ArtifactKind::Other`] so bags
/// from newer writers still read.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(from = "String", into = "String")]
pub enum ArtifactKind {
    /// Ring gauge (inner diameter).
    Ring,
    /// Reference sphere.
    Sphere,
    /// Straightedge.
    Straightedge,
    /// Flat (optical flat, surface plate).
    Plane,
    /// A production part.
    Part,
    /// A kind this version does not know.
    Other(String),
}

impl ArtifactKind {
    /// The name stored in the metadata.
    pub fn as_str(&self) -> &str {
        match self {
            ArtifactKind::Ring => "ring",
            ArtifactKind::Sphere => "sphere",
            ArtifactKind::Straightedge => "straightedge",
            ArtifactKind::Plane => "plane",
            ArtifactKind::Part => "part",
            ArtifactKind::Other(s) => s,
        }
    }
}

impl From<&str> for ArtifactKind {
    fn from(s: &str) -> Self {
        match s {
            "ring" => ArtifactKind::Ring,
            "sphere" => ArtifactKind::Sphere,
            "straightedge" => ArtifactKind::Straightedge,
            "plane" => ArtifactKind::Plane,
            "part" => ArtifactKind::Part,
            other => ArtifactKind::Other(other.to_owned()),
        }
    }
}

impl From<String> for ArtifactKind {
    fn from(s: String) -> Self {
        ArtifactKind::from(s.as_str())
    }
}

impl From<ArtifactKind> for String {
    fn from(k: ArtifactKind) -> String {
        k.as_str().to_owned()
    }
}

impl fmt::Display for ArtifactKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// The artifact a bag measured, so offline evaluation knows what the points should lie on.
///
/// Stored as the string map of the `scancorr.artifact` metadata record (keys = field names,
/// numbers in shortest round-trip decimal); keys this version does not know are kept in
/// [`Artifact::extra`]. Lengths in mm, machine axes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Artifact {
    /// Key `kind`.
    pub kind: ArtifactKind,
    /// Key `diameter_mm`: nominal diameter (ring, sphere).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub diameter_mm: Option<f64>,
    /// Key `length_mm`: nominal length (straightedge).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub length_mm: Option<f64>,
    /// Key `certificate_mm`: the value stated on the artifact's calibration certificate.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub certificate_mm: Option<f64>,
    /// Key `center_x_mm`: centre (ring, sphere) or reference point, machine X.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub center_x_mm: Option<f64>,
    /// Key `center_y_mm`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub center_y_mm: Option<f64>,
    /// Key `center_z_mm`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub center_z_mm: Option<f64>,
    /// Every other key, verbatim (e.g. `serial`, `normal_x`).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub extra: BTreeMap<String, String>,
}

impl Artifact {
    /// An artifact of `kind` with no dimensions.
    pub fn new(kind: ArtifactKind) -> Self {
        Artifact {
            kind,
            diameter_mm: None,
            length_mm: None,
            certificate_mm: None,
            center_x_mm: None,
            center_y_mm: None,
            center_z_mm: None,
            extra: BTreeMap::new(),
        }
    }

    fn numbers(&self) -> [(&'static str, Option<f64>); 6] {
        [
            ("diameter_mm", self.diameter_mm),
            ("length_mm", self.length_mm),
            ("certificate_mm", self.certificate_mm),
            ("center_x_mm", self.center_x_mm),
            ("center_y_mm", self.center_y_mm),
            ("center_z_mm", self.center_z_mm),
        ]
    }

    /// The metadata string map. Typed fields win over equally named keys in `extra`.
    pub fn to_metadata(&self) -> BTreeMap<String, String> {
        let mut m = self.extra.clone();
        m.insert("kind".into(), self.kind.as_str().into());
        for (key, value) in self.numbers() {
            match value {
                Some(v) => m.insert(key.into(), v.to_string()),
                None => m.remove(key),
            };
        }
        m
    }

    /// Parses the metadata string map: `kind` is required, numeric keys must parse as numbers.
    pub fn from_metadata(map: &BTreeMap<String, String>) -> Result<Self, BagError> {
        let mut extra = map.clone();
        let kind = extra.remove("kind").ok_or_else(|| BagError::Artifact {
            key: "kind".into(),
            reason: "missing".into(),
        })?;
        let mut a = Artifact::new(ArtifactKind::from(kind));
        let mut num = |key: &str| -> Result<Option<f64>, BagError> {
            extra
                .remove(key)
                .map(|v| {
                    v.trim().parse::<f64>().map_err(|_| BagError::Artifact {
                        key: key.into(),
                        reason: format!("{v:?} is not a number"),
                    })
                })
                .transpose()
        };
        a.diameter_mm = num("diameter_mm")?;
        a.length_mm = num("length_mm")?;
        a.certificate_mm = num("certificate_mm")?;
        a.center_x_mm = num("center_x_mm")?;
        a.center_y_mm = num("center_y_mm")?;
        a.center_z_mm = num("center_z_mm")?;
        a.extra = extra;
        Ok(a)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn metadata_roundtrip_keeps_unknown_keys() {
        let mut a = Artifact::new(ArtifactKind::Ring);
        a.diameter_mm = Some(50.0001);
        a.certificate_mm = Some(0.1 + 0.2);
        a.center_x_mm = Some(-12.5);
        a.extra.insert("serial".into(), "R-0042".into());
        let m = a.to_metadata();
        assert_eq!(m["kind"], "ring");
        assert_eq!(m["diameter_mm"], "50.0001");
        assert_eq!(m["serial"], "R-0042");
        assert!(!m.contains_key("center_y_mm"));
        assert_eq!(Artifact::from_metadata(&m).unwrap(), a);

        let mut m2 = m.clone();
        m2.insert("kind".into(), "gauge_block".into());
        assert_eq!(
            Artifact::from_metadata(&m2).unwrap().kind,
            ArtifactKind::Other("gauge_block".into())
        );
        m2.insert("diameter_mm".into(), "fifty".into());
        let e = Artifact::from_metadata(&m2).unwrap_err();
        assert!(e.to_string().contains("diameter_mm"), "{e}");
        m2.remove("kind");
        assert!(
            matches!(Artifact::from_metadata(&m2), Err(BagError::Artifact { key, .. }) if key == "kind")
        );
    }

    #[test]
    fn serde_json_roundtrip() {
        let mut a = Artifact::new(ArtifactKind::Sphere);
        a.diameter_mm = Some(25.4);
        let j = serde_json::to_string(&a).unwrap();
        assert_eq!(j, r#"{"kind":"sphere","diameter_mm":25.4}"#);
        assert_eq!(serde_json::from_str::<Artifact>(&j).unwrap(), a);
    }
}
