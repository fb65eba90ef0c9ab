//! Every command block of README.md runs as written: each fenced block tagged `sh` is taken
//! from the file itself (not copied here) and run, in the README's order, with
//! `bash -euo pipefail` in one scratch folder, so state carries from block to block as it
//! does for a reader following the README. One exception: a block whose only command is
//! `scancorr demo` (the "Two commands" block) writes nothing but its own folder, which no other
//! block reads, so it runs beside the others in a folder of its own (`work-N/`, laid out the
//! same way): the lab is one thread and the machine has two cores. Its reports are then checked
//! in headless Chromium from that folder (`common::chromium::check_demo_reports`: the compare,
//! discover and, by the `lab diagnose` line the demo prints next, diagnose reports).
//!
//! The scratch folder is laid out as a clone is: the blocks run in `work/`, which reaches the
//! repository's `deploy/`, `scripts/` and `clients/` (symbolic links) and whose parent holds
//! `shared/` (a link to the one beside the repository), so `../shared/reference/…` resolves as
//! from the repository's root. `target/release` is first on `PATH` (`scancorr`, `scancorrd`,
//! `scancorr-router`), and `cargo` finds the workspace from there as it does in a clone
//! (`--manifest-path` of the repository; the binaries and the working folder stay the
//! block's).
//!
//! Blocks tagged `text` (or any other language) are output and reference, never run; a fenced
//! block without a language tag is refused, so that no block escapes by accident. Lines not run
//! as written are listed in [`EXCLUDED`], each with its reason: the test command (it would run
//! itself) and the benchmarks of minutes, whose same subcommands run here with short options
//! (the CI's time stays under its budget); an exclusion that matches no line fails.
//! A failure names the block, the README line whose command failed and the block's output;
//! every block runs (a later failure may follow from an earlier one).

mod common;
use common::*;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// README lines that are not run as written: (the line exactly, what runs instead — nothing
/// for `None` — and why). Each must match exactly one line of a ```sh block.
const EXCLUDED: &[(&str, Option<&str>, &str)] = &[
    (
        "./scripts/test.sh",
        None,
        "the README's test command runs the whole suite, this test included: run here, it would \
         run itself",
    ),
    (
        "cargo run --release --bin scancorr -- bench live --rounds 5   # scancorrd vs a relay with the same declarations and output; added latency inside each",
        Some("cargo run --release --bin scancorr -- bench live --rounds 1 --points 3000"),
        "a benchmark of minutes on a loaded machine: the same subcommand runs, one short round",
    ),
    (
        "cargo run --release --bin scancorr -- bench fleet --machines 200 --seconds 5  # one scancorrd, many machines at 1 kHz (default 1000 machines for 10 s; --workers N, --links K, --pace 0.25, --router)",
        Some("cargo run --release --bin scancorr -- bench fleet --machines 20 --seconds 1"),
        "a benchmark: the same subcommand runs, 20 machines for 1 s",
    ),
    (
        "cargo run --release --bin scancorr -- bench fleet --relay --machines 200 --seconds 5  # the same fleet served by a bare relay (no correction, no shards): what the bus alone costs per point (--relay-effects N: N entries in each point's breakdown)",
        Some("cargo run --release --bin scancorr -- bench fleet --relay --machines 20 --seconds 1"),
        "a benchmark: the same subcommand runs, 20 machines for 1 s",
    ),
    (
        "cargo run --release --bin scancorr -- bench fleet --largest --workers 2 --from 100 --machines 300 --step 100 --runs 1 --seconds 3  # the largest fleet that keeps real time with N workers, by bisection (defaults --machines 1000 --step 50 --runs 2, 10 s each: minutes)",
        Some(
            "cargo run --release --bin scancorr -- bench fleet --largest --workers 1 --from 4 --machines 8 --step 4 --runs 1 --seconds 1",
        ),
        "a benchmark: the same search runs over 4 to 8 machines, 1 s each",
    ),
    (
        "cargo run --release --bin scancorr -- bench procedures --runs 2  # calibration procedures: σ honesty over runs (the default 20 runs, for the figures: minutes)",
        Some("cargo run --release --bin scancorr -- bench procedures --runs 1 --procedure tips"),
        "a benchmark of minutes: the same subcommand runs, one procedure, one run",
    ),
    (
        "cargo run --release --bin scancorr -- bench discover  # lab discover on the default campaign from nominal: time, steps, memory",
        Some("cargo run --release --bin scancorr -- bench discover --max-steps 1"),
        "the whole loop runs in the README's lab block above and in `scancorr demo`: the same \
         benchmark runs here for its first step",
    ),
];

/// How the blocks' `cargo run --release --bin NAME -- ARGS` (and `--example NAME`) lines run:
/// the binary the suite's build made (`target/release/NAME`, `target/release/examples/NAME`)
/// with ARGS. `cargo run -p`/`--bin` resolves the features of the one package it runs, not the
/// workspace's, so on a fresh clone it would compile a second copy of shared dependencies
/// inside this test (minutes, and the zenoh stack's fingerprints flip between the two); the
/// command a reader types still builds and runs the same binary. A `cargo run` line of another
/// form fails here, so that it is not silently built anew.
const RUN_BUILT: &str = r#"local kind= name= a; local -a rest=(); shift
      while [ $# -gt 0 ]; do case "$1" in
        --release) ;; --bin) kind=bin; name=$2; shift ;; --example) kind=example; name=$2; shift ;;
        --) shift; rest=("$@"); break ;;
        *) echo "readme_blocks.rs: cannot run \`cargo run $*\` from the built binaries" >&2; return 2 ;;
      esac; shift; done
      case $kind in bin) a="$README_BIN_DIR/$name" ;; example) a="$README_BIN_DIR/examples/$name" ;;
        *) echo "readme_blocks.rs: \`cargo run\` without --bin or --example" >&2; return 2 ;; esac
      "$a" "${rest[@]}"; return"#;

/// A block that runs longer is stopped and fails.
const BLOCK_TIMEOUT: Duration = Duration::from_secs(15 * 60);

/// A fenced block of the README.
struct Block {
    /// Line of the opening fence (1-based).
    fence: usize,
    /// The language tag.
    tag: String,
    /// (line number, text) of its lines.
    lines: Vec<(usize, String)>,
}

fn blocks(text: &str) -> (Vec<Block>, Vec<String>) {
    let mut out = vec![];
    let mut problems = vec![];
    let mut open: Option<Block> = None;
    for (i, line) in text.lines().enumerate() {
        let n = i + 1;
        let fence = line.trim_start().strip_prefix("```");
        match (&mut open, fence) {
            (None, Some(info)) => {
                let tag = info.split_whitespace().next().unwrap_or("").to_string();
                if tag.is_empty() {
                    problems.push(format!(
                        "README.md:{n}: a fenced block without a language tag: tag it ```sh \
                         (commands, run by this test) or ```text (output, reference)"
                    ));
                } else if ["bash", "shell", "console", "zsh"].contains(&tag.as_str()) {
                    problems.push(format!(
                        "README.md:{n}: ```{tag}: tag commands ```sh (run by this test) or \
                         ```text"
                    ));
                }
                open = Some(Block {
                    fence: n,
                    tag,
                    lines: vec![],
                });
            }
            (Some(_), Some(rest)) if rest.trim().is_empty() => out.push(open.take().unwrap()),
            (Some(b), _) => b.lines.push((n, line.to_string())),
            (None, None) => {}
        }
    }
    if let Some(b) = open {
        problems.push(format!(
            "README.md:{}: a fenced block never closed",
            b.fence
        ));
    }
    (out, problems)
}

/// Kills what a block left running: its whole process group.
fn kill_group(pgid: u32) {
    for sig in ["-TERM", "-KILL"] {
        let _ = Command::new("kill")
            .args([sig, "--", &format!("-{pgid}")])
            .stderr(Stdio::null())
            .status();
        std::thread::sleep(Duration::from_millis(300));
    }
}

/// The scratch layout of a clone: `work/` with links to the repository's folders the README
/// names, `shared/` beside it.
fn layout(scratch: &Path, name: &str) -> PathBuf {
    let root = root();
    let work = scratch.join(name);
    std::fs::create_dir_all(&work).unwrap();
    for d in ["deploy", "scripts", "clients"] {
        std::os::unix::fs::symlink(root.join(d), work.join(d)).unwrap();
    }
    let shared = root.parent().unwrap().join("shared");
    assert!(
        shared.is_dir(),
        "{}: the README's real data is read from `../shared` beside the repository",
        shared.display()
    );
    let link = scratch.join("shared");
    if !link.exists() {
        std::os::unix::fs::symlink(&shared, link).unwrap();
    }
    work
}

/// The binaries the blocks call by name, built when missing.
fn bin_dir() -> PathBuf {
    let dir = scancorrd().parent().unwrap().to_path_buf();
    if !dir.join("scancorr-router").exists() {
        let mut c = Command::new(env!("CARGO"));
        c.args(["build", "-p", "scancorrd", "--bin", "scancorr-router"])
            .current_dir(root());
        if !cfg!(debug_assertions) {
            c.arg("--release");
        }
        assert!(
            c.status().unwrap().success(),
            "building scancorr-router failed"
        );
    }
    dir
}

/// The script a block runs: the prelude, then its lines (an excluded line replaced or
/// neutralised, with its reason).
fn script(b: &Block) -> String {
    let mut script = prelude().join("\n") + "\n";
    for (_, t) in &b.lines {
        match EXCLUDED.iter().find(|(l, _, _)| t.trim() == *l) {
            Some((_, Some(instead), why)) => {
                script += &format!("{instead}  # readme_blocks.rs, shortened: {why}\n")
            }
            Some((l, None, why)) => {
                script += &format!("true  # not run by readme_blocks.rs: `{l}`: {why}\n")
            }
            None => script += &format!("{t}\n"),
        }
    }
    script
}

/// Lines before the block's own: the failing command's line is reported from bash's LINENO.
fn prelude() -> [String; 3] {
    [
        "set -E".to_string(),
        "trap 'echo \"README_BLOCK_FAILED_AT=$LINENO exit $?\" >&2' ERR".to_string(),
        format!(
            "cargo() {{ if [ \"$1\" = run ]; then {RUN_BUILT}; fi; \
             command cargo \"$1\" --manifest-path '{}' \"${{@:2}}\"; }}",
            root().join("Cargo.toml").display()
        ),
    ]
}

/// What a block's run gave.
struct Ran {
    fence: usize,
    secs: f64,
    /// Why it failed, with the failing README line and its output's tail.
    failure: Option<String>,
}

/// Runs blocks: where the binaries are, where the logs go.
struct Runner {
    bins: PathBuf,
    logs: PathBuf,
}

impl Runner {
    /// Runs block `k` (its script) in `dir` with `bash -euo pipefail`, stops what it left
    /// running, and says how it went.
    fn block(&self, k: usize, b: &Block, script: &str, dir: &Path) -> Ran {
        use std::os::unix::process::CommandExt;
        let path = format!(
            "{}:{}",
            self.bins.display(),
            std::env::var("PATH").unwrap_or_default()
        );
        let file = self.logs.join(format!("{:02}-line{}.sh", k + 1, b.fence));
        std::fs::write(&file, script).unwrap();
        let log_path = file.with_extension("log");
        let log = std::fs::File::create(&log_path).unwrap();
        let t0 = Instant::now();
        let mut child = Command::new("bash")
            .args(["-euo", "pipefail"])
            .arg(&file)
            .current_dir(dir)
            .env("PATH", &path)
            .env("README_BIN_DIR", &self.bins)
            .stdin(Stdio::null())
            .stdout(log.try_clone().unwrap())
            .stderr(log)
            .process_group(0)
            .spawn()
            .unwrap();
        let status = loop {
            if let Some(s) = child.try_wait().unwrap() {
                break Some(s);
            }
            if t0.elapsed() > BLOCK_TIMEOUT {
                break None;
            }
            std::thread::sleep(Duration::from_millis(100));
        };
        // Whatever the block left running (a service started with `&`) goes with it.
        kill_group(child.id());
        let _ = child.wait();
        let secs = t0.elapsed().as_secs_f64();
        let output = std::fs::read_to_string(&log_path).unwrap_or_default();
        let last = b.lines.last().map_or(b.fence, |l| l.0);
        // A `cargo` line of the block that found the binaries stale builds them first: its
        // time is the build's, not the block's.
        let compiled = output
            .lines()
            .filter(|l| l.trim_start().starts_with("Compiling "))
            .count();
        eprintln!(
            "README.md:{} (```sh, lines {}–{last}): {} in {secs:.1} s{}{}",
            b.fence,
            b.fence + 1,
            match status {
                Some(s) if s.success() => "ok".to_string(),
                Some(s) => format!("FAILED ({s})"),
                None => "TIMED OUT".to_string(),
            },
            if compiled > 0 {
                format!(" (cargo compiled {compiled} crate(s) first)")
            } else {
                String::new()
            },
            if dir.ends_with("work") {
                String::new()
            } else {
                format!(", beside the others in {}", dir.display())
            }
        );
        if status.is_some_and(|s| s.success()) {
            return Ran {
                fence: b.fence,
                secs,
                failure: None,
            };
        }
        // The README line of the failing command, from the ERR trap's LINENO.
        let at = output
            .lines()
            .rev()
            .find_map(|l| l.strip_prefix("README_BLOCK_FAILED_AT="))
            .and_then(|l| l.split_whitespace().next()?.parse::<usize>().ok())
            .and_then(|n| b.lines.get(n.checked_sub(prelude().len() + 1)?))
            .map(|(n, t)| format!("README.md:{n}: `{}`", t.trim()))
            .unwrap_or_else(|| "(the failing line was not reported)".into());
        let tail: Vec<&str> = output.lines().collect();
        let tail = tail[tail.len().saturating_sub(120)..].join("\n");
        Ran {
            fence: b.fence,
            secs,
            failure: Some(format!(
                "the ```sh block at README.md:{} {} — failed at {at}\n--- its output (last 120 \
                 lines; all of it in {}) ---\n{tail}\n---",
                b.fence,
                match status {
                    Some(s) => format!("exited with {s}"),
                    None => format!("ran over {} s and was stopped", BLOCK_TIMEOUT.as_secs()),
                },
                log_path.display()
            )),
        }
    }
}

#[test]
fn every_sh_block_of_the_readme_runs_as_written() {
    let readme = std::fs::read_to_string(root().join("README.md")).unwrap();
    let (all, problems) = blocks(&readme);
    assert!(problems.is_empty(), "{}", problems.join("\n"));
    let sh: Vec<&Block> = all.iter().filter(|b| b.tag == "sh").collect();
    assert!(!sh.is_empty(), "README.md has no ```sh block");

    // Every exclusion matches exactly one line of a ```sh block.
    for (line, instead, why) in EXCLUDED {
        let at: Vec<usize> = sh
            .iter()
            .flat_map(|b| &b.lines)
            .filter(|(_, t)| t.trim() == *line)
            .map(|(n, _)| *n)
            .collect();
        assert_eq!(
            at.len(),
            1,
            "exclusion `{line}` matches README lines {at:?}: it must match exactly one"
        );
        match instead {
            Some(i) => eprintln!("README.md:{}: runs as `{i}`: {why}", at[0]),
            None => eprintln!("README.md:{}: `{line}` not run: {why}", at[0]),
        }
    }

    let scratch = scratch("readme-blocks");
    let work = layout(&scratch, "work");
    let logs = scratch.join("blocks");
    std::fs::create_dir_all(&logs).unwrap();
    let run = Runner {
        bins: bin_dir(),
        logs,
    };
    let scripts: Vec<(usize, &Block, String)> = sh
        .iter()
        .enumerate()
        .map(|(k, b)| (k, *b, script(b)))
        .collect();
    // A block whose only command is `demo` writes nothing but its own folder, which no other
    // block reads: it runs beside the others, in a folder of its own (the lab is one thread,
    // the machine has two cores).
    let alone = |b: &Block| {
        let runs: Vec<&str> = b
            .lines
            .iter()
            .map(|(_, t)| t.trim())
            .filter(|t| !t.is_empty() && !t.starts_with('#'))
            .filter(|t| !EXCLUDED.iter().any(|(l, _, _)| t == l))
            .collect();
        !runs.is_empty()
            && runs
                .iter()
                .all(|t| t.starts_with("cargo run --release --bin scancorr -- demo"))
    };
    let t_all = Instant::now();
    let (beside, in_order): (Vec<_>, Vec<_>) = scripts.iter().partition(|(_, b, _)| alone(b));
    let mut results = vec![];
    std::thread::scope(|s| {
        let aside = s.spawn(|| {
            beside
                .iter()
                .map(|(k, b, script)| {
                    let dir = layout(&scratch, &format!("work-{}", k + 1));
                    let mut r = run.block(*k, b, script, &dir);
                    // The demo's reports in a browser, from the folder it wrote (not run twice).
                    if r.failure.is_none() {
                        let log = run.logs.join(format!("{:02}-line{}.log", k + 1, b.fence));
                        r.failure = common::chromium::check_demo_reports(
                            &dir,
                            &std::fs::read_to_string(log).unwrap_or_default(),
                        );
                    }
                    r
                })
                .collect::<Vec<_>>()
        });
        for (k, b, script) in &in_order {
            results.push(run.block(*k, b, script, &work));
        }
        results.extend(aside.join().unwrap());
    });
    results.sort_by_key(|r| r.fence);
    let failures: Vec<String> = results.iter().filter_map(|r| r.failure.clone()).collect();
    let mut times: Vec<(usize, f64)> = results.iter().map(|r| (r.fence, r.secs)).collect();
    times.sort_by(|a, b| b.1.total_cmp(&a.1));
    eprintln!(
        "{} ```sh block(s) in {:.1} s; the slowest: {}",
        sh.len(),
        t_all.elapsed().as_secs_f64(),
        times
            .iter()
            .take(5)
            .map(|(l, s)| format!("line {l} {s:.1} s"))
            .collect::<Vec<_>>()
            .join(", ")
    );
    assert!(
        failures.is_empty(),
        "{} README block(s) failed (run in {}):\n\n{}",
        failures.len(),
        work.display(),
        failures.join("\n\n")
    );
}

#[test]
fn blocks_are_read_from_their_fences_and_untagged_ones_are_refused() {
    let (b, p) = blocks("a\n```sh\necho 1\n\necho 2\n```\n```text\nout\n```\n");
    assert!(p.is_empty(), "{p:?}");
    assert_eq!(b.len(), 2);
    assert_eq!((b[0].fence, b[0].tag.as_str()), (2, "sh"));
    assert_eq!(
        b[0].lines,
        [
            (3, "echo 1".into()),
            (4, String::new()),
            (5, "echo 2".into())
        ]
    );
    assert_eq!(b[1].tag, "text");
    let (_, p) = blocks("```\nls\n```\n```bash\nls\n```\n```sh\nls\n");
    assert_eq!(p.len(), 3, "{p:?}");
    assert!(p[0].contains("README.md:1: a fenced block without a language tag"));
    assert!(p[1].contains("README.md:4: ```bash"));
    assert!(p[2].contains("README.md:7: a fenced block never closed"));
}
