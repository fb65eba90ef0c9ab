//! The moves the lab considers: the library's candidate effects with their variants, a
//! configuration from a candidate name (`kind:options`), the variant key that tells two
//! configurations apart, and the moves `lab add NAME` names.

use super::dataset::{axis_span, Dataset};
use super::types::{Candidate, Move};
use super::LabError;
use crate::effects::{self as fx, EffectConfig};
use crate::sample::Axis;

/// The candidate effects of the library not in the calibration, with their variants.
pub fn library_candidates(ds: &Dataset) -> Vec<(String, EffectConfig)> {
    moves(ds, &ds.calibration.effects)
        .into_iter()
        .filter(|c| c.action == Move::Add)
        .filter_map(|c| c.config.map(|cfg| (c.effect, cfg)))
        .collect()
}

/// The variant of a config, by its configuration: the kind and the options that change what
/// it models (a guide's axis, the axis its angular term turns about and which tables it has; a
/// rigid body's chain, order, spline or polynomial and its errors; for every other kind its
/// parameters' names, which spell its order, split, per-tip and powers), never its values nor
/// sizes that follow the data's span (a table's knots). Parameter names alone do not say
/// which axis a guide's pitch turns about, so `about=y` and `about=z` looked alike.
pub fn variant_key(c: &EffectConfig) -> String {
    match c {
        EffectConfig::GuideStraightness(g) => {
            let about = g.pitch_about.unwrap_or(match g.axis {
                Axis::X => Axis::Y,
                Axis::Y => Axis::X,
                Axis::Z => Axis::Y,
            });
            let tables: Vec<&str> = g.straightness.keys().map(|a| a.name()).collect();
            format!(
                "guide_straightness:axis={},straightness={},{}",
                g.axis.name(),
                tables.join("+"),
                if g.pitch_rad.is_some() {
                    format!("about={}", about.name())
                } else {
                    "no pitch".into()
                }
            )
        }
        EffectConfig::RigidBody(r) => {
            let errors: Vec<String> = r.errors.keys().map(|e| e.name().to_string()).collect();
            format!(
                "rigid_body:chain={:?},order={},{},errors={}",
                r.chain,
                r.order,
                if r.spline_segments.is_some() {
                    "spline"
                } else {
                    "polynomial"
                },
                errors.join("+")
            )
        }
        _ => format!("{}:{}", c.kind(), c.param_names().join("|")),
    }
}

/// Two configs are the same variant when their [`variant_key`]s agree.
fn same_variant(a: &EffectConfig, b: &EffectConfig) -> bool {
    a.kind() == b.kind() && variant_key(a) == variant_key(b)
}

fn guide_axis(c: &EffectConfig) -> Option<Axis> {
    match c {
        EffectConfig::GuideStraightness(g) => Some(g.axis),
        _ => None,
    }
}

/// Every move the lab considers from `model`: library effects (all variants) not in it,
/// other variants of those in it, and dropping each.
pub fn moves(ds: &Dataset, model: &[EffectConfig]) -> Vec<Candidate> {
    let mut v = vec![];
    for kind in fx::KINDS {
        if kind == "custom" {
            continue;
        }
        let present: Vec<&EffectConfig> = model.iter().filter(|e| e.kind() == kind).collect();
        for name in variants(kind, ds) {
            let Ok(mut cfg) = candidate(&name, ds) else {
                continue;
            };
            // Guides of different axes are different effects; every other kind is one.
            let same: Vec<&&EffectConfig> = present
                .iter()
                .filter(|e| guide_axis(e) == guide_axis(&cfg))
                .collect();
            match same.first() {
                None => {
                    if !present.is_empty() {
                        if let Some(a) = guide_axis(&cfg) {
                            cfg.set_id(Some(format!("guide_straightness_{}", a.name())));
                        }
                    }
                    if model.iter().any(|e| e.id() == cfg.id()) {
                        continue;
                    }
                    v.push(Candidate {
                        action: Move::Add,
                        effect: name,
                        replaces: None,
                        config: Some(cfg),
                    });
                }
                Some(e) if !same_variant(e, &cfg) => {
                    // The swap keeps an id made from the kind (`guide_straightness_x`), so
                    // versions compare effect by effect; a name of its own (`squareness`
                    // for a squareness-only rigid body) says what the replaced effect was and
                    // is not carried over to another variant.
                    let id = e.id();
                    let keep = id != cfg.kind() && id.starts_with(cfg.kind());
                    cfg.set_id(keep.then(|| id.clone()));
                    v.push(Candidate {
                        action: Move::Swap,
                        effect: name,
                        replaces: Some(id),
                        config: Some(cfg),
                    });
                }
                Some(_) => {}
            }
        }
    }
    for e in model {
        v.push(Candidate {
            action: Move::Drop,
            effect: e.id(),
            replaces: Some(e.id()),
            config: None,
        });
    }
    v
}

fn tips(ds: &Dataset) -> Vec<u32> {
    let t: std::collections::BTreeSet<u32> = ds.points.iter().map(|p| p.ctx.tip_id).collect();
    t.into_iter().collect()
}

fn variants(kind: &str, ds: &Dataset) -> Vec<String> {
    let several_tips = tips(ds).len() > 1;
    let mut v: Vec<String> = match kind {
        "accel_deflection" => vec![
            "accel_deflection".into(),
            "accel_deflection:full".into(),
            "accel_deflection:full,order=1".into(),
        ],
        "servo_gain" => vec!["servo_gain".into(), "servo_gain:powers=1+2".into()],
        "servo_phase" => vec![
            "servo_phase".into(),
            "servo_phase:static".into(),
            "servo_phase:static,direction".into(),
        ],
        "stylus_thermal" => vec!["stylus_thermal".into(), "stylus_thermal:split".into()],
        "probe_force" => vec!["probe_force".into()],
        "guide_straightness" => Axis::ALL
            .iter()
            .filter(|a| axis_span(ds, **a).1 - axis_span(ds, **a).0 > 100.0)
            .flat_map(|a| {
                Axis::ALL
                    .iter()
                    .filter(|r| *r != a)
                    .map(|r| format!("guide_straightness:axis={},about={}", a.name(), r.name()))
                    .collect::<Vec<_>>()
            })
            .collect(),
        "rigid_body" => vec![
            "rigid_body:order=2".into(),
            "rigid_body:order=3".into(),
            "rigid_body:spline".into(),
        ],
        "probe_lobing" => vec!["probe_lobing".into()],
        k => vec![k.to_string()],
    };
    if several_tips && matches!(kind, "probe_force" | "stylus_thermal") {
        v.push(format!("{kind}:per_tip"));
    }
    v
}

/// A zero-parameter effect from a candidate name: `kind[:option,option=value…]`.
/// Options: accel_deflection `full`, `order=0|1|2`; servo_gain `powers=1+2`; stylus_thermal
/// `split`, `per_tip`; probe_force `per_tip`; guide_straightness `axis=x|y|z`, `about=x|y|z`
/// (rotation axis of its angular term), `knots=N`; servo_phase `order=0|1`, `static` (the
/// term that keeps its sign with the scan direction), `static,direction` (both); rigid_body
/// `order=1…4`, `spline` (cubic B-spline tables, `step=MM` between knots, default 50),
/// `chain=moving_bridge|fixed_bridge|cantilever|horizontal_arm`; probe_lobing
/// `harmonics=2…8`.
pub fn candidate(name: &str, ds: &Dataset) -> Result<EffectConfig, LabError> {
    let (kind, opts) = name.split_once(':').unwrap_or((name, ""));
    let mut o = std::collections::BTreeMap::new();
    for kv in opts.split(',').filter(|s| !s.is_empty()) {
        let (k, v) = kv.split_once('=').unwrap_or((kv, ""));
        o.insert(k.to_string(), v.to_string());
    }
    let bad = |m: String| LabError::Data(format!("effect `{name}`: {m}"));
    let order = |o: &std::collections::BTreeMap<String, String>| -> Result<u8, LabError> {
        match o.get("order").map(|s| s.as_str()) {
            None => Ok(0),
            Some(s) => s
                .parse::<u8>()
                .ok()
                .filter(|v| *v <= 2)
                .ok_or_else(|| bad("order must be 0, 1 or 2".into())),
        }
    };
    let cfg = match kind {
        "accel_deflection" => EffectConfig::AccelDeflection(fx::accel_deflection::Config::zeros(
            order(&o)?,
            !o.contains_key("full"),
        )),
        "servo_phase" => EffectConfig::ServoPhase(fx::servo_phase::Config::zeros_variant(
            order(&o)?,
            !o.contains_key("static") || o.contains_key("direction"),
            o.contains_key("static"),
        )),
        "servo_gain" => {
            let powers = match o.get("powers") {
                None => vec![2],
                Some(s) => s
                    .split('+')
                    .map(|p| p.parse::<u32>().map_err(|_| bad("powers like 1+2".into())))
                    .collect::<Result<_, _>>()?,
            };
            EffectConfig::ServoGain(fx::servo_gain::Config::zeros(order(&o)?, powers))
        }
        "stylus_thermal" => EffectConfig::StylusThermal(if o.contains_key("per_tip") {
            fx::stylus_thermal::Config::zeros_per_tip(&tips(ds), o.contains_key("split"))
        } else {
            fx::stylus_thermal::Config::zeros(o.contains_key("split"))
        }),
        "scale_thermal" => EffectConfig::ScaleThermal(fx::scale_thermal::Config::zeros()),
        "probe_force" => EffectConfig::ProbeForce(if o.contains_key("per_tip") {
            fx::probe_force::Config::zeros_per_tip(&tips(ds))
        } else {
            fx::probe_force::Config::zeros()
        }),
        "probe_lobing" => {
            let h = match o.get("harmonics") {
                None => 5,
                Some(s) => s
                    .parse::<u8>()
                    .ok()
                    .filter(|h| (2..=8).contains(h))
                    .ok_or_else(|| bad("harmonics must be 2…8".into()))?,
            };
            EffectConfig::ProbeLobing(fx::probe_lobing::Config::zeros(h, 0))
        }
        "rigid_body" => {
            let ord = match o.get("order") {
                None => 2,
                Some(s) => s
                    .parse::<u8>()
                    .ok()
                    .filter(|v| (1..=4).contains(v))
                    .ok_or_else(|| bad("order must be 1…4".into()))?,
            };
            let chain = match o
                .get("chain")
                .map(|s| s.as_str())
                .unwrap_or("moving_bridge")
            {
                "moving_bridge" => fx::rigid_body::Chain::MovingBridge,
                "fixed_bridge" => fx::rigid_body::Chain::FixedBridge,
                "cantilever" => fx::rigid_body::Chain::Cantilever,
                "horizontal_arm" => fx::rigid_body::Chain::HorizontalArm,
                c => {
                    return Err(bad(format!(
                        "chain `{c}` (moving_bridge, fixed_bridge, cantilever, horizontal_arm)"
                    )))
                }
            };
            let ranges = Axis::ALL.map(|a| {
                let (lo, hi) = axis_span(ds, a);
                if hi - lo > 1.0 {
                    [lo.floor(), hi.ceil()]
                } else {
                    [lo.floor() - 1.0, lo.floor() + 1.0]
                }
            });
            if o.contains_key("spline") {
                let step = match o.get("step") {
                    None => 50.0,
                    Some(s) => s
                        .parse::<f64>()
                        .ok()
                        .filter(|v| (5.0..=1000.0).contains(v))
                        .ok_or_else(|| bad("step must be 5…1000 (mm between knots)".into()))?,
                };
                EffectConfig::RigidBody(fx::rigid_body::Config::zeros_spline(chain, ranges, step))
            } else {
                EffectConfig::RigidBody(fx::rigid_body::Config::zeros(chain, ord, ranges))
            }
        }
        "guide_straightness" => {
            let axis = match o.get("axis").map(|s| s.as_str()).unwrap_or("x") {
                "x" => Axis::X,
                "y" => Axis::Y,
                "z" => Axis::Z,
                a => return Err(bad(format!("axis `{a}` (x, y or z)"))),
            };
            let (lo, hi) = axis_span(ds, axis);
            // Not more than 1 mm, or no points at all (the span is then not finite).
            if (hi - lo).partial_cmp(&1.0) != Some(std::cmp::Ordering::Greater) {
                return Err(bad(format!(
                    "the data does not move along {} (scan along the axis' travel)",
                    axis.name()
                )));
            }
            let n = match o.get("knots") {
                Some(s) => s
                    .parse::<usize>()
                    .map_err(|_| bad("knots must be a number".into()))?,
                None => (((hi - lo) / 20.0).round() as usize + 1).clamp(3, 61),
            };
            let mut g = fx::guide_straightness::Config::zeros(axis, lo.floor(), hi.ceil(), n, true);
            if let Some(r) = o.get("about") {
                let r = match r.as_str() {
                    "x" => Axis::X,
                    "y" => Axis::Y,
                    "z" => Axis::Z,
                    r => return Err(bad(format!("about `{r}` (x, y or z)"))),
                };
                if r == axis {
                    return Err(bad(
                        "the angular error turns about an axis other than the moving one".into(),
                    ));
                }
                g.pitch_about = Some(r);
            }
            EffectConfig::GuideStraightness(g)
        }
        "custom" => return Err(bad("a custom effect needs terms (--term AXIS:EXPR)".into())),
        "feature_map" => {
            return Err(LabError::Data(
                "feature_map: a scan's dynamic map is measured, not fitted by the lab: \
                 `scancorr calibrate dynamic-map` (slow and fast scans of the feature at two \
                 deflections, e.g. `scancorr sim --program dynamic-map`)"
                    .into(),
            ))
        }
        "thermal_drift" => {
            return Err(LabError::Data(
                "thermal_drift: its sensors and lags are found from a drift recording (the \
                 displacement of the tool against the part with the structure's temperatures, \
                 over hours), not from artifact scans: `scancorr calibrate thermal-drift`"
                    .into(),
            ))
        }
        k => {
            return Err(LabError::Data(format!(
                "unknown effect `{k}` (known: {})",
                fx::KINDS.join(", ")
            )))
        }
    };
    Ok(cfg)
}

/// The moves `lab add NAME` considers: a variant (`kind:options`) or every variant of a kind,
/// each an addition or, when the model has that effect, a swap.
pub fn moves_named(ds: &Dataset, name: &str) -> Result<Vec<Candidate>, LabError> {
    let model = &ds.calibration.effects;
    let all = moves(ds, model);
    let picked: Vec<Candidate> = all
        .into_iter()
        .filter(|c| c.action != Move::Drop)
        .filter(|c| {
            if name.contains(':') {
                c.effect == name
            } else {
                c.effect.split(':').next() == Some(name)
            }
        })
        .collect();
    if !picked.is_empty() {
        return Ok(picked);
    }
    let cfg = candidate(name, ds)?; // names the problem (unknown effect, bad option)
    if model.iter().any(|e| same_variant(e, &cfg)) {
        return Err(LabError::Data(format!(
            "`{name}` is already in the model in this variant (use `lab fit` to refit it)"
        )));
    }
    Ok(vec![Candidate {
        action: Move::Add,
        effect: name.to_string(),
        replaces: None,
        config: Some(cfg),
    }])
}
