//! Moves beyond one library effect at a time, for `lab discover`: structure the library does
//! not have made into a `custom` effect, squareness named where a guide table carries it as a
//! ramp, and the significance test a library move passes, applied to such moves.
//!
//! * A structure found by [`super::structure`] (a period along an axis, a reversal, a harmonic
//!   of the probing direction) becomes a `custom` effect with the structure's own terms
//!   (`x:sin(2*pi*x/P)`, `x:cos(2*pi*x/P)`; `x:sign(vx)`; the four probing-direction terms),
//!   zero coefficients, named for what it is (`cyclic_x_1p514mm`: "cyclic error along x,
//!   period 1.514 mm").
//! * Squareness: a straightness table of axis a towards b that rises linearly with a is,
//!   to first order, the squareness of a and b (ISO 230-1: straightness is the deviation from
//!   the reference straight line; the line's slope is squareness or the part's orientation).
//!   With m the least-squares slope of the table over its knots, the ramp m·(s_a − s̄_a) is
//!   taken out of the table and put in the rigid-body squareness of
//!   [`crate::effects::rigid_body`] (δx = S_xy·y + S_xz·z, δy = S_yz·z): a table of y
//!   towards x gives S_xy = m, of z towards x S_xz = m, of z towards y S_yz = m; a table of x
//!   towards y (δy = m·x) is the same correction as S_xy = −m up to a rotation of the whole
//!   volume about z, which the artifacts' placements take (likewise x towards z: S_xz = −m,
//!   y towards z: S_yz = −m). The constant m·s̄_a left over is a translation (placements).
//! * Significance: the one test of a library move, `analysis::significant_gain`.

use super::dataset::Dataset;
use super::structure::Structure;
use super::types::FitOutcome;
use crate::effects::{custom, rigid_body, EffectConfig};
use crate::sample::Axis;

/// A custom effect made from a found structure.
#[derive(Debug, Clone)]
pub struct CustomEffect {
    /// The effect (zero coefficients), its id named for what it is.
    pub config: EffectConfig,
    /// What it is, in words ("cyclic error along x, period 1.514 mm").
    pub what: String,
}

/// `1.514` → `1p514`.
fn id_number(v: f64) -> String {
    format!("{v:.3}").replace('-', "m").replace('.', "p")
}

/// The custom effect of a structure; None when its terms cannot be read (a structure this
/// module does not know).
pub fn custom_effect(s: &Structure) -> Option<CustomEffect> {
    let (id, what) = match (s.kind.as_str(), s.period_mm, s.harmonic) {
        ("period", Some(p), _) => (
            format!("cyclic_{}_{}mm", s.axis, id_number(p)),
            format!("cyclic error along {}, period {p:.3} mm", s.axis),
        ),
        ("reversal", _, _) => (
            format!("reversal_{}", s.axis),
            format!("reversal error (backlash) along {}", s.axis),
        ),
        ("probe_direction", _, Some(k)) => (
            format!("probe_direction_{k}theta"),
            format!("{k}θ harmonic of the probing direction (probe lobing)"),
        ),
        _ => return None,
    };
    let mut terms = vec![];
    for t in &s.custom_terms {
        let (a, expr) = t.split_once(':')?;
        let axis = Axis::ALL.into_iter().find(|x| x.name() == a)?;
        terms.push(custom::Term {
            axis,
            expr: expr.to_string(),
        });
    }
    if terms.is_empty() {
        return None;
    }
    let cfg = custom::Config {
        id,
        dynamic: s.kind == "reversal",
        coefficients: vec![0.0; terms.len()],
        terms,
    };
    // Only what builds (the expressions parse) is offered.
    let config = EffectConfig::Custom(cfg);
    config
        .build(&mut crate::effects::SensorTable::default())
        .ok()?;
    Some(CustomEffect { config, what })
}

/// The significance test of a library addition ([`super::analysis::significant_gain`]) on a
/// fitted move: `o` its fit (every effect refitted), `base_cv_um` the cross-validated RMS of
/// the model refitted as it is, `base_held_um` the held-out RMS before, `noise_um` the floor.
pub fn significant(o: &FitOutcome, base_cv_um: f64, base_held_um: f64, noise_um: f64) -> bool {
    super::analysis::significant_gain(
        base_cv_um,
        o.cv_rms_after_um,
        base_held_um,
        o.heldout_rms_after_um,
        noise_um,
    )
}

/// Squareness taken from the guide tables' ramps.
#[derive(Debug, Clone)]
pub struct Squareness {
    /// The model with the ramps taken out of the guide tables and a squareness-only
    /// `rigid_body` (id `squareness`) carrying them, at the end.
    pub effects: Vec<EffectConfig>,
    /// S_xy, S_xz, S_yz, rad.
    pub s_rad: [f64; 3],
    /// The largest ramp moved, over the travel it spans, µm.
    pub ramp_um: f64,
    /// Where each came from, in words.
    pub what: String,
}

/// Least-squares slope of `v` over `x`.
fn slope(x: &[f64], v: &[f64]) -> Option<f64> {
    let n = x.len().min(v.len());
    if n < 3 {
        return None;
    }
    let mx = x[..n].iter().sum::<f64>() / n as f64;
    let mv = v[..n].iter().sum::<f64>() / n as f64;
    let sxx: f64 = x[..n].iter().map(|a| (a - mx).powi(2)).sum();
    let sxv: f64 = x[..n]
        .iter()
        .zip(&v[..n])
        .map(|(a, b)| (a - mx) * (b - mv))
        .sum();
    let m = sxv / sxx;
    (sxx > 0.0 && m.is_finite()).then_some(m)
}

/// A squareness-only rigid body (the 18 axis errors not modelled) over the data's travel.
pub fn squareness_config(ds: &Dataset, s_rad: [f64; 3]) -> Option<EffectConfig> {
    let EffectConfig::RigidBody(mut r) =
        super::candidates::candidate("rigid_body:order=1", ds).ok()?
    else {
        return None;
    };
    r.errors.clear();
    r.id = Some("squareness".into());
    r.squareness_rad = rigid_body::Squareness {
        xy: s_rad[0],
        xz: s_rad[1],
        yz: s_rad[2],
    };
    Some(EffectConfig::RigidBody(r))
}

/// Moves the linear ramps of the model's guide tables into a squareness term (see the module
/// doc). None when the model has a rigid body already or no guide table with a ramp.
pub fn squareness_from_guides(ds: &Dataset, effects: &[EffectConfig]) -> Option<Squareness> {
    if effects.iter().any(|e| e.kind() == "rigid_body") {
        return None;
    }
    let mut s = [0.0f64; 3];
    let mut out = vec![];
    let mut ramp_um = 0.0f64;
    let mut what = vec![];
    for e in effects {
        let EffectConfig::GuideStraightness(g) = e else {
            out.push(e.clone());
            continue;
        };
        let mut g = g.clone();
        let k = g.knots_mm.clone();
        let span = match (k.first(), k.last()) {
            (Some(a), Some(b)) => b - a,
            _ => 0.0,
        };
        let mean = k.iter().sum::<f64>() / k.len().max(1) as f64;
        for (b, v) in g.straightness.iter_mut() {
            // (index in S, sign) for a table of g.axis towards b.
            let slot = match (g.axis, *b) {
                (Axis::Y, Axis::X) => (0, 1.0),
                (Axis::X, Axis::Y) => (0, -1.0),
                (Axis::Z, Axis::X) => (1, 1.0),
                (Axis::X, Axis::Z) => (1, -1.0),
                (Axis::Z, Axis::Y) => (2, 1.0),
                (Axis::Y, Axis::Z) => (2, -1.0),
                _ => continue,
            };
            let Some(m) = slope(&k, v) else { continue };
            for (vj, kj) in v.iter_mut().zip(&k) {
                *vj -= m * (kj - mean);
            }
            s[slot.0] += slot.1 * m;
            ramp_um = ramp_um.max((m * span).abs() * 1e3);
            if (m * span).abs() < 1e-5 {
                continue; // under 0.01 µm over the travel: not worth a word
            }
            what.push(format!(
                "{:.1} µrad from the ramp of the {} guide's straightness towards {}",
                m * 1e6,
                g.axis.name(),
                b.name()
            ));
        }
        out.push(EffectConfig::GuideStraightness(g));
    }
    if what.is_empty() || !s.iter().all(|v| v.is_finite()) {
        return None;
    }
    out.push(squareness_config(ds, s)?);
    Some(Squareness {
        effects: out,
        s_rad: s,
        ramp_um,
        what: format!(
            "squareness xy {:.1}, xz {:.1}, yz {:.1} µrad ({})",
            s[0] * 1e6,
            s[1] * 1e6,
            s[2] * 1e6,
            what.join("; ")
        ),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn structure(kind: &str, axis: &str, period: Option<f64>, terms: &[&str]) -> Structure {
        Structure {
            kind: kind.into(),
            axis: axis.into(),
            period_mm: period,
            amplitude_um: 1.0,
            explained: 0.5,
            custom_terms: terms.iter().map(|t| t.to_string()).collect(),
            harmonic: None,
            profile: None,
        }
    }

    #[test]
    fn a_period_is_named_a_cyclic_error() {
        let s = structure(
            "period",
            "x",
            Some(1.51412),
            &["x:sin(2*pi*x/1.51412)", "x:cos(2*pi*x/1.51412)"],
        );
        let c = custom_effect(&s).expect("builds");
        assert_eq!(c.config.id(), "cyclic_x_1p514mm");
        assert_eq!(c.what, "cyclic error along x, period 1.514 mm");
        assert_eq!(c.config.params(), vec![0.0, 0.0]);
        let r = custom_effect(&structure("reversal", "y", None, &["y:sign(vy)"])).unwrap();
        assert_eq!(r.config.id(), "reversal_y");
        // Terms that do not parse are not offered.
        assert!(custom_effect(&structure("period", "x", Some(2.0), &["x:sin(("])).is_none());
        assert!(custom_effect(&structure("period", "q", Some(2.0), &["q:x"])).is_none());
    }

    #[test]
    fn slope_of_a_ramp() {
        let x = [0.0, 100.0, 200.0, 300.0];
        let v: Vec<f64> = x.iter().map(|a| 3e-6 * a + 0.01).collect();
        assert!((slope(&x, &v).unwrap() - 3e-6).abs() < 1e-15);
        assert!(slope(&[1.0, 1.0, 1.0], &[0.0, 1.0, 2.0]).is_none());
    }
}
