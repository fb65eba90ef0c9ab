//! The calibration store against damage, in-process: a store with two machines, `m1` intact
//! and `m2` damaged in one way per variant, is opened again; `m1` must still be served, `m2`
//! must be named as damaged (or, where its rows no longer carry its name, be gone and the rows
//! reported), and a new put for `m2` must heal it. Whole-database damage is a clear error
//! naming the file. The damage is done with raw SQL through the store's test hatch.

use scancorr_core::effects::*;
use scancorr_core::sample::Axis;
use scancorr_core::Calibration;
use scancorrd::store::{Store, StoreError, FILE_NAME, MAX_DOC_BYTES};
use std::path::PathBuf;

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!(
        "scancorr-service-store-{name}-{}",
        std::process::id()
    ));
    let _ = std::fs::remove_dir_all(&d);
    d
}

/// `m1` and `m2`, versions 1 and 2 each, 2 current.
fn two_machines(d: &PathBuf) {
    let mut s = Store::open(d).unwrap();
    for m in ["m1", "m2"] {
        for v in [1, 2] {
            assert_eq!(s.put(Calibration::example(m)).unwrap().version, v);
        }
    }
}

/// What the damage does to `m2`.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Expect {
    /// `m2` is listed and its current calibration is `Damaged` naming it.
    Damaged,
    /// No row carries the name `m2` any more: it is not listed, `current` is `Ok(None)`, and
    /// `damaged_rows` describes the rows.
    Vanished,
    /// The damage is outside `m2`'s current document: it is served; its history marks the
    /// damaged version.
    Intact,
    /// The store repaired the damage when opening: `m2` is served; `damaged_rows` says so.
    Repaired,
}
use Expect::*;

/// Rebuilds `calibration` without its constraints (NOT NULL, primary key), keeping affinities.
const LOOSE_CALIBRATION: &str = "CREATE TABLE c2 (machine TEXT, version INTEGER, parent INTEGER, note TEXT, created TEXT, doc TEXT);
     INSERT INTO c2 SELECT machine, version, parent, note, created, doc FROM calibration;
     DROP TABLE calibration; ALTER TABLE c2 RENAME TO calibration;";
/// Rebuilds `calibration` with no column types at all (no affinity: values keep their type).
const UNTYPED_CALIBRATION: &str = "CREATE TABLE c2 (machine, version, parent, note, created, doc);
     INSERT INTO c2 SELECT machine, version, parent, note, created, doc FROM calibration;
     DROP TABLE calibration; ALTER TABLE c2 RENAME TO calibration;";
/// Rebuilds `current` without its constraints.
const LOOSE_CURRENT: &str = "CREATE TABLE k2 (machine TEXT, version INTEGER);
     INSERT INTO k2 SELECT machine, version FROM current;
     DROP TABLE current; ALTER TABLE k2 RENAME TO current;";

const M2V2: &str = "WHERE machine = 'm2' AND version = 2";

/// (name, SQL, expectation, version the next put for `m2` gets).
fn variants() -> Vec<(&'static str, String, Expect, u64)> {
    let doc = |set: &str| format!("UPDATE calibration SET doc = {set} {M2V2};");
    let cur = |set: &str| format!("UPDATE current SET {set} WHERE machine = 'm2';");
    vec![
        // The current document.
        ("doc not JSON", doc("'{not json'"), Damaged, 3),
        ("doc truncated", doc("substr(doc, 1, 100)"), Damaged, 3),
        ("doc empty text", doc("''"), Damaged, 3),
        ("doc JSON of the wrong shape", doc(r#"'{"machine_id": "m2", "version": 2}'"#), Damaged, 3),
        ("doc a JSON array", doc("'[1, 2, 3]'"), Damaged, 3),
        ("doc for another machine", doc(r#"replace(doc, '"machine_id": "m2"', '"machine_id": "m1"')"#), Damaged, 3),
        ("doc names another version", doc(r#"replace(doc, '"version": 2', '"version": 7')"#), Damaged, 3),
        ("doc NULL", format!("{LOOSE_CALIBRATION} {}", doc("NULL")), Damaged, 3),
        ("doc stored as BLOB", doc("CAST(doc AS BLOB)"), Damaged, 3),
        ("doc INTEGER (text affinity: '42')", doc("42"), Damaged, 3),
        ("doc INTEGER (no affinity)", format!("{UNTYPED_CALIBRATION} {}", doc("42")), Damaged, 3),
        ("doc REAL (no affinity)", format!("{UNTYPED_CALIBRATION} {}", doc("2.5")), Damaged, 3),
        ("doc not UTF-8", doc("CAST(X'7b22ff22' AS TEXT)"), Damaged, 3),
        ("doc over the size limit", doc(&format!("doc || replace(hex(zeroblob({})), '0', ' ')", MAX_DOC_BYTES / 2 + 1)), Damaged, 3),
        // The current entry.
        ("current names a missing version", cur("version = 9"), Damaged, 3),
        ("current version TEXT", cur("version = 'two'"), Damaged, 3),
        ("current version negative", cur("version = -1"), Damaged, 3),
        ("current version zero", cur("version = 0"), Damaged, 3),
        ("current version i64::MAX", cur("version = 9223372036854775807"), Damaged, 3),
        ("current version REAL", cur("version = 1.5"), Damaged, 3),
        ("current version BLOB", cur("version = X'02'"), Damaged, 3),
        ("current version NULL", format!("{LOOSE_CURRENT} {}", cur("version = NULL")), Damaged, 3),
        ("current rows duplicated", format!("{LOOSE_CURRENT} INSERT INTO current VALUES ('m2', 1);"), Damaged, 3),
        ("current row missing", "DELETE FROM current WHERE machine = 'm2';".into(), Damaged, 3),
        ("current machine BLOB", cur("machine = CAST(machine AS BLOB)"), Damaged, 3),
        ("current machine NULL", cur("machine = NULL"), Damaged, 3),
        ("current machine INTEGER (text affinity: '42')", cur("machine = 42"), Damaged, 3),
        ("current machine with *", cur("machine = 'm*'"), Damaged, 3),
        ("current machine with /", cur("machine = 'cmm/m2'"), Damaged, 3),
        // The version column of the current document's row.
        ("row version TEXT", format!("UPDATE calibration SET version = 'two' {M2V2};"), Damaged, 2),
        (
            "row and current version i64::MAX",
            format!("UPDATE calibration SET version = 9223372036854775807 {M2V2}; {}", cur("version = 9223372036854775807")),
            Damaged,
            2,
        ),
        (
            "row and current version 2^60",
            format!("UPDATE calibration SET version = 1152921504606846976 {M2V2}; {}", cur("version = 1152921504606846976")),
            Damaged,
            2,
        ),
        ("row and current version negative", format!("UPDATE calibration SET version = -5 {M2V2}; {}", cur("version = -5")), Damaged, 2),
        ("row and current version REAL", format!("UPDATE calibration SET version = 2.5 {M2V2}; {}", cur("version = 2.5")), Damaged, 2),
        ("row duplicated", format!("{LOOSE_CALIBRATION} INSERT INTO calibration SELECT * FROM calibration {M2V2};"), Damaged, 3),
        // No row carries the name m2 any more.
        ("machine BLOB everywhere", "UPDATE current SET machine = CAST(machine AS BLOB) WHERE machine = 'm2'; UPDATE calibration SET machine = CAST(machine AS BLOB) WHERE machine = 'm2';".into(), Vanished, 1),
        ("machine with * everywhere", "UPDATE current SET machine = 'm*' WHERE machine = 'm2'; UPDATE calibration SET machine = 'm*' WHERE machine = 'm2';".into(), Vanished, 1),
        ("machine with / everywhere", "UPDATE current SET machine = 'a/m2' WHERE machine = 'm2'; UPDATE calibration SET machine = 'a/m2' WHERE machine = 'm2';".into(), Vanished, 1),
        (
            "machine NULL everywhere",
            format!("{LOOSE_CALIBRATION} {LOOSE_CURRENT} UPDATE current SET machine = NULL WHERE machine = 'm2'; UPDATE calibration SET machine = NULL WHERE machine = 'm2';"),
            Vanished,
            1,
        ),
        (
            "machine not UTF-8 everywhere",
            "UPDATE current SET machine = CAST(X'6dff' AS TEXT) WHERE machine = 'm2'; UPDATE calibration SET machine = CAST(X'6dff' AS TEXT) WHERE machine = 'm2';".into(),
            Vanished,
            1,
        ),
        (
            "machine name too long everywhere",
            format!("UPDATE current SET machine = '{0}' WHERE machine = 'm2'; UPDATE calibration SET machine = '{0}' WHERE machine = 'm2';", "m".repeat(65)),
            Vanished,
            1,
        ),
        // Outside the current document.
        ("an older version's doc not JSON", "UPDATE calibration SET doc = 'garbage' WHERE machine = 'm2' AND version = 1;".into(), Intact, 3),
        ("parent column TEXT", format!("UPDATE calibration SET parent = 'one' {M2V2};"), Intact, 3),
        ("note column BLOB", format!("UPDATE calibration SET note = X'00ff' {M2V2};"), Intact, 3),
        ("an older row's version TEXT", "UPDATE calibration SET version = 'one' WHERE machine = 'm2' AND version = 1;".into(), Intact, 3),
        // Repaired when opening.
        ("table current dropped", "DROP TABLE current;".into(), Repaired, 3),
    ]
}

#[test]
fn a_damaged_machine_is_named_while_the_others_are_served() {
    let vs = variants();
    assert!(vs.len() >= 20);
    for (name, sql, expect, next) in vs {
        let d = scratch("variant");
        two_machines(&d);
        Store::open(&d)
            .unwrap()
            .raw_sql_for_tests(&sql)
            .unwrap_or_else(|e| panic!("{name}: the damage itself failed: {e}"));
        let mut s = Store::open(&d).unwrap_or_else(|e| panic!("{name}: open: {e}"));
        let machines = s
            .machines()
            .unwrap_or_else(|e| panic!("{name}: machines: {e}"));
        let damaged_rows = s.damaged_rows();
        // m1 is served whatever happened to m2.
        assert!(machines.iter().any(|m| m == "m1"), "{name}: {machines:?}");
        assert_eq!(s.current("m1").unwrap().unwrap().version, 2, "{name}");
        assert_eq!(s.history("m1").unwrap().len(), 2, "{name}");
        // Every listed machine is either served or named as damaged; nothing else.
        for m in &machines {
            match s.current(m) {
                Ok(Some(c)) => assert_eq!(&c.machine_id, m, "{name}"),
                Err(StoreError::Damaged { machine, .. }) => assert_eq!(&machine, m, "{name}"),
                other => panic!("{name}: current({m}): {other:?}"),
            }
            s.history(m)
                .unwrap_or_else(|e| panic!("{name}: history({m}): {e}"));
        }
        match expect {
            Damaged => {
                assert!(machines.iter().any(|m| m == "m2"), "{name}: {machines:?}");
                match s.current("m2") {
                    Err(e @ StoreError::Damaged { .. }) => {
                        let msg = e.to_string();
                        assert!(msg.contains("`m2`"), "{name}: {msg}");
                        println!("{name}: {msg}");
                    }
                    other => panic!("{name}: current(m2) = {other:?}"),
                }
            }
            Vanished => {
                assert!(!machines.iter().any(|m| m == "m2"), "{name}: {machines:?}");
                assert!(s.current("m2").unwrap().is_none(), "{name}");
                assert!(s.history("m2").unwrap().is_empty(), "{name}");
                assert!(
                    damaged_rows.iter().any(|r| r.contains("table `current`"))
                        && damaged_rows
                            .iter()
                            .any(|r| r.contains("table `calibration`")),
                    "{name}: {damaged_rows:?}"
                );
                println!("{name}: {}", damaged_rows.join(" | "));
            }
            Intact => {
                assert_eq!(s.current("m2").unwrap().unwrap().version, 2, "{name}");
                let h = s.history("m2").unwrap();
                let marked = h.iter().any(|v| v.damaged.is_some());
                let skipped = h.len() < 2 && !damaged_rows.is_empty();
                assert!(marked || skipped, "{name}: {h:?} {damaged_rows:?}");
                println!(
                    "{name}: {:?} {damaged_rows:?}",
                    h.iter()
                        .filter_map(|v| v.damaged.as_ref())
                        .collect::<Vec<_>>()
                );
            }
            Repaired => {
                assert_eq!(s.current("m2").unwrap().unwrap().version, 2, "{name}");
                assert!(!damaged_rows.is_empty(), "{name}");
                println!("{name}: {}", damaged_rows.join(" | "));
            }
        }
        if matches!(expect, Damaged) {
            // Rows that belong to no machine are described; damage of m2 itself is
            // current()'s to report.
            if name.starts_with("current machine") && !name.contains("INTEGER") {
                assert!(
                    damaged_rows.iter().any(|r| r.contains("table `current`")),
                    "{name}: {damaged_rows:?}"
                );
            }
        }
        // A new put heals m2.
        let put = s
            .put(Calibration::example("m2"))
            .unwrap_or_else(|e| panic!("{name}: put(m2): {e}"));
        assert_eq!(put.version, next, "{name}");
        assert_eq!(s.current("m2").unwrap().unwrap().version, next, "{name}");
        let h = s.history("m2").unwrap();
        assert!(
            h.iter().any(|v| v.version == next && v.current),
            "{name}: {h:?}"
        );
        drop(s);
        let s = Store::open(&d).unwrap();
        assert_eq!(s.current("m2").unwrap().unwrap().version, next, "{name}");
        assert_eq!(s.current("m1").unwrap().unwrap().version, 2, "{name}");
        assert!(s.machines().unwrap().iter().any(|m| m == "m2"), "{name}");
        drop(s);
        std::fs::remove_dir_all(&d).ok();
    }
}

#[test]
fn a_lost_calibration_table_names_every_machine() {
    let d = scratch("no-calibration-table");
    two_machines(&d);
    Store::open(&d)
        .unwrap()
        .raw_sql_for_tests("DROP TABLE calibration;")
        .unwrap();
    let mut s = Store::open(&d).unwrap();
    assert!(
        s.damaged_rows()
            .iter()
            .any(|r| r.contains("`calibration` was missing")),
        "{:?}",
        s.damaged_rows()
    );
    assert_eq!(s.machines().unwrap(), vec!["m1", "m2"]);
    for m in ["m1", "m2"] {
        let e = s.current(m).unwrap_err();
        assert!(
            matches!(&e, StoreError::Damaged { machine, version: 2, .. } if machine == m),
            "{e}"
        );
        assert_eq!(s.put(Calibration::example(m)).unwrap().version, 1);
        assert_eq!(s.current(m).unwrap().unwrap().version, 1);
    }
    std::fs::remove_dir_all(&d).ok();
}

#[test]
fn whole_database_damage_is_an_error_naming_the_file() {
    // Not SQLite at all.
    let d = scratch("not-sqlite");
    std::fs::create_dir_all(&d).unwrap();
    std::fs::write(
        d.join(FILE_NAME),
        "this is a text file, not a database\n".repeat(100),
    )
    .unwrap();
    let e = Store::open(&d).err().expect("a text file is no store");
    let msg = e.to_string();
    assert!(matches!(e, StoreError::Open { .. }), "{msg}");
    assert!(
        msg.contains(&d.join(FILE_NAME).display().to_string())
            && msg.contains("not an SQLite database"),
        "{msg}"
    );
    std::fs::remove_dir_all(&d).ok();

    // Tables of the wrong shape.
    for (what, sql, needle) in [
        (
            "calibration without doc",
            "DROP TABLE calibration; CREATE TABLE calibration (machine TEXT, version INTEGER);",
            "`calibration` has no column parent, note, created, doc",
        ),
        (
            "current without version",
            "DROP TABLE current; CREATE TABLE current (machine TEXT, v INTEGER);",
            "`current` has no column version",
        ),
        (
            "current is a view",
            "DROP TABLE current; CREATE VIEW current AS SELECT 'm1' AS machine, 2 AS version;",
            "`current` is a view",
        ),
    ] {
        let d = scratch("shape");
        two_machines(&d);
        Store::open(&d).unwrap().raw_sql_for_tests(sql).unwrap();
        let e = Store::open(&d)
            .err()
            .unwrap_or_else(|| panic!("{what}: opened"));
        let msg = e.to_string();
        assert!(
            msg.contains(&d.join(FILE_NAME).display().to_string()) && msg.contains(needle),
            "{what}: {msg}"
        );
        println!("{what}: {msg}");
        std::fs::remove_dir_all(&d).ok();
    }

    // An empty file is an empty store.
    let d = scratch("empty-file");
    std::fs::create_dir_all(&d).unwrap();
    std::fs::write(d.join(FILE_NAME), "").unwrap();
    let mut s = Store::open(&d).unwrap();
    assert!(s.machines().unwrap().is_empty());
    assert_eq!(s.put(Calibration::example("m1")).unwrap().version, 1);
    drop(s);
    std::fs::remove_dir_all(&d).ok();
}

/// The largest calibration the lab and the simulator write: every library effect, guide
/// straightness towards both perpendicular axes and pitch on all three axes at 101 knots,
/// every number at full precision. [`MAX_DOC_BYTES`] must leave 20 times that.
#[test]
fn the_size_limit_leaves_room_for_the_largest_realistic_document() {
    let mut c = Calibration::example("cmm-bay-3.left");
    let mut x = 0.123_456_789_012_345_f64;
    let mut val = || {
        x = (x * 3.987_654_321 + 0.271_828_182_845_904_5).fract();
        (x - 0.5) * 1.234_567_891_234_567e-3
    };
    let mut effects = vec![
        EffectConfig::AccelDeflection(accel_deflection::Config::zeros(2, false)),
        EffectConfig::ServoPhase(servo_phase::Config::zeros(1)),
        EffectConfig::ServoGain(servo_gain::Config::zeros(2, vec![1, 2])),
        EffectConfig::StylusThermal(stylus_thermal::Config::zeros(true)),
        EffectConfig::ScaleThermal(scale_thermal::Config::zeros()),
        EffectConfig::ProbeForce(probe_force::Config::zeros()),
    ];
    for axis in [Axis::X, Axis::Y, Axis::Z] {
        let mut g = guide_straightness::Config::zeros(axis, -500.25, 1200.75, 101, true);
        g.id = Some(format!("guide_{}", axis.name()));
        effects.push(EffectConfig::GuideStraightness(g));
    }
    for e in effects {
        let p: Vec<f64> = e.params().iter().map(|_| val()).collect();
        c.effects.push(e.with_params(&p).unwrap());
    }
    c.note = "lab fit: every effect, guide tables on three axes; ".repeat(10);
    for k in [
        "heldout_rms_um",
        "fit_rms_um",
        "delta_bic",
        "noise_floor_um",
    ] {
        c.metrics.insert(k.into(), val());
    }
    c.build().unwrap();
    let n = c.to_json().len();
    println!(
        "largest realistic document: {n} bytes; limit {MAX_DOC_BYTES} = {:.0}×",
        MAX_DOC_BYTES as f64 / n as f64
    );
    assert!(20 * n <= MAX_DOC_BYTES, "{n} bytes");
    // And the store takes it.
    let d = scratch("large-realistic");
    let mut s = Store::open(&d).unwrap();
    assert_eq!(s.put(c).unwrap().version, 1);
    drop(s);
    std::fs::remove_dir_all(&d).ok();
}
