//! A bag `scancorr correct` wrote opens in Foxglove: `tests/python/foxglove_bag.py` reads its
//! Foxglove channels with the Python `mcap` reader and Foxglove's published schemas
//! (`foxglove-schemas-protobuf`), the packed point fields by the types each cloud declares.
//! Every corrected point is there once, at its corrected position (in metres), with the lab's
//! deviation from the nominal feature of its segment; each alarm is a log line; the machine
//! frame and the nominal features are there. `--no-foxglove` leaves them out. `scancorr record`
//! writes the same channels from the corrected points and alarms it records off the bus.
//!
//! The Python environment comes from `scripts/python-env.sh` (the pinned packages of
//! `tests/python/requirements.txt`); without Python 3 and pip these tests fail, not skip.

mod common;

use common::*;
use serde_json::Value;
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

fn read_foxglove(bag: &Path) -> Value {
    let out = Command::new(python())
        .arg(root().join("tests/python/foxglove_bag.py"))
        .arg(bag)
        .output()
        .expect("python runs");
    assert!(
        out.status.success(),
        "foxglove_bag.py failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

#[test]
fn correct_writes_foxglove_channels_an_independent_reader_decodes() {
    let d = scratch("foxglove-bag");
    // A collision: alarms to log.
    ok(
        &d,
        &[
            "sim",
            "--program",
            "ring",
            "--seed",
            "5050",
            "--machine-seed",
            "5051",
            "--fault",
            "collision",
            "--out",
            "r.mcap",
            "--calib-out",
            "v1.json",
        ],
    );
    let cor: Value = serde_json::from_str(&ok(
        &d,
        &[
            "correct", "--bag", "r.mcap", "--calib", "v1.json", "--out", "o.mcap", "--json",
        ],
    ))
    .unwrap();
    let r = read_foxglove(&d.join("o.mcap"));
    eprintln!("{r}");
    let n = cor["points"].as_u64().unwrap();
    assert!(n > 10_000, "{cor}");
    assert_eq!(r["corrected_points"], n, "{r}");
    // Every point once, where the correction put it, with its version, segment, validity.
    assert_eq!(r["foxglove_points"], n, "{r}");
    assert_eq!(r["duplicates"], 0, "{r}");
    assert_eq!(r["missing"], 0, "{r}");
    assert_eq!(r["max_position_diff_m"], 0.0, "{r}");
    assert_eq!(r["metadata_mismatches"], 0, "{r}");
    // The lab's deviation, on every point of a segment with a feature (the ring's scans; the
    // approaches have none).
    let with = r["points_with_feature"].as_u64().unwrap();
    assert!(with > n / 2, "{r}");
    assert_eq!(r["points_with_deviation"], with, "{r}");
    assert!(r["max_deviation_diff_mm"].as_f64().unwrap() <= 1e-12, "{r}");
    // Deviations of a corrected ring near its nominal: within a few µm … a collision's mm.
    let range = &r["deviation_range_mm"];
    assert!(
        range[0].as_f64().unwrap() < range[1].as_f64().unwrap(),
        "{r}"
    );
    // Foxglove's numbering: FLOAT64 = 8, UINT32 = 5, UINT8 = 1 (not ROS PointField's).
    assert_eq!(r["field_types"]["x"], "FLOAT64", "{r}");
    assert_eq!(r["field_types"]["deviation_mm"], "FLOAT64", "{r}");
    assert_eq!(r["field_types"]["seq"], "UINT32", "{r}");
    assert_eq!(r["field_types"]["valid"], "UINT8", "{r}");
    // Each alarm raised or cleared is a log line.
    let alarms = r["alarms"].as_u64().unwrap();
    assert!(alarms > 0, "a collision raises the estimator alarm: {cor}");
    assert_eq!(r["logs"], alarms, "{r}");
    // The machine frame once, the nominal ring once.
    assert_eq!(r["frames"], serde_json::json!([["world", "m1"]]), "{r}");
    assert_eq!(r["scenes"], 1, "{r}");
    assert_eq!(
        r["entities"].as_array().unwrap().len() as u64,
        r["features"].as_u64().unwrap(),
        "{r}"
    );
    for (topic, schema) in [
        ("cmm/m1/foxglove/points", "foxglove.PointCloud"),
        ("cmm/m1/foxglove/alarms", "foxglove.Log"),
        ("cmm/m1/foxglove/nominal", "foxglove.SceneUpdate"),
        ("cmm/m1/foxglove/frame", "foxglove.FrameTransform"),
        (
            "cmm/m1/foxglove/deviation",
            "scancorr.foxglove.DeviationSummary",
        ),
    ] {
        assert_eq!(
            r["schemas"][topic],
            serde_json::json!([schema, "protobuf", "protobuf"]),
            "{r}"
        );
    }

    // The shipped layout names only what the bag publishes: each topic is a channel, each
    // message path a field of its schema, the 3D colour field a field of the clouds.
    layout_names_what_the_bag_holds(&r);

    // Without them, the bag holds our channels only.
    ok(
        &d,
        &[
            "correct",
            "--bag",
            "r.mcap",
            "--calib",
            "v1.json",
            "--out",
            "plain.mcap",
            "--no-foxglove",
        ],
    );
    let plain = scancorr_bag::BagReader::open(d.join("plain.mcap")).unwrap();
    assert!(plain.unknown_channels().is_empty());
    let with = scancorr_bag::BagReader::open(d.join("o.mcap")).unwrap();
    assert_eq!(with.unknown_channels().len(), 5);
    assert_eq!(points(&d.join("plain.mcap")), points(&d.join("o.mcap")));
}

/// Every topic and message path of the shipped layout against what a bag's Foxglove channels
/// hold (`r`, what `foxglove_bag.py` read).
fn layout_names_what_the_bag_holds(r: &Value) {
    let paths = foxglove_layout_paths();
    assert!(paths.len() >= 5, "{paths:?}");
    let topics = r["schemas"].as_object().unwrap();
    for p in &paths {
        let (topic, field) = topics
            .keys()
            .find_map(|t| match p.strip_prefix(t.as_str()) {
                Some("") => Some((t, None)),
                Some(rest) => rest.strip_prefix('.').map(|f| (t, Some(f))),
                None => None,
            })
            .unwrap_or_else(|| panic!("the layout names `{p}`, no channel of the bag: {topics:?}"));
        if let Some(f) = field {
            let first = f.split(['.', '[']).next().unwrap();
            let fields = &r["message_fields"][topic];
            assert!(
                fields.as_array().unwrap().iter().any(|x| x == first),
                "the layout plots `{p}`, but {topic} has the fields {fields}"
            );
        }
    }
    let text = std::fs::read_to_string(root().join("deploy/foxglove/scancorr-layout.json"));
    let l: Value = serde_json::from_str(&text.unwrap()).unwrap();
    for (_, panel) in l["configById"].as_object().unwrap() {
        for (t, cfg) in panel["topics"].as_object().into_iter().flatten() {
            if let Some(c) = cfg["colorField"].as_str() {
                assert!(
                    r["field_types"][c].is_string(),
                    "{t} is coloured by `{c}`: {r}"
                );
            }
        }
        if let Some(f) = panel["followTf"].as_str() {
            let frames = r["frames"].as_array().unwrap();
            assert!(
                frames.iter().any(|x| x[1] == f),
                "follows frame {f}: {frames:?}"
            );
        }
    }
}

/// The shipped layout shows what the channels carry: a 3D panel on the points coloured by a
/// field the clouds have, the nominal scene, a plot of fields of the deviation summary, the
/// alarm log — every topic one of machine m1's Foxglove channels.
#[test]
fn the_shipped_layout_names_the_channels_and_fields_there_are() {
    use scancorr_bag::foxglove::{Channel, POINT_FIELDS};
    let text =
        std::fs::read_to_string(root().join("deploy/foxglove/scancorr-layout.json")).unwrap();
    let l: Value = serde_json::from_str(&text).unwrap();
    let topic = |c: Channel| c.topic("cmm", "m1");
    let panels = l["configById"].as_object().unwrap();
    let of = |kind: &str| {
        panels
            .iter()
            .find(|(k, _)| k.starts_with(&format!("{kind}!")))
            .map(|(_, v)| v)
            .unwrap_or_else(|| panic!("no {kind} panel: {:?}", panels.keys()))
    };
    let three = of("3D");
    let pts = &three["topics"][topic(Channel::Points)];
    assert_eq!(pts["visible"], true);
    assert_eq!(pts["colorMode"], "colormap");
    let field = pts["colorField"].as_str().unwrap();
    assert!(POINT_FIELDS.iter().any(|f| f.0 == field), "{field}");
    assert_eq!(three["topics"][topic(Channel::Nominal)]["visible"], true);
    assert_eq!(three["followTf"], "m1");
    let paths = of("Plot")["paths"].as_array().unwrap();
    assert!(!paths.is_empty());
    for p in paths {
        let v = p["value"].as_str().unwrap();
        let (t, f) = v.rsplit_once('.').unwrap();
        assert_eq!(t, topic(Channel::Deviation));
        assert!(["min_mm", "max_mm", "rms_mm"].contains(&f), "{v}");
    }
    assert_eq!(of("RosOut")["topicToRender"], topic(Channel::Alarms));
    // Every panel is placed.
    for k in panels.keys() {
        assert!(
            l["layout"].to_string().contains(k.as_str()),
            "{k} is not in the layout"
        );
    }
}

/// Starts `scancorr record` of `keys` into `out` (with `extra`) and waits until it subscribes.
fn recorder(d: &Path, keys: &str, out: &str, bus: &str, extra: &[&str]) -> Child {
    let mut c = Command::new(scancorr())
        .args(["record", "--keys", keys, "--out", out])
        .args(extra)
        .args(["--idle", "2", "--seconds", "60", "--connect", bus])
        .current_dir(d)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut err = BufReader::new(c.stderr.take().unwrap());
    let mut line = String::new();
    err.read_line(&mut line).unwrap();
    assert!(line.starts_with("recording"), "record says: {line}");
    // The rest of its log, read on (a full pipe would block it).
    std::thread::spawn(move || std::io::copy(&mut err, &mut std::io::sink()));
    c
}

/// `scancorr record` of a live run (scancorrd correcting a replayed ring with a collision)
/// writes the Foxglove channels beside the recorded points and alarms: every recorded point
/// once, at its place, with the lab's deviation from the nominal the bag of `--nominal` gives
/// (its program record copied in); each recorded alarm a log line. (Points and alarms are
/// recorded by two recorders, each on one key: the raw streams are not recorded, as the
/// router may drop them for a recorder behind a replay at full speed.)
#[test]
fn record_writes_the_foxglove_channels_of_what_it_records() {
    let d = scratch("foxglove-record");
    ok(
        &d,
        &[
            "sim",
            "--program",
            "ring",
            "--seed",
            "5056",
            "--machine-seed",
            "5057",
            "--fault",
            "collision",
            "--out",
            "r.mcap",
            "--calib-out",
            "v1.json",
        ],
    );
    ok(
        &d,
        &[
            "correct", "--bag", "r.mcap", "--calib", "v1.json", "--out", "off.mcap",
        ],
    );
    let off = points(&d.join("off.mcap"));
    let port = free_port();
    let bus = format!("tcp/127.0.0.1:{port}");
    let svc = Service::start(&d, port);
    calib_put(&d, "m1", "v1.json", &bus);
    let nominal = ["--nominal", "r.mcap"];
    let pts = recorder(&d, "cmm/m1/corrected/**", "pts.mcap", &bus, &nominal);
    let alm = recorder(&d, "cmm/m1/alarms/**", "alarms.mcap", &bus, &nominal);
    let plain = recorder(
        &d,
        "cmm/m1/alarms/**",
        "plain.mcap",
        &bus,
        &["--no-foxglove"],
    );
    std::thread::sleep(Duration::from_millis(500));
    replay_max(&d, "r.mcap", &bus);
    svc.stop(); // flushes what the corrector holds
    for (mut c, what) in [(pts, "points"), (alm, "alarms"), (plain, "plain alarms")] {
        let st = c.wait().unwrap();
        assert!(st.success(), "recording the {what} failed");
    }

    let r = read_foxglove(&d.join("pts.mcap"));
    eprintln!("{r}");
    // Every point of the live run recorded, each once in the Foxglove channel, at its place.
    assert_eq!(r["corrected_points"], off.len(), "{r}");
    assert_eq!(r["foxglove_points"], off.len(), "{r}");
    assert_eq!(r["duplicates"], 0, "{r}");
    assert_eq!(r["missing"], 0, "{r}");
    assert_eq!(r["max_position_diff_m"], 0.0, "{r}");
    assert_eq!(r["metadata_mismatches"], 0, "{r}");
    let with = r["points_with_feature"].as_u64().unwrap();
    assert!(with > off.len() as u64 / 2, "{r}");
    assert_eq!(r["points_with_deviation"], with, "{r}");
    assert!(r["max_deviation_diff_mm"].as_f64().unwrap() <= 1e-12, "{r}");
    assert_eq!(r["frames"], serde_json::json!([["world", "m1"]]), "{r}");
    assert_eq!(r["scenes"], 1, "{r}");
    // points, deviation, nominal, frame: no alarms on this recorder.
    assert_eq!(r["schemas"].as_object().unwrap().len(), 4, "{r}");

    let a = read_foxglove(&d.join("alarms.mcap"));
    let n_alarms = a["alarms"].as_u64().unwrap();
    assert!(n_alarms > 0, "{a}");
    assert_eq!(a["logs"], n_alarms, "{a}");
    assert_eq!(
        a["schemas"]["cmm/m1/foxglove/alarms"],
        serde_json::json!(["foxglove.Log", "protobuf", "protobuf"]),
        "{a}"
    );

    // The deviations are from the program of `--nominal`, which the recorded bag keeps.
    let rec = scancorr_bag::BagReader::open(d.join("pts.mcap")).unwrap();
    assert!(rec.metadata().iter().any(|m| m.name == "scancorr.program"));

    // Without them, the recorded bag holds our channels only.
    let plain = scancorr_bag::BagReader::open(d.join("plain.mcap")).unwrap();
    assert!(plain.unknown_channels().is_empty());
    assert_eq!(alarms(&d.join("plain.mcap")).len() as u64, n_alarms);
}
