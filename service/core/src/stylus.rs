//! Stylus and articulating-head geometry: where the tip centre is relative to the point the
//! scales measure.
//!
//! Equation: machine_from_probe = Rz(A1)·Rx(A2); in probe axes the shank points along −z
//! with length l1 and the bent part adds l2·(sin β1, 0, −cos β1) + l3·(0, sin β2, −cos β2);
//! tip offset (machine) = machine_from_probe · (shank + bent).
//!
//! Source idea: the usual description of an articulating head (swivel A1 about the ram axis,
//! tilt A2 about a horizontal axis) carrying a cranked/star stylus whose limbs are given by
//! their lengths and bend angles.

use crate::sample::Vec3;
use nalgebra::Matrix3;
use serde::{Deserialize, Serialize};

/// Longest limb of a stylus (`l1_mm`, `l2_mm`, `l3_mm`), mm.
pub const MAX_LENGTH_MM: f64 = 2000.0;

/// Geometry of one tip of a calibration document. Ranges: limbs 0 … 2000 mm, tip radius
/// 0.005 … 100 mm, bend angles ±360°.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TipGeometry {
    /// Tip id as reported in `ProbeSample.tip_id`.
    pub id: u32,
    /// Probe type carrying this tip; selects the probe model G2 in `nominal.probes`.
    pub probe: String,
    /// Reference (shank) length l1 along the probe axis, mm.
    pub l1_mm: f64,
    /// Tip ball radius, mm.
    pub radius_mm: f64,
    /// Bent-stylus limb l2 (in the probe x–z plane), mm.
    #[serde(default)]
    pub l2_mm: f64,
    /// Bend angle β1 of l2 from the probe axis, degrees.
    #[serde(default)]
    pub beta1_deg: f64,
    /// Bent-stylus limb l3 (in the probe y–z plane), mm.
    #[serde(default)]
    pub l3_mm: f64,
    /// Bend angle β2 of l3 from the probe axis, degrees.
    #[serde(default)]
    pub beta2_deg: f64,
}

impl TipGeometry {
    /// Shank part of the offset in probe axes.
    pub fn shank_probe(&self) -> Vec3 {
        Vec3::new(0.0, 0.0, -self.l1_mm)
    }
    /// Bent part of the offset in probe axes.
    pub fn bent_probe(&self) -> Vec3 {
        let (b1, b2) = (self.beta1_deg.to_radians(), self.beta2_deg.to_radians());
        self.l2_mm * Vec3::new(b1.sin(), 0.0, -b1.cos())
            + self.l3_mm * Vec3::new(0.0, b2.sin(), -b2.cos())
    }
    /// Checks every number; `field` prefixes the message.
    pub fn validate(&self, field: &str) -> Result<(), String> {
        for (name, v) in [
            ("l1_mm", self.l1_mm),
            ("radius_mm", self.radius_mm),
            ("l2_mm", self.l2_mm),
            ("beta1_deg", self.beta1_deg),
            ("l3_mm", self.l3_mm),
            ("beta2_deg", self.beta2_deg),
        ] {
            if !v.is_finite() {
                return Err(format!("{field}.{name}: must be a finite number"));
            }
        }
        for (name, v, lo, hi, unit) in [
            ("l1_mm", self.l1_mm, 0.0, MAX_LENGTH_MM, "mm"),
            ("radius_mm", self.radius_mm, 0.005, 100.0, "mm"),
            ("l2_mm", self.l2_mm, 0.0, MAX_LENGTH_MM, "mm"),
            ("beta1_deg", self.beta1_deg, -360.0, 360.0, "°"),
            ("l3_mm", self.l3_mm, 0.0, MAX_LENGTH_MM, "mm"),
            ("beta2_deg", self.beta2_deg, -360.0, 360.0, "°"),
        ] {
            crate::checks::in_range(&format!("{field}.{name}"), v, lo, hi, unit)?;
        }
        Ok(())
    }
}

/// Rotation from probe axes to machine axes for head angles A1 (swivel about Z) and A2
/// (tilt about the swivelled X axis), degrees.
pub fn machine_from_probe(a1_deg: f64, a2_deg: f64) -> Matrix3<f64> {
    let (s1, c1) = a1_deg.to_radians().sin_cos();
    let (s2, c2) = a2_deg.to_radians().sin_cos();
    let rz = Matrix3::new(c1, -s1, 0.0, s1, c1, 0.0, 0.0, 0.0, 1.0);
    let rx = Matrix3::new(1.0, 0.0, 0.0, 0.0, c2, -s2, 0.0, s2, c2);
    rz * rx
}

/// One tip at one pair of head angles: the head's rotation and the tip's offset in machine
/// axes. They change only when the tip or the head does, so the corrector keeps the last one
/// and computes a new one only then (not per point).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TipPose {
    /// Tip id.
    pub tip_id: u32,
    /// Head angle A1, degrees.
    pub a1_deg: f64,
    /// Head angle A2, degrees.
    pub a2_deg: f64,
    /// [`machine_from_probe`] at these angles.
    pub machine_from_probe: Matrix3<f64>,
    /// Shank part of the tip offset, machine axes, mm.
    pub shank: Vec3,
    /// Bent part of the tip offset, machine axes, mm.
    pub bent: Vec3,
}

impl TipPose {
    /// The pose of `tip` at head angles A1, A2 (degrees).
    pub fn new(tip: &TipGeometry, a1_deg: f64, a2_deg: f64) -> TipPose {
        let r = machine_from_probe(a1_deg, a2_deg);
        TipPose {
            tip_id: tip.id,
            a1_deg,
            a2_deg,
            machine_from_probe: r,
            shank: r * tip.shank_probe(),
            bent: r * tip.bent_probe(),
        }
    }

    /// Whether this is the pose of tip `tip_id` at these head angles (the same bits: −0 is
    /// not +0 here, so a cached pose equals the one computed afresh).
    #[inline]
    pub fn is_for(&self, tip_id: u32, a1_deg: f64, a2_deg: f64) -> bool {
        self.tip_id == tip_id
            && self.a1_deg.to_bits() == a1_deg.to_bits()
            && self.a2_deg.to_bits() == a2_deg.to_bits()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bent_stylus_offset_for_known_geometry() {
        let tip = TipGeometry {
            id: 2,
            probe: "sp25".into(),
            l1_mm: 50.0,
            radius_mm: 1.0,
            l2_mm: 20.0,
            beta1_deg: 90.0,
            l3_mm: 0.0,
            beta2_deg: 0.0,
        };
        // Straight down 50 mm, then 20 mm sideways along probe +x.
        let off = tip.shank_probe() + tip.bent_probe();
        assert!((off - Vec3::new(20.0, 0.0, -50.0)).norm() < 1e-12);
        // Head swivelled by A1 = 90°: probe +x becomes machine +y.
        let r = machine_from_probe(90.0, 0.0);
        assert!((r * off - Vec3::new(0.0, 20.0, -50.0)).norm() < 1e-12);
        // Tilted by A2 = 90°: the shank (−z probe) points along machine +y.
        let r = machine_from_probe(0.0, 90.0);
        assert!((r * tip.shank_probe() - Vec3::new(0.0, 50.0, 0.0)).norm() < 1e-12);
        // 45° bend: l2 (sin45, 0, −cos45).
        let t45 = TipGeometry {
            beta1_deg: 45.0,
            l1_mm: 0.0,
            ..tip
        };
        let h = 20.0 / 2f64.sqrt();
        assert!((t45.bent_probe() - Vec3::new(h, 0.0, -h)).norm() < 1e-12);
    }
}
