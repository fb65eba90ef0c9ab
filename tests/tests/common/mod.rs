//! Helpers for tests that drive the `scancorr` binary as a separate process.
#![allow(dead_code)]

/// Headless Chromium and the reports' plot checks (report_html.rs, readme_blocks.rs).
pub mod chromium;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

/// The workspace root.
pub fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

/// The `scancorr` binary of the profile these tests were built with (built if missing).
pub fn scancorr() -> PathBuf {
    let target = std::env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| root().join("target"));
    let profile = if cfg!(debug_assertions) {
        "debug"
    } else {
        "release"
    };
    let bin = target.join(profile).join("scancorr");
    if !bin.exists() {
        let mut c = Command::new(env!("CARGO"));
        c.args(["build", "-p", "scancorr-cli", "--bin", "scancorr"])
            .current_dir(root());
        if profile == "release" {
            c.arg("--release");
        }
        assert!(
            c.status().expect("cargo runs").success(),
            "building scancorr failed"
        );
    }
    bin
}

/// A fresh scratch directory, removed when the test passes and kept (to be looked at) when it
/// fails: dropped while the test panics, it stays.
pub fn scratch(name: &str) -> Scratch {
    let d = std::env::temp_dir().join(format!("scancorr-test-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    Scratch(d)
}

/// A test's scratch directory (see [`scratch`]); a `Path` wherever one is expected.
#[derive(Debug)]
pub struct Scratch(PathBuf);

impl std::ops::Deref for Scratch {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.0
    }
}

impl AsRef<Path> for Scratch {
    fn as_ref(&self) -> &Path {
        &self.0
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        if std::thread::panicking() {
            eprintln!("scratch directory kept: {}", self.0.display());
        } else {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

/// Runs `scancorr ARGS` in `dir`, outputs allowed to replace existing files (the tests rewrite
/// their scratch files; `cli_outputs` tests the refusal without it).
pub fn run(dir: &Path, args: &[&str]) -> Output {
    Command::new(scancorr())
        .env("SCANCORR_FORCE", "1")
        .args(args)
        .current_dir(dir)
        .output()
        .expect("scancorr runs")
}

/// Runs and expects success; returns stdout.
/// `scancorr sim --program ring --out r.mcap --calib-out <calib_out>` in `dir`.
pub fn sim_ring(dir: &Path, calib_out: &str) {
    ok(
        dir,
        &[
            "sim",
            "--program",
            "ring",
            "--out",
            "r.mcap",
            "--calib-out",
            calib_out,
        ],
    );
}

pub fn ok(dir: &Path, args: &[&str]) -> String {
    let o = run(dir, args);
    assert!(
        o.status.success(),
        "scancorr {args:?} failed:\n{}\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8(o.stdout).unwrap()
}

/// Replays `bag` onto the bus at `bus` as fast as it goes (`scancorr replay --speed max`); its
/// output. A failed replay fails the test.
pub fn replay_max(dir: &Path, bag: &str, bus: &str) -> String {
    ok(
        dir,
        &["replay", "--bag", bag, "--speed", "max", "--connect", bus],
    )
}

/// `scancorr calib put --machine M --file F --connect BUS`, expected to succeed: its output.
pub fn calib_put(dir: &Path, machine: &str, file: &str, bus: &str) -> String {
    ok(
        dir,
        &[
            "calib",
            "put",
            "--machine",
            machine,
            "--file",
            file,
            "--connect",
            bus,
        ],
    )
}

/// Runs and expects failure with a message containing every needle; no panic.
pub fn fails(dir: &Path, args: &[&str], needles: &[&str]) -> String {
    let o = run(dir, args);
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(!o.status.success(), "scancorr {args:?} should fail");
    assert_eq!(
        o.status.code(),
        Some(1),
        "scancorr {args:?} exited by {:?}:\n{err}",
        o.status
    );
    assert!(
        !err.contains("panicked"),
        "scancorr {args:?} panicked:\n{err}"
    );
    for n in needles {
        assert!(
            err.contains(n),
            "scancorr {args:?}: expected `{n}` in:\n{err}"
        );
    }
    err
}

/// The `scancorrd` binary next to `scancorr` (built if missing).
pub fn scancorrd() -> PathBuf {
    let s = scancorr();
    let bin = s.with_file_name("scancorrd");
    if !bin.exists() {
        let mut c = Command::new(env!("CARGO"));
        c.args(["build", "-p", "scancorrd"]).current_dir(root());
        if !cfg!(debug_assertions) {
            c.arg("--release");
        }
        assert!(c.status().unwrap().success(), "building scancorrd failed");
    }
    bin
}

/// Writes `router.json5` in `dir` (plain TCP on loopback `port`, no access control) and
/// starts `scancorr-router` from it; returns once it listens.
pub fn start_router(dir: &Path, port: u16) -> Child {
    std::fs::write(
        dir.join("router.json5"),
        format!("{{ mode: 'router', listen: {{ endpoints: ['tcp/127.0.0.1:{port}'] }}, scouting: {{ multicast: {{ enabled: false }} }} }}"),
    )
    .unwrap();
    let child = Command::new(scancorrd().with_file_name("scancorr-router"))
        .args(["-c", "router.json5"])
        .current_dir(dir)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    wait_listening(port, || "router did not start".into());
    child
}

/// Waits (at most 20 s) until something listens on loopback `port`; else fails with `why()`.
pub fn wait_listening(port: u16, why: impl Fn() -> String) {
    let t0 = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(t0.elapsed() < Duration::from_secs(20), "{}", why());
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// `scripts/make-certs.sh DIR`: a throw-away CA and the roles' certificates in `dir/certs`.
pub fn make_certs(dir: &Path) -> PathBuf {
    let certs = dir.join("certs");
    let out = Command::new("bash")
        .arg(root().join("scripts/make-certs.sh"))
        .arg(&certs)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "scripts/make-certs.sh failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    certs
}

/// A free TCP port on loopback.
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A running scancorrd (separate process) listening on a loopback port.
pub struct Service {
    child: Child,
    log: PathBuf,
}

impl Service {
    /// Starts it in `dir` (data in `dir/data`) and waits until it listens.
    pub fn start(dir: &Path, port: u16) -> Service {
        let mut c = Command::new(scancorrd());
        c.args([
            "--listen",
            &format!("tcp/127.0.0.1:{port}"),
            "--data-dir",
            "data",
        ]);
        Service::spawn(c, dir, port)
    }

    /// Starts it with a JSON5 configuration: listening on `port`, data in `dir/data`, and
    /// `extra` spliced in (which may name its own `listen`).
    pub fn start_with(dir: &Path, port: u16, extra: &str) -> Service {
        let cfg = dir.join(format!("scancorrd-{port}.json5"));
        let listen = if extra.contains("listen:") {
            String::new()
        } else {
            format!("listen: ['tcp/127.0.0.1:{port}'],")
        };
        std::fs::write(&cfg, format!("{{ {listen} data_dir: 'data', {extra} }}")).unwrap();
        let mut c = Command::new(scancorrd());
        c.args(["--config", cfg.to_str().unwrap()]);
        Service::spawn(c, dir, port)
    }

    fn spawn(mut c: Command, dir: &Path, port: u16) -> Service {
        let log = dir.join(format!("scancorrd-{port}.log"));
        let child = c
            .current_dir(dir)
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap();
        wait_listening(port, || {
            format!(
                "scancorrd did not start; its log:\n{}",
                std::fs::read_to_string(&log).unwrap_or_default()
            )
        });
        Service { child, log }
    }

    /// What it logged so far.
    pub fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// Its resident memory, KiB.
    pub fn rss_kib(&self) -> u64 {
        let s = std::fs::read_to_string(format!("/proc/{}/status", self.child.id())).unwrap();
        s.lines()
            .find_map(|l| l.strip_prefix("VmRSS:"))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
            .unwrap()
    }

    /// SIGKILL: no flushing, no closing (a crash); waits for the exit.
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// SIGTERM: flush and close; waits for the exit.
    pub fn stop(mut self) {
        let _ = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status();
        let t0 = Instant::now();
        loop {
            if let Some(st) = self.child.try_wait().unwrap() {
                assert!(
                    st.success(),
                    "scancorrd exited with {st:?}; its log:\n{}",
                    std::fs::read_to_string(&self.log).unwrap_or_default()
                );
                return;
            }
            assert!(
                t0.elapsed() < Duration::from_secs(20),
                "scancorrd ignored SIGTERM for 20 s; its log:\n{}",
                self.log()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

impl Drop for Service {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Every corrected point in a bag, in order.
pub fn points(bag: &Path) -> Vec<scancorr_proto::v1::CorrectedPoint> {
    use scancorr_proto::Message;
    let r = scancorr_bag::BagReader::open(bag).unwrap();
    let mut v = vec![];
    for m in r.messages().unwrap() {
        let m = m.unwrap();
        if m.stream == scancorr_bag::Stream::Points {
            v.extend(
                scancorr_proto::v1::CorrectedPointBatch::decode(&*m.data)
                    .unwrap()
                    .into_points()
                    .unwrap(),
            );
        }
    }
    v
}

/// Every estimator alarm in a bag, in order.
pub fn alarms(bag: &Path) -> Vec<scancorr_proto::v1::EstimatorAlarm> {
    use scancorr_proto::Message;
    let r = scancorr_bag::BagReader::open(bag).unwrap();
    let mut v = vec![];
    for m in r.messages().unwrap() {
        let m = m.unwrap();
        if m.stream == scancorr_bag::Stream::Alarms {
            v.push(scancorr_proto::v1::EstimatorAlarm::decode(&*m.data).unwrap());
        }
    }
    v
}

/// Copies the messages of the streams `keep` accepts into a new bag, without any metadata
/// record (bags as a recorder that knows nothing of the program would write them).
pub fn copy_bag(src: &Path, dst: &Path, keep: impl Fn(scancorr_bag::Stream) -> bool) {
    let r = scancorr_bag::BagReader::open(src).unwrap();
    let mut w = scancorr_bag::BagWriter::create(dst, scancorr_bag::BagHeader::default()).unwrap();
    for m in r.messages().unwrap() {
        let m = m.unwrap();
        if keep(m.stream) {
            w.write(
                m.stream,
                &m.machine,
                r.prefix(),
                m.log_time,
                m.publish_time,
                &m.data,
            )
            .unwrap();
        }
    }
    w.finish().unwrap();
}

/// A zenoh peer session connected to a service on a loopback port.
pub async fn session(port: u16) -> zenoh::Session {
    let mut c = zenoh::Config::default();
    c.insert_json5("mode", "\"peer\"").unwrap();
    c.insert_json5("connect/endpoints", &format!("[\"tcp/127.0.0.1:{port}\"]"))
        .unwrap();
    c.insert_json5("scouting/multicast/enabled", "false")
        .unwrap();
    zenoh::open(c).await.unwrap()
}

/// The status queryable's answer for `machine` (retried while the service is starting).
pub async fn status(s: &zenoh::Session, machine: &str) -> serde_json::Value {
    for _ in 0..40 {
        let r = s
            .get(format!("cmm/{machine}/status"))
            .timeout(Duration::from_secs(10))
            .await
            .unwrap();
        if let Ok(reply) = r.recv_async().await {
            let t = reply
                .into_result()
                .unwrap()
                .payload()
                .try_to_string()
                .unwrap()
                .to_string();
            return serde_json::from_str(&t).unwrap();
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    panic!("no status reply");
}

/// What `scancorr sim` adds to write the documents a machine's buyer gets: its data sheet
/// (`datasheet.json`) and the probe and stylus catalogue (`catalogue.json`), which
/// [`nominal_start`] makes the user's start from.
pub const BUYERS_DOCUMENTS: [&str; 4] = [
    "--datasheet-out",
    "datasheet.json",
    "--catalogue-out",
    "catalogue.json",
];

/// `scancorr sim --program PROGRAM` of `machine` (run `seed`) into `out`, with every library
/// effect hidden from the start and the buyer's documents beside, and the user's nominal start
/// `nominal.json` from them (with the catalogue's styli when `catalogue`); the truth goes to
/// `truth.json`.
pub fn measure_from_nominal(
    dir: &Path,
    program: &str,
    machine: &str,
    seed: &str,
    out: &str,
    catalogue: bool,
) {
    let mut a = vec![
        "sim",
        "--program",
        program,
        "--machine-seed",
        machine,
        "--seed",
        seed,
        "--out",
        out,
        "--calib-out",
        "start.json",
        "--truth",
        "truth.json",
    ];
    a.extend(BUYERS_DOCUMENTS);
    for h in scancorr_sim::LIBRARY_EFFECTS {
        a.extend(["--hide", h]);
    }
    ok(dir, &a);
    nominal_start(dir, "nominal.json", catalogue);
}

/// A user's nominal start, written to `to` by `scancorr calib nominal` from the data sheet a
/// `scancorr sim … BUYERS_DOCUMENTS` wrote in `dir`: no effects, data-sheet time constants
/// (30 % off) and, with `catalogue`, the catalogue's styli; without, the machine's own styli
/// (as a qualification would find them), taken from the simulator's `start.json` (`--tips-from`).
pub fn nominal_start(dir: &Path, to: &str, catalogue: bool) {
    let styli = if catalogue {
        ["--catalogue", "catalogue.json"]
    } else {
        ["--tips-from", "start.json"]
    };
    let mut a = vec!["calib", "nominal", "--datasheet", "datasheet.json"];
    a.extend(styli);
    a.extend(["--out", to]);
    ok(dir, &a);
}

/// `scancorr calibrate PROC --bag BAG --calib FROM --out TO --json` in `dir`: its JSON output,
/// which must hold no NaN.
#[allow(dead_code)]
pub fn calibrate_json(
    dir: &Path,
    proc: &str,
    bag: &str,
    from: &str,
    to: &str,
) -> serde_json::Value {
    let out = ok(
        dir,
        &[
            "calibrate",
            proc,
            "--bag",
            bag,
            "--calib",
            from,
            "--out",
            to,
            "--json",
        ],
    );
    assert!(!out.contains("NaN"), "{out}");
    serde_json::from_str(&out).unwrap_or_else(|e| panic!("not JSON ({e}): {out}"))
}

/// The user's start for a lab test, written to `to` in `dir`: the nominal model from the data
/// sheet `datasheet` (`scancorr calib nominal`, the styli from `listed` as a qualification
/// would find them) with the list of effects an earlier lab session chose — `listed`'s kinds
/// and variants, never its values: every parameter starts at zero — fitted by `scancorr lab
/// fit` on `bag`. The simulator's calibration only names the effects; the truth only judges.
#[allow(dead_code)]
pub fn fitted_start(dir: &Path, listed: &str, datasheet: &str, bag: &str, to: &str) {
    let nominal = format!("{to}.nominal.json");
    ok(
        dir,
        &[
            "calib",
            "nominal",
            "--datasheet",
            datasheet,
            "--tips-from",
            listed,
            "--out",
            &nominal,
        ],
    );
    let listed =
        scancorr_core::Calibration::from_json(&std::fs::read_to_string(dir.join(listed)).unwrap())
            .unwrap();
    let mut start = scancorr_core::Calibration::from_json(
        &std::fs::read_to_string(dir.join(&nominal)).unwrap(),
    )
    .unwrap();
    start.effects = listed
        .effects
        .iter()
        .map(|e| e.with_params(&vec![0.0; e.params().len()]).unwrap())
        .collect();
    let unfitted = format!("{to}.unfitted.json");
    std::fs::write(dir.join(&unfitted), start.to_json()).unwrap();
    ok(
        dir,
        &[
            "lab", "fit", "--bag", bag, "--calib", &unfitted, "--out", to,
        ],
    );
}

/// The first `n` numbers the README quotes after `marker` (its text with line breaks and runs
/// of spaces made single spaces): what a test holds to what the quoted command prints.
#[allow(dead_code)]
pub fn readme_figures(marker: &str, n: usize) -> Vec<f64> {
    let text = include_str!("../../../README.md")
        .split_whitespace()
        .collect::<Vec<_>>()
        .join(" ");
    let at = text
        .find(marker)
        .unwrap_or_else(|| panic!("README.md no longer says `{marker}`"));
    let mut out = vec![];
    let mut cur = String::new();
    for c in text[at + marker.len()..].chars() {
        if c.is_ascii_digit() || (c == '.' && !cur.is_empty()) {
            cur.push(c);
        } else if !cur.is_empty() {
            out.push(cur.trim_end_matches('.').parse().expect("a number"));
            cur.clear();
            if out.len() == n {
                break;
            }
        }
    }
    assert_eq!(out.len(), n, "README.md after `{marker}`: {out:?}");
    out
}

/// `printed` rounds to the README's `quoted` figure at the `decimals` it quotes.
#[allow(dead_code)]
pub fn assert_quoted(what: &str, quoted: f64, printed: f64, decimals: i32) {
    let half = 0.5 * 10f64.powi(-decimals) + 1e-9;
    assert!(
        (quoted - printed).abs() <= half,
        "README.md quotes {what} as {quoted}; the command prints {printed}: regenerate the figure"
    );
}

/// The Python interpreter of the project's venv (`scripts/python-env.sh`, last stdout line).
pub fn python() -> PathBuf {
    let out = Command::new("bash")
        .arg(root().join("scripts/python-env.sh"))
        .current_dir(root())
        .output()
        .expect("bash runs");
    assert!(
        out.status.success(),
        "scripts/python-env.sh failed (needs Python 3 with pip and venv):\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let py = PathBuf::from(
        String::from_utf8_lossy(&out.stdout)
            .lines()
            .last()
            .unwrap_or("")
            .trim(),
    );
    assert!(py.is_file(), "no interpreter: {}", py.display());
    py
}

/// Every topic, or topic and message path (`topic.field…`), that the shipped Foxglove layout
/// (`deploy/foxglove/scancorr-layout.json`) names: its strings, keys and values, that begin
/// with the default prefix `cmm/`.
pub fn foxglove_layout_paths() -> Vec<String> {
    fn walk(v: &serde_json::Value, out: &mut Vec<String>) {
        match v {
            serde_json::Value::String(s) if s.starts_with("cmm/") => out.push(s.clone()),
            serde_json::Value::Array(a) => a.iter().for_each(|x| walk(x, out)),
            serde_json::Value::Object(o) => {
                for (k, x) in o {
                    if k.starts_with("cmm/") {
                        out.push(k.clone());
                    }
                    walk(x, out);
                }
            }
            _ => {}
        }
    }
    let path = root().join("deploy/foxglove/scancorr-layout.json");
    let text = std::fs::read_to_string(&path).unwrap();
    let mut out = vec![];
    walk(&serde_json::from_str(&text).unwrap(), &mut out);
    out
}
