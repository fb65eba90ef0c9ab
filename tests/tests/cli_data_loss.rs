//! The CLI never loses data: no command truncates or replaces a file before its arguments and
//! inputs are checked; an output that is one of the inputs (by name, symlink or hard link) is
//! refused; outputs are written under a temporary name and renamed when complete, so a failing
//! command leaves every existing file byte for byte as it was, and a successful one leaves no
//! temporary file behind. Printing into a closed pipe is a quiet exit, not a panic.

mod common;
use common::*;
use std::path::Path;
use std::process::{Command, Stdio};

/// Every file of `dir` (name → bytes), to compare before and after a command.
fn snapshot(dir: &Path) -> std::collections::BTreeMap<String, Vec<u8>> {
    std::fs::read_dir(dir)
        .unwrap()
        .flatten()
        .filter(|e| e.file_type().map(|t| t.is_file()).unwrap_or(false))
        .map(|e| {
            (
                e.file_name().to_string_lossy().to_string(),
                std::fs::read(e.path()).unwrap(),
            )
        })
        .collect()
}

/// Runs a command expected to fail (exit 1, naming the problem) and checks that no file of
/// `dir` changed, none appeared and none vanished.
fn fails_intact(dir: &Path, args: &[&str], needles: &[&str]) {
    let before = snapshot(dir);
    let err = fails(dir, args, needles);
    let after = snapshot(dir);
    assert_eq!(
        before.keys().collect::<Vec<_>>(),
        after.keys().collect::<Vec<_>>(),
        "scancorr {args:?} changed the folder's files:\n{err}"
    );
    for (name, bytes) in &before {
        assert!(
            after[name] == *bytes,
            "scancorr {args:?} changed {name} ({} → {} bytes):\n{err}",
            bytes.len(),
            after[name].len()
        );
    }
}

fn no_temporaries(dir: &Path) {
    let left: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().to_string())
        .filter(|n| n.contains(".tmp"))
        .collect();
    assert!(left.is_empty(), "temporary files left behind: {left:?}");
}

#[test]
fn correct_refuses_to_write_over_its_input_bag() {
    let d = scratch("loss-correct");
    sim_ring(&d, "v1.json");
    let size = std::fs::metadata(d.join("r.mcap")).unwrap().len();
    assert!(size > 100_000, "{size}");
    // The same name.
    fails_intact(
        &d,
        &[
            "correct", "--bag", "r.mcap", "--calib", "v1.json", "--out", "r.mcap",
        ],
        &["--out r.mcap", "same file", "--bag r.mcap"],
    );
    // The same name spelled differently.
    fails_intact(
        &d,
        &[
            "correct", "--bag", "r.mcap", "--calib", "v1.json", "--out", "./r.mcap",
        ],
        &["same file"],
    );
    // The calibration is an input too.
    fails_intact(
        &d,
        &[
            "correct", "--bag", "r.mcap", "--calib", "v1.json", "--out", "v1.json",
        ],
        &["same file", "--calib v1.json"],
    );
    // Another output file: written completely, no temporary file left; over an existing
    // file, replaced.
    ok(
        &d,
        &[
            "correct", "--bag", "r.mcap", "--calib", "v1.json", "--out", "o.mcap",
        ],
    );
    assert!(!points(&d.join("o.mcap")).is_empty());
    std::fs::write(d.join("p.bin"), "old").unwrap();
    ok(&d, &["proto", "--out", "p.bin"]);
    assert!(std::fs::read(d.join("p.bin")).unwrap().len() > 1000);
    no_temporaries(&d);
}

#[test]
fn correct_refuses_the_input_through_a_symlink_or_a_hard_link() {
    let d = scratch("loss-links");
    sim_ring(&d, "v1.json");
    std::os::unix::fs::symlink(d.join("r.mcap"), d.join("link.mcap")).unwrap();
    std::fs::hard_link(d.join("r.mcap"), d.join("hard.mcap")).unwrap();
    fails_intact(
        &d,
        &[
            "correct",
            "--bag",
            "r.mcap",
            "--calib",
            "v1.json",
            "--out",
            "link.mcap",
        ],
        &["--out link.mcap", "same file"],
    );
    fails_intact(
        &d,
        &[
            "correct",
            "--bag",
            "link.mcap",
            "--calib",
            "v1.json",
            "--out",
            "r.mcap",
        ],
        &["same file"],
    );
    fails_intact(
        &d,
        &[
            "correct",
            "--bag",
            "hard.mcap",
            "--calib",
            "v1.json",
            "--out",
            "r.mcap",
        ],
        &["--out r.mcap", "same file", "--bag hard.mcap"],
    );
    assert!(std::fs::symlink_metadata(d.join("link.mcap"))
        .unwrap()
        .file_type()
        .is_symlink());
    // A symlink to another file: the file it points to is replaced, the link stays.
    ok(
        &d,
        &[
            "correct", "--bag", "r.mcap", "--calib", "v1.json", "--out", "o.mcap",
        ],
    );
    std::fs::write(d.join("target.mcap"), "old").unwrap();
    std::os::unix::fs::symlink(d.join("target.mcap"), d.join("via.mcap")).unwrap();
    ok(
        &d,
        &[
            "correct", "--bag", "r.mcap", "--calib", "v1.json", "--out", "via.mcap",
        ],
    );
    assert!(std::fs::symlink_metadata(d.join("via.mcap"))
        .unwrap()
        .file_type()
        .is_symlink());
    assert_eq!(points(&d.join("target.mcap")), points(&d.join("o.mcap")));
    no_temporaries(&d);
}

#[test]
fn a_failing_sim_leaves_existing_outputs_alone() {
    let d = scratch("loss-sim");
    sim_ring(&d, "v1.json");
    std::fs::copy(d.join("r.mcap"), d.join("existing.mcap")).unwrap();
    std::fs::write(d.join("t.json"), "{\"old\": \"truth\"}").unwrap();
    // A bad --hide is found by the simulator, after the outputs are prepared.
    fails_intact(
        &d,
        &[
            "sim",
            "--program",
            "ring",
            "--hide",
            "foo",
            "--out",
            "existing.mcap",
            "--truth",
            "t.json",
            "--calib-out",
            "v1.json",
        ],
        &["--hide foo", "unknown effect"],
    );
    // An unknown program.
    fails_intact(
        &d,
        &["sim", "--program", "nosuch", "--out", "existing.mcap"],
        &["nosuch"],
    );
    // Two outputs on the same file.
    fails_intact(
        &d,
        &[
            "sim",
            "--program",
            "ring",
            "--out",
            "existing.mcap",
            "--truth",
            "existing.mcap",
        ],
        &["--out existing.mcap", "--truth existing.mcap", "same file"],
    );
    // An output in a folder that does not exist fails before anything else is written.
    fails_intact(
        &d,
        &[
            "sim",
            "--program",
            "ring",
            "--out",
            "existing.mcap",
            "--truth",
            "nodir/t.json",
        ],
        &["--truth nodir/t.json"],
    );
}

#[test]
fn a_failing_lab_command_leaves_existing_calibrations_alone() {
    let d = scratch("loss-lab");
    ok(
        &d,
        &[
            "sim",
            "--program",
            "ring-speeds",
            "--hide",
            "servo_phase",
            "--out",
            "r.mcap",
            "--calib-out",
            "v1.json",
        ],
    );
    std::fs::write(d.join("existing.json"), "{\"kept\": true}\n").unwrap();
    // The report cannot be written: the new version must not replace existing.json either.
    fails_intact(
        &d,
        &[
            "lab",
            "add",
            "servo_phase",
            "--bag",
            "r.mcap",
            "--calib",
            "v1.json",
            "--out",
            "existing.json",
            "--report",
            "nodir/report.html",
        ],
        &["--report nodir/report.html"],
    );
    // The new version over the calibration it starts from.
    fails_intact(
        &d,
        &[
            "lab",
            "add",
            "servo_phase",
            "--bag",
            "r.mcap",
            "--calib",
            "v1.json",
            "--out",
            "v1.json",
        ],
        &["--out v1.json", "same file", "--calib v1.json"],
    );
    fails_intact(
        &d,
        &[
            "lab", "fit", "--bag", "r.mcap", "--calib", "v1.json", "--out", "r.mcap",
        ],
        &["--out r.mcap", "same file", "--bag r.mcap"],
    );
    fails_intact(
        &d,
        &[
            "lab", "compare", "--bag", "r.mcap", "--calib", "v1.json", "--report", "v1.json",
        ],
        &["--report v1.json", "same file"],
    );
    // A failure found late (an unknown effect) leaves existing.json as it was.
    fails_intact(
        &d,
        &[
            "lab",
            "add",
            "gravity",
            "--bag",
            "r.mcap",
            "--calib",
            "v1.json",
            "--out",
            "existing.json",
        ],
        &["unknown effect"],
    );
    // And a successful one replaces it, completely, with no temporary file left.
    ok(
        &d,
        &[
            "lab",
            "add",
            "servo_phase",
            "--bag",
            "r.mcap",
            "--calib",
            "v1.json",
            "--out",
            "existing.json",
            "--report",
            "report.html",
        ],
    );
    let v2: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("existing.json")).unwrap()).unwrap();
    assert_eq!(v2["version"], 2, "{v2}");
    assert!(std::fs::read_to_string(d.join("report.html"))
        .unwrap()
        .ends_with("</html>"));
    no_temporaries(&d);
}

#[test]
fn record_with_nothing_listening_leaves_an_existing_bag_alone() {
    let d = scratch("loss-record");
    sim_ring(&d, "v1.json");
    let ep = format!("tcp/127.0.0.1:{}", free_port());
    fails_intact(
        &d,
        &[
            "record",
            "--keys",
            "cmm/m1/raw/**",
            "--out",
            "r.mcap",
            "--seconds",
            "2",
            "--connect",
            &ep,
        ],
        &[&ep],
    );
}

#[test]
fn a_closed_stdout_is_a_quiet_exit() {
    let d = scratch("loss-pipe");
    for args in [
        &["calib", "example", "--all-effects"][..],
        &["shape", "fit", "--kind", "circle", "--points", "pts.txt"][..],
    ] {
        std::fs::write(
            d.join("pts.txt"),
            (0..36)
                .map(|i| {
                    let a = i as f64 * 10f64.to_radians();
                    format!("{} {} 0\n", 5.0 * a.cos(), 5.0 * a.sin())
                })
                .collect::<String>(),
        )
        .unwrap();
        // The reader is gone before the command writes a byte.
        let (r, w) = std::io::pipe().unwrap();
        drop(r);
        let o = Command::new(scancorr())
            .args(args)
            .current_dir(&d)
            .stdout(w)
            .stderr(Stdio::piped())
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!err.contains("panicked"), "scancorr {args:?}: {err}");
        assert_eq!(o.status.code(), Some(0), "scancorr {args:?}: {err}");
    }
}

/// `scancorr sim --program ring --seed 4703 EXTRA…`.
fn sim<'a>(extra: &[&'a str]) -> Vec<&'a str> {
    let mut a = vec!["sim", "--program", "ring", "--seed", "4703"];
    a.extend(extra);
    a
}

/// Raw messages in a bag.
fn raw_messages(bag: &Path) -> usize {
    let r = scancorr_bag::BagReader::open(bag).unwrap();
    r.messages()
        .unwrap()
        .filter(|m| scancorr_bag::Stream::RAW.contains(&m.as_ref().unwrap().stream))
        .count()
}

/// `record --keys 'cmm/m1/**'` of a run faster than real time records every raw message
/// (issue 47: it lost 8 130 raw samples where `cmm/m1/raw/**` got all). With the points and
/// their Foxglove channels to write as well, the recorder used to write slower than the run
/// arrived; zenoh's subscriber queue (256 samples) then held the recorder's link, and
/// scancorrd dropped the raw messages it forwards to it (droppable, in their own lane). The
/// recorder now queues what arrives without holding the link.
#[test]
fn record_of_everything_faster_than_real_time_loses_no_raw_sample() {
    let d = scratch("loss-record-all");
    let port = free_port();
    let ep = format!("tcp/127.0.0.1:{port}");
    ok(
        &d,
        &sim(&["--out", "offline.mcap", "--calib-out", "v1.json"]),
    );
    let expected = raw_messages(&d.join("offline.mcap"));
    let svc = Service::start(&d, port);
    calib_put(&d, "m1", "v1.json", &ep);
    let rec = Command::new(scancorr())
        .args([
            "record",
            "--keys",
            "cmm/m1/**",
            "--out",
            "all.mcap",
            "--idle",
            "3",
            "--seconds",
            "120",
            "--connect",
            &ep,
        ])
        .current_dir(&d)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(std::time::Duration::from_millis(1500));
    ok(
        &d,
        &sim(&["--live", "--live-rate", "max", "--connect", &ep]),
    );
    let rec = rec.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&rec.stderr).to_string();
    assert!(rec.status.success(), "record failed:\n{err}");
    assert!(!err.contains("missing"), "{err}");
    let bag = d.join("all.mcap");
    assert_eq!(raw_messages(&bag), expected, "{err}");
    assert!(
        !points(&bag).is_empty(),
        "the points were recorded too: {err}"
    );
    svc.stop();
}
