//! What is plausible: a sample's values within the machine's ranges, a seq jump's bound, a
//! corrected point inside the machine's volume.

use super::*;

/// Most samples a stream can have lost in `dt_ns` since its previous sample: four per sample
/// period (a controller streaming faster than its calibration says; the temperature stream's
/// several sensors per instant) plus 1024. A longer seq jump is not counted as missing.
pub(super) fn plausible_missing(dt_ns: i64, m: &Model) -> u64 {
    let period_ns = m
        .nominal
        .values()
        .next()
        .map_or(1e6, |d| d[0].period_s * 1e9)
        .max(1.0);
    // `as` saturates: a time jump of centuries gives a large bound, never a wrapped one.
    ((dt_ns.max(0) as f64 / period_ns * 4.0) as u64).saturating_add(1024)
}

/// Whether a sample's values lie in the machine's plausible ranges; its name in the grammar.
pub(super) fn plausible(s: &Sample, m: &Model) -> Result<(), DropReason> {
    let l = &m.settings.limits;
    let in_travel = |p: &Vec3| within_box(p, &l.travel_mm);
    let ok = match s {
        Sample::Command(c) => {
            in_travel(&c.pos)
                && (c.arc_radius == 0.0
                    || (in_travel(&c.arc_center) && c.arc_radius <= m.max_arc_radius_mm))
        }
        Sample::Scale(c) => in_travel(&c.pos),
        Sample::Probe(p) => {
            p.deflection.iter().all(|d| d.abs() <= l.probe_range_mm)
                && p.head_a1_deg.abs() <= 360.0
                && p.head_a2_deg.abs() <= 360.0
        }
        Sample::Temperature(t) => {
            if !scancorr_proto::names::is_valid(&t.sensor) {
                return Err(DropReason::BadName);
            }
            t.celsius >= l.temperature_c[0] && t.celsius <= l.temperature_c[1]
        }
    };
    if ok {
        Ok(())
    } else {
        Err(DropReason::Implausible)
    }
}

/// Whether a corrected point is finite, inside the machine's volume and every correction
/// within `limits.max_correction_mm`.
pub(super) fn inside(p: &Geometry, corrections: &[Vec3], m: &Model) -> bool {
    let max_c = m.settings.limits.max_correction_mm;
    // Every test evaluated (`&`, not `&&`): no branch per coordinate on the hot path.
    within_box(&p.surface, &m.volume_mm)
        & within_box(&p.tip_center, &m.volume_mm)
        & p.normal.iter().fold(true, |ok, v| ok & v.is_finite())
        & corrections.iter().fold(true, |ok, c| {
            ok & (c.x.abs() <= max_c) & (c.y.abs() <= max_c) & (c.z.abs() <= max_c)
        })
}

/// Whether `p` lies in the box `[lo, hi]` per axis (false for a coordinate that is NaN).
#[inline]
pub(super) fn within_box(p: &Vec3, b: &[[f64; 2]; 3]) -> bool {
    (p.x >= b[0][0])
        & (p.x <= b[0][1])
        & (p.y >= b[1][0])
        & (p.y <= b[1][1])
        & (p.z >= b[2][0])
        & (p.z <= b[2][1])
}
