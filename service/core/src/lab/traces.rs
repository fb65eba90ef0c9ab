//! Circular-test traces: the residual of each circle feature, one trace per run — tip, head
//! angles, deflection, direction and programmed speed — as a ballbar or an ISO 230-4 circular
//! test draws them.
//!
//! Per trace (a circle feature × tip × head angles × deflection × direction × speed,
//! steady-speed points only) the residual
//! against the artifact is averaged in 1° bins of the angle about the feature's nominal
//! centre, e(θ_k). The trace's own centre is taken out by least squares — e(θ) ≈ a + b·cos θ +
//! c·sin θ, and b·cos θ + c·sin θ removed (the 1θ term is where the circle lies, not its form;
//! ISO 230-4 evaluates about the least-squares circle of each trace) — keeping a, the radius
//! against the certified circle. The **circularity** of the trace is the range (maximum −
//! minimum) of the de-centred bin means: ISO 230-4's circular deviation G evaluated on 1°
//! means, so the points' noise (a 0.1 µm floor) does not widen it by its own extremes.
//!
//! Averaging the traces of both directions or of several speeds hides what distinguishes them:
//! a servo mismatch between two axes draws mirror-image ovals in the two directions (their 2θ
//! terms opposite), which cancel in a mean over the directions. Likewise a sphere scanned with
//! two styli, or one stylus at two head angles, is two runs: pooled, the setting that fails
//! would be averaged with the ones that do not.
//!
//! The deflection of a run is its scans' measured stylus deflection (the programmed one is not
//! in the points): each scan's mean |deflection|, scans whose means lie within
//! [`DEFLECTION_GAP_MM`] of each other one class, labelled by the class's mean to 0.01 mm.

use super::dataset::{Dataset, Phase};
use super::program::FeatureKind;
use serde::Serialize;
use std::collections::BTreeMap;

/// Bins per turn.
const BINS: usize = 360;
/// Least bins a trace needs to be evaluated (a quarter of the circle).
const MIN_BINS: usize = 90;
/// Scans whose mean deflections differ by less than this are one deflection setting, mm.
pub const DEFLECTION_GAP_MM: f64 = 0.03;

/// One trace.
#[derive(Debug, Clone, Serialize)]
pub struct Trace {
    /// Index of the feature in the dataset.
    pub feature: usize,
    /// Its artifact.
    pub artifact: String,
    /// Certified (or nominal) diameter, mm.
    pub diameter_mm: f64,
    /// Active tip.
    pub tip: u32,
    /// Head angle A1, degrees (to 0.1°).
    pub head_a1_deg: f64,
    /// Head angle A2, degrees (to 0.1°).
    pub head_a2_deg: f64,
    /// Stylus deflection of the run's scans, mm (to 0.01 mm; see the module doc).
    pub deflection_mm: f64,
    /// +1 counter-clockwise, −1 clockwise.
    pub direction: i32,
    /// Programmed speed, mm/s.
    pub speed_mm_s: f64,
    /// Points in the trace.
    pub points: usize,
    /// Command segments of its points.
    pub segments: Vec<u32>,
    /// Diameter of the least-squares circle through its corrected points, mm (what
    /// `scancorr shape fit --kind circle` gives for the same points).
    pub diameter_fit_mm: Option<f64>,
    /// Circularity: range of the de-centred 1° means, µm.
    pub circularity_um: f64,
    /// Mean radius against the certified circle (a), µm.
    pub radius_um: f64,
    /// Centre taken out (b, c: X and Y), µm.
    pub center_um: [f64; 2],
    /// Bin centres with data, degrees from +X towards +Y.
    pub theta_deg: Vec<f64>,
    /// De-centred deviation at each, µm (outwards positive).
    pub deviation_um: Vec<f64>,
}

/// The de-centred bins and the fit of a set of (θ radians, e µm) samples: (θ° of the bins with
/// data, their de-centred means, a, [b, c]); `None` with fewer than `MIN_BINS` bins.
pub fn decentre(samples: impl IntoIterator<Item = (f64, f64)>) -> Option<Decentred> {
    let mut bins = vec![(0.0, 0usize); BINS];
    for (th, e) in samples {
        if !(th.is_finite() && e.is_finite()) {
            continue;
        }
        let d = th.to_degrees().rem_euclid(360.0);
        let b = &mut bins[(d as usize).min(BINS - 1)];
        b.0 += e;
        b.1 += 1;
    }
    let pts: Vec<(f64, f64)> = bins
        .iter()
        .enumerate()
        .filter(|(_, b)| b.1 > 0)
        .map(|(k, b)| ((k as f64 + 0.5).to_radians(), b.0 / b.1 as f64))
        .collect();
    if pts.len() < MIN_BINS {
        return None;
    }
    // Least squares of e ≈ a + b cos θ + c sin θ over the bins (3×3 normal equations).
    let mut m = nalgebra::Matrix3::<f64>::zeros();
    let mut v = nalgebra::Vector3::<f64>::zeros();
    for (th, e) in &pts {
        let g = nalgebra::Vector3::new(1.0, th.cos(), th.sin());
        m += g * g.transpose();
        v += g * *e;
    }
    let x = m.try_inverse()? * v;
    let dev: Vec<f64> = pts
        .iter()
        .map(|(th, e)| e - x[1] * th.cos() - x[2] * th.sin())
        .collect();
    let (lo, hi) = dev
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), d| {
            (a.min(*d), b.max(*d))
        });
    Some(Decentred {
        theta_deg: pts.iter().map(|(th, _)| th.to_degrees()).collect(),
        deviation_um: dev,
        radius_um: x[0],
        center_um: [x[1], x[2]],
        circularity_um: hi - lo,
    })
}

/// What [`decentre`] finds.
#[derive(Debug, Clone)]
pub struct Decentred {
    /// Bin centres with data, degrees.
    pub theta_deg: Vec<f64>,
    /// De-centred means, µm.
    pub deviation_um: Vec<f64>,
    /// a, µm.
    pub radius_um: f64,
    /// b, c, µm.
    pub center_um: [f64; 2],
    /// Range of `deviation_um`, µm.
    pub circularity_um: f64,
}

/// The traces of every circle feature of `ds`, `residual_um` the residual of each point (as
/// [`super::analysis::Comparison::residual_um`]); by feature, then tip, head angles,
/// deflection, direction and speed.
pub fn traces(ds: &Dataset, residual_um: &[f64]) -> Vec<Trace> {
    let use_point = |p: &super::dataset::LabPoint| {
        ds.features[p.feature].1.kind != FeatureKind::Face
            && p.direction != 0
            && p.phase == Phase::Steady
    };
    // Each scan's mean |deflection| (bag, segment) → (sum, n), then the deflection classes.
    let mut scan_defl: BTreeMap<(usize, u32), (f64, usize)> = BTreeMap::new();
    for p in ds.points.iter().filter(|p| use_point(p)) {
        let d = p.ctx.deflection_probe.norm();
        if d.is_finite() {
            let e = scan_defl.entry((p.bag, p.segment)).or_default();
            e.0 += d;
            e.1 += 1;
        }
    }
    let scan_mean: BTreeMap<(usize, u32), f64> = scan_defl
        .into_iter()
        .map(|(k, (s, n))| (k, s / n as f64))
        .collect();
    let classes = deflection_classes(scan_mean.values().copied().collect());
    let class_of = |bag: usize, seg: u32| -> i64 {
        scan_mean
            .get(&(bag, seg))
            .map(|d| {
                classes
                    .iter()
                    .find(|(lo, hi, _)| *d >= *lo && *d <= *hi)
                    .map_or((d * 100.0).round() as i64, |c| c.2)
            })
            .unwrap_or(0)
    };
    // (feature, tip, A1 and A2 in 0.1°, deflection in 0.01 mm, direction, speed in 0.1 mm/s)
    // → points.
    type Key = (usize, u32, i64, i64, i64, i32, i64);
    let mut groups: BTreeMap<Key, Vec<usize>> = BTreeMap::new();
    for (i, p) in ds.points.iter().enumerate() {
        if !use_point(p) {
            continue;
        }
        let tenth = |a: f64| (a * 10.0).round() as i64;
        groups
            .entry((
                p.feature,
                p.ctx.tip_id,
                tenth(p.ctx.head_a1_deg),
                tenth(p.ctx.head_a2_deg),
                class_of(p.bag, p.segment),
                p.direction,
                tenth(p.speed),
            ))
            .or_default()
            .push(i);
    }
    let mut out = vec![];
    for ((fi, tip, a1, a2, defl, dir, v), idx) in groups {
        let f = &ds.features[fi].1;
        let c = f.nominal_center;
        let samples = idx.iter().filter_map(|&i| {
            let p = &ds.points[i];
            residual_um
                .get(i)
                .map(|e| ((p.surface.y - c[1]).atan2(p.surface.x - c[0]), *e))
        });
        let Some(d) = decentre(samples) else {
            continue;
        };
        let mut segments: Vec<u32> = idx.iter().map(|&i| ds.points[i].segment).collect();
        segments.sort_unstable();
        segments.dedup();
        let pts: Vec<_> = idx.iter().map(|&i| ds.points[i].surface).collect();
        let diameter_fit_mm = crate::shape::fit_circle(&pts).ok().map(|c| c.diameter);
        out.push(Trace {
            feature: fi,
            artifact: f.artifact.clone(),
            diameter_mm: f.certificate_diameter_mm.unwrap_or(f.nominal_diameter_mm),
            tip,
            head_a1_deg: a1 as f64 / 10.0,
            head_a2_deg: a2 as f64 / 10.0,
            deflection_mm: defl as f64 / 100.0,
            direction: dir,
            speed_mm_s: v as f64 / 10.0,
            points: idx.len(),
            segments,
            diameter_fit_mm,
            circularity_um: d.circularity_um,
            radius_um: d.radius_um,
            center_um: d.center_um,
            theta_deg: d.theta_deg,
            deviation_um: d.deviation_um,
        });
    }
    out
}

/// Classes of scans' mean deflections (mm): sorted, a new class where two neighbours differ
/// by more than [`DEFLECTION_GAP_MM`]; each (lowest, highest, mean in 0.01 mm).
fn deflection_classes(mut d: Vec<f64>) -> Vec<(f64, f64, i64)> {
    d.retain(|x| x.is_finite());
    d.sort_by(f64::total_cmp);
    let mut out: Vec<(f64, f64, i64)> = vec![];
    let mut start = 0;
    for i in 0..d.len() {
        if i + 1 == d.len() || d[i + 1] - d[i] > DEFLECTION_GAP_MM {
            let part = &d[start..=i];
            let mean = part.iter().sum::<f64>() / part.len() as f64;
            out.push((part[0], d[i], (mean * 100.0).round() as i64));
            start = i + 1;
        }
    }
    out
}

impl Trace {
    /// The run's setting apart from direction and speed: `tip 2, A1 90°, A2 0°, 0.30 mm`.
    pub fn setting(&self) -> String {
        format!(
            "tip {}, A1 {}°, A2 {}°, deflection {:.2} mm",
            self.tip, self.head_a1_deg, self.head_a2_deg, self.deflection_mm
        )
    }

    /// Everything that makes the run: `CW 60 mm/s, tip 2, A1 90°, A2 0°, deflection 0.30 mm`.
    pub fn label(&self) -> String {
        format!(
            "{} {} mm/s, {}",
            if self.direction > 0 { "CCW" } else { "CW" },
            self.speed_mm_s,
            self.setting()
        )
    }

    /// Whether `other` is the same run (feature, tip, head angles, deflection, direction,
    /// speed), e.g. the measured trace a prediction is drawn over.
    pub fn same_run(&self, other: &Trace) -> bool {
        self.feature == other.feature
            && self.direction == other.direction
            && self.same_setting_and_speed(other)
    }

    /// Whether `other` has this run's setting and speed (either direction).
    pub fn same_setting_and_speed(&self, other: &Trace) -> bool {
        self.tip == other.tip
            && self.head_a1_deg == other.head_a1_deg
            && self.head_a2_deg == other.head_a2_deg
            && self.deflection_mm == other.deflection_mm
            && self.speed_mm_s == other.speed_mm_s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::TAU;

    #[test]
    fn an_oval_off_centre_keeps_its_oval_and_loses_its_centre() {
        // 0.5 µm larger than certified, 3 µm off centre along X, a 2θ oval of ±4 µm.
        let s = (0..3600).map(|k| {
            let th = TAU * (k as f64 + 0.5) / 3600.0;
            (th, 0.5 + 3.0 * th.cos() + 4.0 * (2.0 * th).cos())
        });
        let d = decentre(s).unwrap();
        assert_eq!(d.theta_deg.len(), 360);
        assert!((d.radius_um - 0.5).abs() < 1e-9, "{}", d.radius_um);
        assert!((d.center_um[0] - 3.0).abs() < 1e-3 && d.center_um[1].abs() < 1e-3);
        // The range of 4·cos 2θ on 1° means: 8 µm, less a hair for averaging across a bin.
        assert!(
            (d.circularity_um - 8.0).abs() < 0.01,
            "{}",
            d.circularity_um
        );
    }

    #[test]
    fn scans_a_few_micrometres_apart_are_one_deflection_and_farther_ones_two() {
        let c = deflection_classes(vec![0.301, 0.104, 0.297, 0.499, 0.31, f64::NAN, 0.1]);
        let labels: Vec<i64> = c.iter().map(|x| x.2).collect();
        assert_eq!(labels, vec![10, 30, 50], "{c:?}");
        assert!(deflection_classes(vec![]).is_empty());
    }

    #[test]
    fn too_little_of_the_circle_is_no_trace() {
        let s = (0..80).map(|k| ((k as f64).to_radians(), 1.0));
        assert!(decentre(s).is_none());
        assert!(decentre(std::iter::empty()).is_none());
        // Non-finite samples are left out, not spread.
        let s = (0..360).map(|k| {
            (
                (k as f64 + 0.5).to_radians(),
                if k == 7 { f64::NAN } else { 0.0 },
            )
        });
        assert_eq!(decentre(s).unwrap().circularity_um, 0.0);
    }
}
