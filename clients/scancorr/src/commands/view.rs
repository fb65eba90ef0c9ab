//! `scancorr view`: the bus's corrected points and alarms live in Foxglove — a Foxglove
//! WebSocket server on localhost (`shared::foxglove_ws`) fed by a zenoh client of the bus, on
//! any machine that reaches it; scancorrd does nothing more for it. With `--raw`, the machine's
//! raw streams too, as they are on the bus (our own protobuf batches, schema advertised).

use crate::shared::bus::Bus;
use crate::shared::foxglove::Nominal;
use crate::shared::foxglove_ws::{Server, SUBPROTOCOL};
use anyhow::Result;
use scancorr_bag::Stream;
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::sync::mpsc;
use std::time::{Duration, Instant};
use zenoh::Wait;

/// `scancorr view`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Port of the WebSocket server on 127.0.0.1 (Foxglove's default 8765; 0: any free one,
    /// printed).
    #[arg(long, default_value_t = 8765)]
    pub port: u16,
    /// Machine to show (repeatable): its channels are advertised at once. Default: every
    /// machine under the prefix, each advertised when its first message arrives.
    #[arg(long)]
    pub machine: Vec<String>,
    /// A bag whose program (`scancorr.program` record, e.g. the simulator's) gives the nominal
    /// features: the scene and each point's deviation. Without it, no deviations.
    #[arg(long, value_name = "BAG")]
    pub nominal: Option<PathBuf>,
    /// Also serve the raw streams (commanded path, scales, probe, temperatures, distance,
    /// stage) as channels named by their bus keys, schema our `scancorr.v1` batch messages.
    #[arg(long)]
    pub raw: bool,
    /// Stop after this many seconds (default: run until interrupted).
    #[arg(long)]
    pub seconds: Option<f64>,
    #[command(flatten)]
    pub bus: Bus,
}

/// Runs `scancorr view`.
pub fn exec(a: Args) -> Result<()> {
    a.bus.check()?;
    for m in &a.machine {
        crate::shared::output::check_machine("--machine", m)?;
    }
    if let Some(s) = a.seconds {
        anyhow::ensure!(s.is_finite() && s > 0.0, "--seconds must be > 0, got {s}");
    }
    let nominal = a.nominal.as_deref();
    let nominal = nominal
        .map(|b| Nominal::from_bag("--nominal", b))
        .transpose()?;
    let mut server = Server::new(&a.bus.prefix, nominal, a.raw);
    for m in &a.machine {
        server.announce_machine(m);
    }
    let mut cfg = a.bus.config()?;
    for (k, v) in [
        ("connect/timeout_ms", "0"),
        ("connect/exit_on_failure", "true"),
    ] {
        cfg.insert_json5(k, v)
            .map_err(|e| anyhow::anyhow!("zenoh configuration `{k}`: {e}"))?;
    }
    let session = zenoh::open(cfg).wait().map_err(|e| {
        anyhow::anyhow!("cannot connect to the bus (is scancorrd or a zenoh router running?): {e}")
    })?;
    let (tx, rx) = mpsc::channel::<(String, Vec<u8>)>();
    let machines = match a.machine.is_empty() {
        true => vec!["*".to_string()],
        false => a.machine.clone(),
    };
    let mut subs = vec![];
    for m in &machines {
        let raw: &[Stream] = if a.raw { &Stream::RAW } else { &[] };
        for &s in Stream::OUTPUT.iter().chain(raw) {
            let tx = tx.clone();
            let sub = session
                .declare_subscriber(s.key(&a.bus.prefix, m))
                .callback(move |sample| {
                    let key = sample.key_expr().as_str().to_string();
                    let _ = tx.send((key, sample.payload().to_bytes().into_owned()));
                })
                .wait()
                .map_err(|e| anyhow::anyhow!("subscribing: {e}"))?;
            subs.push(sub);
        }
    }
    drop(tx);
    let addr = server.listen(&format!("127.0.0.1:{}", a.port))?;
    eprintln!(
        "view: Foxglove WebSocket on ws://{addr} ({SUBPROTOCOL}): in Foxglove, Open connection → Foxglove WebSocket; layout deploy/foxglove/scancorr-layout.json"
    );
    let deadline = a
        .seconds
        .map(|s| Instant::now() + Duration::from_secs_f64(s));
    let (mut n, mut other) = (0u64, 0u64);
    loop {
        let wait = match deadline {
            Some(d) if Instant::now() >= d => break,
            Some(d) => d.saturating_duration_since(Instant::now()),
            None => Duration::from_secs(1),
        };
        match rx.recv_timeout(wait.min(Duration::from_millis(200))) {
            Ok((key, bytes)) => match server.handle(&key, &bytes) {
                true => n += 1,
                false => other += 1,
            },
            Err(mpsc::RecvTimeoutError::Timeout) => {}
            Err(mpsc::RecvTimeoutError::Disconnected) => break,
        }
    }
    drop(subs);
    let _ = session.close().wait();
    eprintln!(
        "view: served {n} message(s) from the bus ({other} not read: not a stream served, or malformed); {} dropped for clients that fell behind",
        server.dropped.load(Ordering::Relaxed)
    );
    Ok(())
}
