//! `scancorr import`: a recorded table into a bag of the wire contract, and `scancorr export
//! --raw`, the way back.
//!
//! * A simulated bag exported raw and imported back holds the same raw samples (seq, time and
//!   every value, bit for bit), exports raw to the same bytes again, and `scancorr correct`
//!   gives the same corrected points from both.
//! * A bad table (a non-number, time going back, a missing mapped column, a partial row, a
//!   gap) fails naming file, line and column and how many rows were bad, exits non-zero and
//!   leaves no output file (and a file that had the output's name untouched).
//! * An imported bag with every kind of stream reads in the Python package
//!   (`scancorr.read_bag`).

mod common;
use common::*;
use scancorr_bag::BagReader;
use scancorr_core::sample::Sample;
use scancorr_core::wire;
use std::path::Path;
use std::process::Command;

fn json(s: &str) -> serde_json::Value {
    serde_json::from_str(s).unwrap_or_else(|e| panic!("not JSON ({e}): {s}"))
}

/// Every raw sample of the corrected streams of `machine`, per stream in bag order, as text
/// that shows every bit (`{:?}` of f64 is its shortest round-trip form).
fn raw_samples(bag: &Path) -> Vec<String> {
    let r = BagReader::open(bag).unwrap();
    let mut out: Vec<(usize, String)> = vec![];
    let mut batch = vec![];
    for m in r.messages().unwrap() {
        let m = m.unwrap();
        let Some(stream) = wire::stream_id(m.stream) else {
            continue;
        };
        batch.clear();
        let foreign = wire::decode_machine(stream, &m.data, "m1", &mut batch).unwrap();
        assert_eq!(foreign, 0);
        for s in &batch {
            let k = match s {
                Sample::Command(_) => 0,
                Sample::Scale(_) => 1,
                Sample::Probe(_) => 2,
                Sample::Temperature(_) => 3,
            };
            out.push((k, format!("{s:?}")));
        }
    }
    // Stable: each stream keeps its order.
    out.sort_by_key(|(k, _)| *k);
    out.into_iter().map(|(_, s)| s).collect()
}

#[test]
fn a_bag_exported_raw_and_imported_back_corrects_to_the_same_points() {
    let dir = scratch("cli-import-roundtrip");
    let sim = json(&ok(
        &dir,
        &[
            "sim",
            "--program",
            "ring",
            "--seed",
            "4",
            "--out",
            "r.mcap",
            "--calib-out",
            "start.json",
            "--json",
        ],
    ));
    let o = run(
        &dir,
        &["export", "--bag", "r.mcap", "--raw", "--out", "r.csv"],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let said = String::from_utf8_lossy(&o.stderr);
    assert!(
        said.contains("scancorr import --csv r.csv --map r.map.json --artifacts r.meta.json"),
        "{said}"
    );
    let csv = std::fs::read_to_string(dir.join("r.csv")).unwrap();
    let head = csv.lines().next().unwrap();
    for col in [
        "t_ns",
        "command_arc_radius_mm",
        "command_segment_id",
        "scale_x_mm",
        "probe_tip_id",
        "probe_head_a2_deg",
        "temperature_stylus_C",
        "temperature_air_C",
    ] {
        assert!(head.split(',').any(|c| c == col), "{col} in {head}");
    }
    let map = json(&std::fs::read_to_string(dir.join("r.map.json")).unwrap());
    assert_eq!(map["machine"], "m1");
    assert_eq!(map["time"]["unit"], "ns");

    let imp = json(&ok(
        &dir,
        &[
            "import",
            "--csv",
            "r.csv",
            "--map",
            "r.map.json",
            "--artifacts",
            "r.meta.json",
            "--out",
            "back.mcap",
            "--json",
        ],
    ));
    for s in ["command", "scale", "probe", "temperature"] {
        assert_eq!(imp["samples"][s], sim["samples"][s], "{s}: {imp}");
    }
    assert_eq!(imp["machine"], "m1");
    assert!(imp["span_s"].as_f64().unwrap() > 1.0, "{imp}");
    assert_eq!(imp["unmapped_columns"], serde_json::json!([]));

    // The same raw samples, bit for bit, and the same table again.
    let (a, b) = (
        raw_samples(&dir.join("r.mcap")),
        raw_samples(&dir.join("back.mcap")),
    );
    assert_eq!(a.len(), b.len());
    assert!(a == b, "the raw samples differ");
    ok(
        &dir,
        &[
            "export",
            "--bag",
            "back.mcap",
            "--raw",
            "--out",
            "again.csv",
        ],
    );
    assert!(
        std::fs::read(dir.join("again.csv")).unwrap() == csv.as_bytes(),
        "the re-exported table differs"
    );
    // The records came along (the lab's program, the artifact).
    let back = BagReader::open(dir.join("back.mcap")).unwrap();
    assert!(back.metadata_named("scancorr.program").is_some());
    assert!(back.artifact().unwrap().is_some());
    let rec = back.metadata_named("scancorr.import").unwrap();
    assert_eq!(rec["csv"], "r.csv");

    // Corrected from both: the same points.
    let c1 = json(&ok(
        &dir,
        &[
            "correct",
            "--bag",
            "r.mcap",
            "--calib",
            "start.json",
            "--out",
            "o1.mcap",
            "--json",
        ],
    ));
    let c2 = json(&ok(
        &dir,
        &[
            "correct",
            "--bag",
            "back.mcap",
            "--calib",
            "start.json",
            "--out",
            "o2.mcap",
            "--json",
        ],
    ));
    for k in ["samples", "points", "points_flagged", "alarms", "dropped"] {
        assert_eq!(c1[k], c2[k], "{k}: {c1} vs {c2}");
    }
    assert!(c1["points"].as_u64().unwrap() > 1000, "{c1}");
    ok(
        &dir,
        &[
            "export", "--bag", "o1.mcap", "--format", "csv", "--out", "p1.csv",
        ],
    );
    ok(
        &dir,
        &[
            "export", "--bag", "o2.mcap", "--format", "csv", "--out", "p2.csv",
        ],
    );
    let (p1, p2) = (
        std::fs::read_to_string(dir.join("p1.csv")).unwrap(),
        std::fs::read_to_string(dir.join("p2.csv")).unwrap(),
    );
    assert_eq!(p1.lines().count(), p2.lines().count());
    assert!(p1 == p2, "the corrected points differ");
}

/// The files of `dir` (to check that nothing was left behind).
fn files(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

/// `scancorr import` of `bad.csv` with a scale and a temperature mapped from flags.
fn import_args<'a>(extra: &[&'a str]) -> Vec<&'a str> {
    import_to("m1", "o.mcap", extra)
}

/// [`import_args`] with another machine id and output.
fn import_to<'a>(machine: &'a str, out: &'a str, extra: &[&'a str]) -> Vec<&'a str> {
    let mut a = vec![
        "import",
        "--csv",
        "bad.csv",
        "--time",
        "t",
        "--time-unit",
        "ms",
        "--col",
        "scale.x=x",
        "--col",
        "scale.y=y",
        "--col",
        "scale.z=z",
        "--col",
        "temperature.air=T",
        "--unit",
        "scale=um",
        "--machine",
        machine,
        "--out",
        out,
    ];
    a.extend_from_slice(extra);
    a
}

#[test]
fn a_bad_table_names_line_and_column_and_writes_nothing() {
    let dir = scratch("cli-import-bad");
    let good = "\
# a data logger's export
t,x,y,z,T
0,1000,2000,3000,20.5
1,1001,2000,3000,
2,1002,2000,3000,
3,1003,2000,3000,20.6
";
    // The table itself imports.
    std::fs::write(dir.join("bad.csv"), good).unwrap();
    let out = ok(&dir, &import_args(&[]));
    assert!(out.contains("samples: scale 4, temperature 2"), "{out}");
    assert!(out.contains("sensors: air"), "{out}");
    std::fs::remove_file(dir.join("o.mcap")).unwrap();
    let before = files(&dir);

    let cases: [(&str, &str, &[&str], &[&str]); 5] = [
        (
            "a non-number",
            "1,1001,2000,3000,\n",
            &[],
            &[
                "bad.csv:4:3: column \"y\": \"2.0.0\" is not a number",
                "1 bad row(s) of 4",
            ],
        ),
        (
            "time going back",
            "1,1001,2000,3000,\n",
            &[],
            &[
                "bad.csv:5:1: column \"t\": time 0.5 (t_ns 500000) is not after scale's previous sample (line 4, t_ns 1000000)",
                "1 bad row(s) of 4",
            ],
        ),
        (
            "a missing mapped column",
            "",
            &["--col", "scale.z=Z_mm"],
            &["bad.csv:2: no column \"Z_mm\" (mapped as scale.z)", "the header's columns: t, x, y, z, T"],
        ),
        (
            "a partial row",
            "",
            &[],
            &[
                "bad.csv:4:4: column \"z\": empty, but 2 other column(s) of scale are filled",
                "1 bad row(s) of 4",
            ],
        ),
        (
            "a gap",
            "",
            &["--max-gap", "0.0015"],
            &[
                "bad.csv:5:1: column \"t\": a gap of 0.002 s in scale since its previous sample (line 4), more than the largest gap 0.0015 s",
                "bad.csv:5:1: column \"t\": a gap of 0.003 s in temperature.air since its previous sample (line 3)",
                "1 bad row(s) of 3",
            ],
        ),
    ];
    for (what, _, flags, needles) in cases {
        let table = match what {
            "a non-number" => good.replace("1,1001,2000,3000,", "1,1001,2.0.0,3000,"),
            "time going back" => good.replace("2,1002,2000,3000,", "0.5,1002,2000,3000,"),
            "a partial row" => good.replace("1,1001,2000,3000,", "1,1001,2000,,"),
            "a gap" => good.replace("2,1002,2000,3000,\n", ""),
            _ => good.to_string(),
        };
        std::fs::write(dir.join("bad.csv"), &table).unwrap();
        let err = fails(&dir, &import_args(flags), needles);
        assert!(err.contains("nothing written to o.mcap"), "{what}: {err}");
        assert_eq!(files(&dir), before, "{what}: a file was left behind");
    }

    // Several bad rows: all counted, each named; a file with the output's name is untouched.
    std::fs::write(dir.join("o.mcap"), "old").unwrap();
    let table = "t,x,y,z,T\n0,1,2,3,20\n1,x,2,3,\n2,1,2,3,hot\n3,1,2\n4,1,2,3,\n";
    std::fs::write(dir.join("bad.csv"), table).unwrap();
    fails(
        &dir,
        &import_args(&["--max-errors", "2"]),
        &[
            "bad.csv: 3 bad row(s) of 5",
            "bad.csv:3:2: column \"x\": \"x\" is not a number",
            "bad.csv:4:5: column \"T\": \"hot\" is not a number",
            "… and 1 more error(s)",
        ],
    );
    assert_eq!(std::fs::read_to_string(dir.join("o.mcap")).unwrap(), "old");
    std::fs::remove_file(dir.join("o.mcap")).unwrap();
    assert_eq!(files(&dir), before);

    // Mapping mistakes before any reading.
    fails(
        &dir,
        &import_args(&["--col", "temperature.a/b=T"]),
        &["sensor name \"a/b\""],
    );
    fails(
        &dir,
        &[
            "import",
            "--csv",
            "bad.csv",
            "--col",
            "scale.x=x",
            "--machine",
            "m1",
            "--out",
            "o.mcap",
        ],
        &["no time column"],
    );
    fails(
        &dir,
        &["import", "--csv", "bad.csv", "--out", "o.mcap"],
        &["give --map MAP.json"],
    );
    fails(
        &dir,
        &import_to("m 1", "o.mcap", &[]),
        &["--machine: machine id"],
    );
    fails(
        &dir,
        &import_args(&["--unit", "scale=furlong"]),
        &["--unit scale=furlong", "mm, um, m or in"],
    );
    fails(
        &dir,
        &import_to("m1", "bad.csv", &[]),
        &["is the same file as the input --csv"],
    );
    std::fs::write(dir.join("bad.csv"), good).unwrap();
    std::fs::write(
        dir.join("art.json"),
        r#"{"kind": "ring", "diameter_mm": "fifty"}"#,
    )
    .unwrap();
    fails(
        &dir,
        &import_args(&["--artifacts", "art.json"]),
        &["--artifacts art.json", "diameter_mm"],
    );
    std::fs::remove_file(dir.join("art.json")).unwrap();
    assert_eq!(files(&dir), before);
}

#[test]
fn an_imported_bag_reads_in_the_python_package() {
    let dir = scratch("cli-import-python");
    // A trace at 1 kHz with a 10 Hz logger and two distance probes in one table, tab-separated,
    // seconds and micrometres, a Kelvin sensor.
    let mut t = String::from("# trace\ntime\tXc\tYc\tZc\tX\tY\tZ\tU\tV\tW\tTip\tT_air\tD1\tD2\n");
    for k in 0..300 {
        let s = k as f64 / 1000.0;
        let (x, y) = (
            100.0 + 20.0 * (s * 6.0).cos(),
            200.0 + 20.0 * (s * 6.0).sin(),
        );
        let logger = if k % 100 == 0 {
            format!(
                "{}\t{}\t{}",
                293.15 + 0.001 * k as f64,
                5.0 + k as f64,
                -3.0
            )
        } else {
            "\t\t".to_string()
        };
        t += &format!(
            "{s}\t{}\t{}\t-50000\t{}\t{}\t-50000\t30\t0\t0\t1\t{logger}\n",
            x * 1000.0,
            y * 1000.0,
            x * 1000.0 + 0.5,
            y * 1000.0 - 0.5,
        );
    }
    std::fs::write(dir.join("trace.tsv"), &t).unwrap();
    std::fs::write(
        dir.join("trace.map.json"),
        r#"{
  "machine": "cmm-7",
  "time": {"column": "time", "unit": "s"},
  "command": {"unit": "um", "x": "Xc", "y": "Yc", "z": "Zc"},
  "scale": {"unit": "um", "x": "X", "y": "Y", "z": "Z"},
  "probe": {"unit": "um", "u": "U", "v": "V", "w": "W", "tip_id": "Tip", "head_a1_deg": 0, "head_a2_deg": 0},
  "temperature": {"unit": "K", "sensors": {"air": "T_air"}},
  "distance": {"unit": "um", "probes": {"1": "D1", "2": {"column": "D2", "spacing": 25000}}}
}"#,
    )
    .unwrap();
    std::fs::write(
        dir.join("ring.json"),
        r#"{"kind": "ring", "diameter_mm": 40, "serial": "R-7"}"#,
    )
    .unwrap();
    let imp = json(&ok(
        &dir,
        &[
            "import",
            "--csv",
            "trace.tsv",
            "--map",
            "trace.map.json",
            "--artifacts",
            "ring.json",
            "--out",
            "t.mcap",
            "--json",
        ],
    ));
    assert_eq!(imp["delimiter"], "tab", "{imp}");
    assert_eq!(imp["samples"]["scale"], 300, "{imp}");
    assert_eq!(imp["samples"]["temperature"], 3, "{imp}");
    assert_eq!(imp["samples"]["distance"], 6, "{imp}");
    assert_eq!(imp["records"], serde_json::json!(["scancorr.artifact"]));

    let script = r#"
import json, sys
import scancorr
b = scancorr.read_bag(sys.argv[1])
out = {"topics": {}, "metadata": b.metadata, "skipped": b.skipped, "malformed": b.malformed}
for topic, c in b.channels.items():
    d = c.data
    out["topics"][topic] = {
        "schema": c.schema,
        "n": int(len(d)),
        "seq": [int(s) for s in d["seq"]],
        "first": {k: (d[k][0].item() if hasattr(d[k][0], "item") else d[k][0]) for k in d.dtype.names},
    }
print(json.dumps(out))
"#;
    let o = Command::new(python())
        .args(["-c", script])
        .arg(dir.join("t.mcap"))
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "read_bag failed:\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    let py = json(&String::from_utf8_lossy(&o.stdout));
    assert_eq!(py["skipped"], serde_json::json!({}), "{py}");
    assert_eq!(py["malformed"], serde_json::json!({}), "{py}");
    let topic = |s: &str| &py["topics"][format!("cmm/cmm-7/raw/{s}")];
    for (s, n, schema) in [
        ("command", 300, "scancorr.v1.CommandBatch"),
        ("scale", 300, "scancorr.v1.ScaleBatch"),
        ("probe", 300, "scancorr.v1.ProbeBatch"),
        ("temperature", 3, "scancorr.v1.TemperatureBatch"),
        ("distance", 6, "scancorr.v1.DistanceBatch"),
    ] {
        let t = topic(s);
        assert_eq!(t["schema"], schema, "{s}: {t}");
        assert_eq!(t["n"], n, "{s}: {t}");
        let seq: Vec<u64> = t["seq"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_u64().unwrap())
            .collect();
        assert_eq!(seq, (0..n).collect::<Vec<u64>>(), "{s}: consecutive seq");
    }
    let f = &topic("scale")["first"];
    assert_eq!(f["t_ns"], 0);
    assert_eq!(f["x"].as_f64().unwrap(), 120.0005);
    assert_eq!(f["z"].as_f64().unwrap(), -50.0);
    let p = &topic("probe")["first"];
    assert_eq!(p["u"].as_f64().unwrap(), 0.03);
    assert_eq!(p["tip_id"], 1);
    let temp = &topic("temperature")["first"];
    assert_eq!(temp["sensor"], "air");
    assert!(
        (temp["celsius"].as_f64().unwrap() - 20.0).abs() < 1e-9,
        "{temp}"
    );
    let d = &topic("distance")["first"];
    assert_eq!(d["probe_id"], 1);
    assert_eq!(d["distance_mm"].as_f64().unwrap(), 0.005);
    let d2 = &py["topics"]["cmm/cmm-7/raw/distance"];
    assert_eq!(d2["n"], 6);
    assert_eq!(py["metadata"]["scancorr.artifact"]["serial"], "R-7", "{py}");
    assert_eq!(
        py["metadata"]["scancorr.artifact"]["diameter_mm"], "40",
        "{py}"
    );
    assert_eq!(
        py["metadata"]["scancorr.import"]["machine_id"], "cmm-7",
        "{py}"
    );
}
