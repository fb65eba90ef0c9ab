//! Synthesis: the surface point from scales, corrections, deflection, tip offset and radius.

use super::*;

/// The geometric result of one point.
#[derive(Debug, Clone, PartialEq)]
pub struct Synthesis {
    /// Surface point, mm.
    pub surface: Vec3,
    /// Tip centre, mm.
    pub tip_center: Vec3,
    /// Unit normal or zero.
    pub normal: Vec3,
    /// Per-effect corrections.
    pub corrections: Vec<Vec3>,
}

/// A point's geometry without its corrections (those go to a list of the caller's).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Geometry {
    pub(super) surface: Vec3,
    pub(super) tip_center: Vec3,
    pub(super) normal: Vec3,
}

/// Surface point = scales + Σ corrections + R·deflection + tip offset − radius·normal.
pub fn synthesize(
    ctx: &PointContext,
    effects: &[BuiltEffect],
    suspend_dynamic: bool,
    min_contact: f64,
) -> Synthesis {
    let mut corrections = Vec::with_capacity(effects.len());
    let g = synthesize_into(ctx, effects, suspend_dynamic, min_contact, &mut corrections);
    Synthesis {
        surface: g.surface,
        tip_center: g.tip_center,
        normal: g.normal,
        corrections,
    }
}

/// [`synthesize`], appending the per-effect corrections to `corrections` (empty).
pub(super) fn synthesize_into(
    ctx: &PointContext,
    effects: &[BuiltEffect],
    suspend_dynamic: bool,
    min_contact: f64,
    corrections: &mut Vec<Vec3>,
) -> Geometry {
    corrections.extend(effects.iter().map(|e| {
        if suspend_dynamic && e.dynamic {
            Vec3::zeros()
        } else {
            e.model.correction(ctx)
        }
    }));
    // Summed once all are written (the same additions in the same order), not in the loop:
    // there each sum waited on a load of the correction just stored, often in pieces.
    let total = corrections.iter().fold(Vec3::zeros(), |t, c| t + c);
    let tip_center = ctx.scale + total + ctx.deflection + ctx.tip_offset();
    let d = ctx.deflection.norm();
    let normal = if d >= min_contact && d > 0.0 {
        ctx.deflection * (1.0 / d)
    } else {
        Vec3::zeros()
    };
    Geometry {
        surface: tip_center - normal * ctx.tip_radius,
        tip_center,
        normal,
    }
}

pub(super) fn lerp_estimate(a: &Estimate, b: &Estimate, t: i64) -> Estimate {
    let w = (t - a.cmd.t_ns) as f64 / (b.cmd.t_ns - a.cmd.t_ns) as f64;
    let mut cmd = a.cmd;
    cmd.t_ns = t;
    cmd.pos = a.cmd.pos + (b.cmd.pos - a.cmd.pos) * w;
    Estimate {
        cmd,
        pos: a.pos + (b.pos - a.pos) * w,
        vel: a.vel + (b.vel - a.vel) * w,
        acc: a.acc + (b.acc - a.acc) * w,
    }
}
