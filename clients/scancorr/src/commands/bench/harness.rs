//! What the benchmarks share: running this `scancorr` and the service as child processes,
//! asking the service, the processes' memory and CPU, quantiles and a detrend.

use anyhow::{bail, Context, Result};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// Runs this `scancorr` in `dir` with `args`; its stdout, or its stderr as the error.
pub(crate) fn exe(dir: &Path, args: &[&str]) -> Result<String> {
    let out = Command::new(std::env::current_exe()?)
        .current_dir(dir)
        .args(args)
        .output()
        .context("running scancorr")?;
    if !out.status.success() {
        bail!(
            "scancorr {}: {}",
            args.join(" "),
            String::from_utf8_lossy(&out.stderr)
        );
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// The service binary: next to this one (they are built and installed together).
pub(crate) fn scancorrd_path() -> Result<PathBuf> {
    let exe = std::env::current_exe()?;
    let p = exe.with_file_name(format!("scancorrd{}", std::env::consts::EXE_SUFFIX));
    if !p.exists() {
        bail!(
            "{} not found: build it with `cargo build --release -p scancorrd`",
            p.display()
        );
    }
    Ok(p)
}

/// Resident and peak memory (VmRSS, VmHWM) of a process, bytes.
pub(crate) fn memory(pid: u32) -> Option<(u64, u64)> {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let field = |name: &str| -> Option<u64> {
        let l = s.lines().find(|l| l.starts_with(name))?;
        let kb: u64 = l.split_whitespace().nth(1)?.parse().ok()?;
        Some(kb * 1024)
    };
    Some((field("VmRSS:")?, field("VmHWM:")?))
}

/// CPU seconds (user + system) a process has used; Linux clock ticks are 1/100 s.
pub(crate) fn cpu_seconds(pid: &str) -> Option<f64> {
    let s = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    let rest = &s[s.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks: u64 = f.get(11)?.parse::<u64>().ok()? + f.get(12)?.parse::<u64>().ok()?;
    Some(ticks as f64 / 100.0)
}

/// Task switches of a process so far, summed over its live threads: (voluntary — a thread
/// that waited, for a message or a lock —, involuntary — a thread preempted).
pub(crate) fn task_switches(pid: u32) -> Option<(u64, u64)> {
    let mut sum = (0u64, 0u64);
    for task in std::fs::read_dir(format!("/proc/{pid}/task"))
        .ok()?
        .flatten()
    {
        let Ok(s) = std::fs::read_to_string(task.path().join("status")) else {
            continue; // a thread that ended meanwhile
        };
        for line in s.lines() {
            let field = |name: &str| {
                line.strip_prefix(name)
                    .and_then(|v| v.trim().parse::<u64>().ok())
            };
            if let Some(v) = field("voluntary_ctxt_switches:") {
                sum.0 += v;
            } else if let Some(v) = field("nonvoluntary_ctxt_switches:") {
                sum.1 += v;
            }
        }
    }
    Some(sum)
}

/// A child process (scancorrd, or a relay) stopped with SIGTERM when dropped; `dir` is removed.
pub(crate) struct Service {
    pub(crate) child: Child,
    pub(crate) dir: PathBuf,
}

impl Drop for Service {
    fn drop(&mut self) {
        let _ = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status();
        let t = Instant::now();
        while t.elapsed() < Duration::from_secs(10) {
            if let Ok(Some(_)) = self.child.try_wait() {
                break;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
        std::fs::remove_dir_all(&self.dir).ok();
    }
}

/// Starts scancorrd in peer mode on `port` with its data in `dir`; `extra` adds config fields.
pub(crate) fn start_scancorrd(dir: &Path, port: u16, extra: &str) -> Result<Service> {
    start_scancorrd_with(
        dir,
        &format!("mode: \"peer\", listen: [\"tcp/127.0.0.1:{port}\"],"),
        extra,
    )
}

/// Starts scancorrd with `head` (its mode and endpoints) and `extra` config fields, its data
/// in `dir`.
pub(crate) fn start_scancorrd_with(dir: &Path, head: &str, extra: &str) -> Result<Service> {
    std::fs::create_dir_all(dir)?;
    let cfg = format!(
        "{{ {head} data_dir: \"{}\", allow_any_machine: true, {extra} }}",
        dir.join("data").display(),
    );
    std::fs::write(dir.join("scancorrd.json5"), cfg)?;
    let log = std::fs::File::create(dir.join("scancorrd.log"))?;
    let child = Command::new(scancorrd_path()?)
        .arg("--config")
        .arg(dir.join("scancorrd.json5"))
        // `SCANCORRD_LOG` (a `RUST_LOG` filter) to look inside a run; quiet by default.
        .env(
            "RUST_LOG",
            std::env::var("SCANCORRD_LOG").unwrap_or_else(|_| "warn,zenoh=error".into()),
        )
        .stdout(Stdio::null())
        .stderr(log)
        .spawn()
        .context("starting scancorrd")?;
    Ok(Service {
        child,
        dir: dir.to_path_buf(),
    })
}

/// A zenoh error as an `anyhow` one.
pub(crate) fn z<E: std::fmt::Display>(e: E) -> anyhow::Error {
    anyhow::anyhow!("{e}")
}

/// A peer session on loopback, connecting to the `connect` ports and listening on `listen`.
pub(crate) async fn session(connect: &[u16], listen: Option<u16>) -> Result<zenoh::Session> {
    let connect: Vec<String> = connect
        .iter()
        .map(|p| format!("tcp/127.0.0.1:{p}"))
        .collect();
    let listen: Vec<String> = listen
        .iter()
        .map(|p| format!("tcp/127.0.0.1:{p}"))
        .collect();
    let cfg = scancorrd::config::zenoh_config("peer", &listen, &connect, false)?;
    zenoh::open(cfg).await.map_err(z)
}

pub(crate) async fn query(
    s: &zenoh::Session,
    key: String,
    payload: Option<String>,
) -> Result<String> {
    let mut g = s.get(key.clone()).timeout(Duration::from_secs(30));
    if let Some(p) = payload {
        g = g.payload(p);
    }
    let replies = g.await.map_err(|e| anyhow::anyhow!("{e}"))?;
    let r = replies
        .recv_async()
        .await
        .map_err(|_| anyhow::anyhow!("{key}: no reply"))?;
    match r.into_result() {
        Ok(s) => Ok(s.payload().try_to_string()?.to_string()),
        Err(e) => bail!("{key}: {}", e.payload().try_to_string().unwrap_or_default()),
    }
}

/// The `p` quantile of `v` (sorted in place); 0 when empty.
pub(crate) fn pct(v: &mut [f64], p: f64) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    v[((v.len() as f64 - 1.0) * p).round() as usize]
}

/// y less its least-squares line over x.
pub(crate) fn detrend(x: &[f64], y: &[f64]) -> Vec<f64> {
    let n = x.len().max(1) as f64;
    let (mx, my) = (x.iter().sum::<f64>() / n, y.iter().sum::<f64>() / n);
    let sxx: f64 = x.iter().map(|a| (a - mx).powi(2)).sum();
    let b = if sxx > 0.0 {
        x.iter()
            .zip(y)
            .map(|(a, c)| (a - mx) * (c - my))
            .sum::<f64>()
            / sxx
    } else {
        0.0
    };
    x.iter()
        .zip(y)
        .map(|(a, c)| c - my - b * (a - mx))
        .collect()
}
