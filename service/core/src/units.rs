//! One table of the units parameters and results are stated in, for every effect, procedure,
//! report, text and JSON output.
//!
//! * A fitted **parameter's name** ends with its unit in parentheses — `k_u (mm/mm)`,
//!   `P[0][x]x (mm per mm/s²)` — and the unit is one of [`PARAMETER_UNITS`]; its value is in
//!   that unit. [`name_unit`] reads it, [`check_name`] checks it.
//! * A **JSON key** or CSV column states its unit by its suffix — `radius_um`, `speed_mm_s`,
//!   `alpha_per_k` — one of [`KEY_SUFFIXES`]; its value is in that unit. [`key_unit`] reads it.
//! * A **custom term's coefficient** carries the unit of its expression: the correction is in
//!   mm, so a term `vx` (mm/s) has a coefficient in `mm per mm/s`, a term `sin(2*pi*x/4)`
//!   (a number) one in `mm`. [`expression_dim`] works out the expression's dimension from the
//!   signals' units ([`signal_dim`]); [`coefficient_unit`] states the coefficient's.
//!
//! * A **JSON output** is walked key by key by [`check_json`]: every number's key states its
//!   unit or is a count, id or ratio of [`NUMBER_KEYS`] (`tests/tests/cli_units.rs` walks the
//!   CLI's outputs).
//!
//! Dimensions are powers of length (mm), time (s) and temperature (K); angles, counts and ids
//! are numbers.

pub use crate::dim::Dim;
use crate::expr::Expr;

/// The units a parameter's name may state (in its trailing parentheses), with what they mean.
pub const PARAMETER_UNITS: &[(&str, &str)] = &[
    ("mm", "length"),
    ("µm", "length, micrometres"),
    ("rad", "angle"),
    ("µrad", "angle, microradians"),
    ("°", "angle, degrees"),
    ("rad/Hz", "phase lag per rotation frequency"),
    ("rad/Hz²", "phase lag per squared rotation frequency"),
    ("1/Hz", "relative gain per rotation frequency"),
    ("1/Hz²", "relative gain per squared rotation frequency"),
    ("1/K", "expansion coefficient"),
    ("mm/K", "drift per kelvin"),
    (
        "mm/mm",
        "deflection per deflection (probe-force compliance)",
    ),
    ("µm/mm", "micrometres per millimetre of deflection"),
    (
        "mm per mm/s²",
        "deflection per acceleration (s²; 1 mm per mm/s² = 10⁶ µm per m/s²)",
    ),
    (
        "µm per m/s²",
        "deflection per acceleration, engineering unit",
    ),
    ("s", "time"),
    ("Hz", "frequency"),
    ("ppm", "relative length, parts per million"),
    ("1", "a number"),
];

/// JSON keys and CSV columns: the suffix that states the unit, longest first.
pub const KEY_SUFFIXES: &[(&str, &str)] = &[
    // P, the deflection per acceleration: as stored (s², the effect's `mm per mm/s²`) or in
    // the engineering unit (1 mm per mm/s² = 10⁶ µm per m/s²).
    ("_mm_per_mm_s2", "mm per mm/s²"),
    ("_um_per_m_s2", "µm per m/s²"),
    ("_um_per_mm", "µm/mm"),
    ("_mm_per_mm", "mm/mm"),
    ("_rad_per_hz2", "rad/Hz²"),
    ("_rad_per_hz", "rad/Hz"),
    ("_per_hz2", "1/Hz²"),
    ("_per_hz", "1/Hz"),
    ("_mm_per_k", "mm/K"),
    ("_um_per_k", "µm/K"),
    ("_per_k", "1/K"),
    ("_mm_s2", "mm/s²"),
    ("_mm_s", "mm/s"),
    ("_ppm", "ppm"),
    ("_urad", "µrad"),
    ("_rad", "rad"),
    ("_deg", "°"),
    ("_mm", "mm"),
    ("_um", "µm"),
    ("_nm", "nm"),
    ("_ms", "ms"),
    ("_ns", "ns"),
    ("_hz", "Hz"),
    ("_s", "s"),
    ("_c", "°C"),
    ("_k", "K"),
];

/// Keys that are their own unit (`seconds`: s).
pub const UNIT_KEYS: &[(&str, &str)] = &[("seconds", "s"), ("ppm", "ppm")];

/// The unit a JSON key or CSV column states by its suffix (`radius_um` → `µm`). A key's
/// standard uncertainty is the key with `_u` or `_sigma` after it (`pitch_rad_u`), in the same
/// unit.
pub fn key_unit(key: &str) -> Option<&'static str> {
    let k = key.to_ascii_lowercase();
    // `…_mm_u`, `…_rad_sigma`: not after a one-letter unit (`probe_k_u` is no kelvin).
    let k = ["_u", "_sigma"]
        .iter()
        .find_map(|s| {
            k.strip_suffix(s).filter(|b| {
                KEY_SUFFIXES
                    .iter()
                    .any(|(x, _)| x.len() > 2 && b.ends_with(x) && b.len() > x.len())
            })
        })
        .unwrap_or(&k);
    if let Some((_, u)) = UNIT_KEYS.iter().find(|(n, _)| *n == k) {
        return Some(u);
    }
    KEY_SUFFIXES
        .iter()
        .find(|(s, _)| k.ends_with(s) && k.len() > s.len())
        .map(|(_, u)| *u)
}

/// JSON keys whose values are numbers without a unit: counts, ids, versions, orders, fractions,
/// statistics. A key is one of these when it is listed, or ends (after `_`) or starts (before
/// `_`) with one of [`NUMBER_KEY_WORDS`].
pub const NUMBER_KEYS: &[&str] = &[
    "version",
    "parent_version",
    "calibration_version",
    "tip",
    "reference_tip",
    "id",
    "bag",
    "degree",
    "order",
    "powers",
    "segments",
    "k",
    "explained",
    "delta_bic",
    "direction",
    "feature",
    "probes",
    "alarms",
    "seed",
    "machine_seed",
    "sigma_scale",
    "birge",
    "stations",
    "r2",
    "harmonic",
];

/// Keys of objects of counts (`"dropped": {"no_arc": 3}`): every key inside is a count.
pub const COUNT_MAPS: &[&str] = &["dropped", "effect_points", "counts", "samples"];

/// Words that make a key a count or another number (`points`, `n_scans`, `cell_chi2`,
/// `clear_fraction`, `max_gap_periods`).
pub const NUMBER_KEY_WORDS: &[&str] = &[
    "points", "samples", "readings", "messages", "resets", "scans", "count", "total", "n", "id",
    "index", "seq", "version", "order", "pending", "periods", "fraction", "ratio", "chi2", "bic",
    "aic", "dof", "unpaired", "flagged", "knots", "folds", "rank", "cond", "seed",
];

/// Whether a key holds a number without a unit (see [`NUMBER_KEYS`]).
pub fn key_is_number(key: &str) -> bool {
    let k = key.to_ascii_lowercase();
    NUMBER_KEYS.contains(&k.as_str())
        || NUMBER_KEY_WORDS.iter().any(|w| {
            k == *w
                || k.strip_suffix(w)
                    .is_some_and(|b| b.ends_with('_') || b.ends_with('.'))
                || k.strip_prefix(w).is_some_and(|b| b.starts_with('_'))
        })
}

/// Checks a JSON key that holds a number: it states its unit by its suffix ([`key_unit`]), is a
/// parameter's name with its unit ([`check_name`]), or is a number ([`key_is_number`]).
/// `Ok(Some(unit))`, `Ok(None)` for a number.
pub fn check_key(key: &str) -> Result<Option<&str>, String> {
    if key.trim_end().ends_with(')') {
        return check_name(key).map(Some);
    }
    if let Some(u) = key_unit(key) {
        return Ok(Some(u));
    }
    if key_is_number(key) {
        return Ok(None);
    }
    Err(format!(
        "`{key}` holds a physical value? It states no unit (a suffix of the table: `_um`, `_mm_s`, …) and is no count, id or ratio of the table"
    ))
}

/// Keys of an object named by its `name` (`{"name": "P[x][x] (mm per mm/s²)", "value": …,
/// "sigma": …}`): their values are in the name's unit.
pub const NAMED_VALUE_KEYS: &[&str] = &[
    "value",
    "sigma",
    "sigma_stat",
    "penalty_shift",
    "fold_spread",
    "sigma_scan",
    "model_spread",
    "truth",
    "true",
    "error",
    "before",
    "after",
    "start",
    "fitted",
    "mean",
    "min",
    "max",
];

fn is_numeric(v: &serde_json::Value) -> bool {
    match v {
        serde_json::Value::Number(_) => true,
        serde_json::Value::Array(a) => {
            a.iter().any(|x| !x.is_null()) && a.iter().all(|x| x.is_null() || is_numeric(x))
        }
        _ => false,
    }
}

/// Walks every key of a JSON output and returns what states no unit (each with its path):
/// a key holding a number that is neither suffixed with a unit, nor a parameter's name with a
/// unit, nor a count, id or ratio ([`check_key`]); a parameter's `name` without a unit of the
/// table. Inside an object under a key that states a unit (`"error_at_f1_um": {"max": …}`) or
/// is a count (`"dropped": {"no_arc": 3}`), the keys inherit it; in an object with a `name`,
/// [`NAMED_VALUE_KEYS`] are in the name's unit. A calibration document's effects (objects with
/// a `kind` under `effects`) state their parameters' units by their parameter names
/// (`Effect::param_names`, checked against [`check_name`] by the effects' own test and by
/// the CLI units test): they are not walked here.
pub fn check_json(v: &serde_json::Value) -> Vec<String> {
    let mut bad = vec![];
    walk(v, "", false, &mut bad);
    bad
}

fn walk(v: &serde_json::Value, path: &str, inherited: bool, bad: &mut Vec<String>) {
    use serde_json::Value;
    match v {
        Value::Object(o) => {
            let name = ["name", "param", "parameter"]
                .iter()
                .find_map(|k| o.get(*k).and_then(|n| n.as_str()));
            let named = match name {
                Some(n) if o.keys().any(|k| NAMED_VALUE_KEYS.contains(&k.as_str())) => {
                    // `effect: name (unit)` or `tip1.radius_mm`.
                    let bare = n.rsplit(": ").next().unwrap_or(n);
                    let ok = check_name(bare).is_ok() || key_unit(bare).is_some();
                    if !ok {
                        bad.push(format!(
                            "{path}: parameter `{n}` states no unit of the table"
                        ));
                    }
                    true
                }
                _ => false,
            };
            for (k, x) in o {
                let p = format!("{path}.{k}");
                if k == "effects"
                    && x.as_array()
                        .is_some_and(|a| a.iter().all(|e| e.get("kind").is_some()))
                {
                    continue;
                }
                let keyed = check_key(k);
                if let Err(m) = &keyed {
                    if k.trim_end().ends_with(')') {
                        bad.push(format!("{p}: {m}"));
                        continue;
                    }
                }
                let ok =
                    keyed.is_ok() || inherited || (named && NAMED_VALUE_KEYS.contains(&k.as_str()));
                if is_numeric(x) {
                    if !ok {
                        bad.push(format!("{p}: {}", keyed.unwrap_err()));
                    }
                } else {
                    let inherit =
                        inherited || key_unit(k).is_some() || COUNT_MAPS.contains(&k.as_str());
                    walk(x, &p, inherit, bad);
                }
            }
        }
        Value::Array(a) => {
            for x in a {
                walk(x, &format!("{path}[]"), inherited, bad);
            }
        }
        Value::String(s) if !inherited => {
            // A parameter named in a list (`"servo_phase: φ_z b1 (rad/Hz)"`).
            if let Some((effect, name)) = s.split_once(": ") {
                let effect_like = !effect.is_empty()
                    && effect
                        .chars()
                        .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_');
                if effect_like && name.len() < 60 && name.ends_with(')') && !name.contains(": ") {
                    if let Err(m) = check_name(name) {
                        bad.push(format!("{path}: {effect}: {m}"));
                    }
                }
            }
        }
        _ => {}
    }
}

/// The unit a parameter's name states: the text in its last parentheses (`k_u (mm/mm)` →
/// `mm/mm`).
pub fn name_unit(name: &str) -> Option<&str> {
    let n = name.trim_end();
    let body = n.strip_suffix(')')?;
    let open = body.rfind('(')?;
    Some(body[open + 1..].trim())
}

/// Checks a parameter's name: it states a unit, and one of [`PARAMETER_UNITS`] (or, for a
/// custom term, `mm per <a unit>` built by [`coefficient_unit`]).
pub fn check_name(name: &str) -> Result<&str, String> {
    let u = name_unit(name).ok_or_else(|| format!("`{name}`: no unit in parentheses"))?;
    if PARAMETER_UNITS.iter().any(|(k, _)| *k == u) {
        return Ok(u);
    }
    if let Some(rest) = u.strip_prefix("mm per ") {
        if parse_unit(rest).is_some() {
            return Ok(u);
        }
    }
    Err(format!("`{name}`: `{u}` is not a unit of the table"))
}

/// Reads a unit written as [`Dim::text`] writes it (`mm/s²`, `1/K`, `mm`, `Hz`).
pub fn parse_unit(u: &str) -> Option<Dim> {
    if u == "Hz" {
        return Some(Dim { mm: 0, s: -1, k: 0 });
    }
    let (num, den) = u.split_once('/').unwrap_or((u, ""));
    let factor = |f: &str| -> Option<Dim> {
        let (sym, p) = match f.strip_suffix('²') {
            Some(s) => (s, 2),
            None => match f.strip_suffix('³') {
                Some(s) => (s, 3),
                None => (f, 1),
            },
        };
        let d = match sym {
            "mm" => Dim::MM,
            "s" => Dim { mm: 0, s: 1, k: 0 },
            "K" => Dim { mm: 0, s: 0, k: 1 },
            "1" => Dim::ONE,
            _ => return None,
        };
        Some(d.pow(p))
    };
    let mut d = Dim::ONE;
    for f in num.split('·').filter(|f| !f.is_empty()) {
        d = d.mul(factor(f)?);
    }
    for f in den.split('·').filter(|f| !f.is_empty()) {
        d = d.div(factor(f)?);
    }
    Some(d)
}

/// The dimension of a signal a custom expression may use (see
/// [`crate::effects::custom::SIGNALS`]); temperatures `T_<sensor>` are K (a difference of
/// °C); angles, the rotation axis, ids are numbers.
pub fn signal_dim(name: &str) -> Option<Dim> {
    let mm = Dim::MM;
    let per_s = Dim { mm: 0, s: -1, k: 0 };
    Some(match name {
        "x" | "y" | "z" | "ex" | "ey" | "ez" | "cx" | "cy" | "cz" | "r" | "du" | "dv" | "dw"
        | "defl" => mm,
        "vx" | "vy" | "vz" | "speed" => mm.mul(per_s),
        "ax" | "ay" | "az" | "acc" => mm.mul(per_s.pow(2)),
        "f" => per_s,
        "t" => Dim { mm: 0, s: 1, k: 0 },
        "wz" | "a1" | "a2" | "tip" | "seg" | "pi" | "e" => Dim::ONE,
        n if n.starts_with("T_") => Dim { mm: 0, s: 0, k: 1 },
        _ => return None,
    })
}

/// The dimension of a custom expression: `None` when it adds or compares quantities of
/// different units, raises to a power that is not a whole constant, or takes a function of a
/// quantity that is not a number (`sin(x)` with x in mm: the coefficient has no one unit).
pub fn expression_dim(src: &str) -> Option<Dim> {
    let e = Expr::parse(src).ok()?;
    e.dimension(&|v: &str| signal_dim(v))
}

/// The unit of a custom term's coefficient, the correction being in mm: `mm` for a number,
/// `mm per mm/s` for a velocity, …; for an expression of mixed units, `mm per unit of the
/// expression (mixed units)`.
pub fn coefficient_unit(expr: &str) -> String {
    match expression_dim(expr) {
        Some(Dim::ONE) => "mm".into(),
        Some(d) => format!("mm per {}", d.text()),
        None => "mm per unit of the expression (mixed units)".into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_effect_names_each_parameter_with_a_unit_of_the_table() {
        // Every effect of the library, as `calib example --all-effects` and the lab build them.
        let mut effects: Vec<EffectConfig> = crate::Calibration::example("m1").effects;
        use crate::effects::*;
        use crate::sample::Axis;
        effects.extend([
            EffectConfig::AccelDeflection(accel_deflection::Config::zeros(2, true)),
            EffectConfig::ServoPhase(servo_phase::Config::zeros(2)),
            EffectConfig::ServoGain(servo_gain::Config::zeros(1, vec![1, 2])),
            EffectConfig::StylusThermal(stylus_thermal::Config::zeros(true)),
            EffectConfig::ScaleThermal(scale_thermal::Config::zeros()),
            EffectConfig::ProbeForce(probe_force::Config {
                id: None,
                k: [0.01, 0.01, 0.005],
                per_tip: Default::default(),
            }),
            EffectConfig::GuideStraightness(guide_straightness::Config::zeros(
                Axis::X,
                0.0,
                1000.0,
                5,
                true,
            )),
            EffectConfig::Custom(custom::Config {
                id: "c".into(),
                dynamic: true,
                terms: vec![
                    custom::Term {
                        axis: Axis::X,
                        expr: "sin(2*pi*x/4)".into(),
                    },
                    custom::Term {
                        axis: Axis::Y,
                        expr: "vx*abs(ax)".into(),
                    },
                ],
                coefficients: vec![0.0, 0.0],
            }),
            EffectConfig::ProbeLobing(probe_lobing::Config::zeros(3, 4)),
            EffectConfig::ThermalDrift(thermal_drift::Config::zeros(&[(
                "air".into(),
                600.0,
                20.0,
            )])),
            EffectConfig::RigidBody(rigid_body::Config::zeros(
                rigid_body::Chain::MovingBridge,
                2,
                [[0.0, 1000.0]; 3],
            )),
            EffectConfig::FeatureMap(feature_map::Config {
                values_mm: vec![0.0; 8],
                per_deflection: vec![0.0; 8],
                ..serde_json::from_str(r#"{"tip":1,"segments":[],"center_mm":[0,0],"values_mm":[],"place_tolerance_mm":1}"#)
                    .expect("a feature map")
            }),
        ]);
        let mut bad = vec![];
        let mut n = 0;
        for e in &effects {
            for name in e.param_names() {
                n += 1;
                if let Err(m) = check_name(&name) {
                    bad.push(format!("{}: {m}", e.kind()));
                }
            }
        }
        assert!(n > 50, "{n} parameters");
        assert!(
            bad.is_empty(),
            "{} of {n} names:\n{}",
            bad.len(),
            bad.join("\n")
        );
    }

    #[test]
    fn a_custom_coefficient_carries_the_unit_of_its_expression() {
        assert_eq!(coefficient_unit("sin(2*pi*x/4)"), "mm");
        assert_eq!(coefficient_unit("vx"), "mm per mm/s");
        assert_eq!(coefficient_unit("vx*abs(ax)"), "mm per mm²/s³");
        assert_eq!(coefficient_unit("ax"), "mm per mm/s²");
        assert_eq!(coefficient_unit("(T_air-20)*x"), "mm per mm·K");
        assert_eq!(coefficient_unit("f^2"), "mm per 1/s²");
        assert_eq!(coefficient_unit("sign(vx)"), "mm");
        assert_eq!(coefficient_unit("sqrt(x*x+y*y)"), "mm per mm");
        // Adding a speed to a length has no one unit, nor has comparing them; an unknown signal
        // none at all.
        assert!(coefficient_unit("x+vx").contains("mixed"));
        assert!(coefficient_unit("min(x, vx)").contains("mixed"));
        assert!(coefficient_unit("x^y").contains("mixed"));
        // Every unit the table builds is one `check_name` accepts.
        for e in ["vx", "ax", "f^2", "(T_air-20)*x"] {
            let name = format!("x·[{e}] ({})", coefficient_unit(e));
            assert!(check_name(&name).is_ok(), "{name}");
        }
    }

    #[test]
    fn the_json_walk_finds_what_states_no_unit() {
        let v: serde_json::Value = serde_json::from_str(
            r#"{"version": 3, "points": 10, "rms_um": 0.1, "pitch_rad_u": [1e-6],
                "error_at_f1_um": {"max": 1.0}, "dropped": {"no_arc": 2},
                "params": {"tip1.radius_mm": 1.5, "k_u (mm/mm)": 0.01},
                "rotation": [{"name": "rotation_x_rad", "value": 1e-5, "sigma": 1e-6}],
                "unidentifiable": ["servo_phase: φ_z b1 (rad/Hz)"],
                "effects": [{"kind": "probe_force", "k": [0.01, 0.01, 0.005]}]}"#,
        )
        .unwrap();
        assert_eq!(check_json(&v), Vec::<String>::new());
        let v: serde_json::Value = serde_json::from_str(
            r#"{"stiffness": 0.01, "params": {"tip1.probe_k_u": 0.01, "k (furlongs)": 1},
                "fit": [{"name": "k_u", "value": 0.01}],
                "unidentifiable": ["servo_phase: φ_z b1 (rad/s)"]}"#,
        )
        .unwrap();
        let bad = check_json(&v);
        assert_eq!(bad.len(), 5, "{bad:#?}");
        for needle in ["stiffness", "probe_k_u", "furlongs", "`k_u`", "rad/s"] {
            assert!(bad.iter().any(|b| b.contains(needle)), "{needle}: {bad:#?}");
        }
    }

    #[test]
    fn keys_state_their_unit_by_suffix() {
        assert_eq!(key_unit("radius_at_zero_force_mm"), Some("mm"));
        assert_eq!(key_unit("circularity_um"), Some("µm"));
        assert_eq!(key_unit("speed_mm_s"), Some("mm/s"));
        assert_eq!(key_unit("k_um_per_mm"), Some("µm/mm"));
        assert_eq!(key_unit("alpha_per_k"), Some("1/K"));
        assert_eq!(key_unit("points"), None);
        assert_eq!(key_unit("pitch_rad_u"), Some("rad"));
        assert_eq!(key_unit("tip1.probe_k_u"), None);
        assert_eq!(key_unit("tip1.probe_k_u_mm_per_mm"), Some("mm/mm"));
        assert_eq!(key_unit("seconds"), Some("s"));
        assert_eq!(key_unit("dynamics.P_xx_um_per_m_s2"), Some("µm per m/s²"));
        assert_eq!(key_unit("P_xx_mm_per_mm_s2"), Some("mm per mm/s²"));
        assert!(
            key_is_number("n_scans") && key_is_number("cell_chi2") && key_is_number("feature_id")
        );
        assert!(!key_is_number("noise_floor") && !key_is_number("stiffness"));
        assert_eq!(name_unit("k_u (mm/mm)"), Some("mm/mm"));
        assert_eq!(name_unit("P[0][x]x (mm per mm/s²)"), Some("mm per mm/s²"));
        assert!(check_name("k_u").is_err() && check_name("k_u (furlongs)").is_err());
    }
}
