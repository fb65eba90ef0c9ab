//! `scancorrd`: runs the service on embedded defaults or a JSON5 configuration file.

use anyhow::Result;
use clap::Parser;
use std::path::PathBuf;

#[derive(Parser)]
#[command(
    name = "scancorrd",
    version,
    about = "scancorr correction service on zenoh"
)]
struct Args {
    /// JSON5 configuration file (mode, listen, connect, prefix, machines, data_dir, …).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Override the listen endpoint.
    #[arg(long)]
    listen: Vec<String>,
    /// Override the data folder.
    #[arg(long)]
    data_dir: Option<PathBuf>,
    /// Override the number of correcting worker shards (0: one per core).
    #[arg(long)]
    workers: Option<usize>,
    /// Log lines as `text` (colour only on a terminal) or `json` (one object per line).
    #[arg(long, default_value = "text", value_parser = ["text", "json"])]
    log_format: String,
}

/// zenoh's runtimes unless `ZENOH_RUNTIME` says otherwise (an operator's own setting wins):
/// - four transmit workers. A link whose subscriber stopped reading holds its queue lock while
///   a publication waits for room, and zenoh's transmit task for that link then blocks its
///   worker; with one worker (zenoh's default) every other link would wait too.
/// - the acceptor's runtime handed over to the receiving one. An accepted link's socket is
///   registered with the reactor of the runtime that accepted it, so with zenoh's default
///   every incoming batch woke the acceptor's thread, which then woke a receiving worker to
///   read it: two task switches where one does. Paired runs of `scancorr bench fleet
///   --machines 1000 --seconds 5` (5 pairs): the service's task switches 0.76x (0.74–0.85),
///   its CPU per point 0.99x (0.89–1.04: no gain beyond the noise). The cost: a receiving
///   worker held up now holds up the links' reactor too; the service's callbacks never wait
///   for a link (the one wait, a queryable's bounded channel, is for the control task).
const ZENOH_RUNTIME_DEFAULT: &str = "(tx: (worker_threads: 4), acc: (handover: rx))";

fn main() {
    // Read once by zenoh at its first use, so set before any thread or runtime exists.
    if std::env::var_os("ZENOH_RUNTIME").is_none() {
        std::env::set_var("ZENOH_RUNTIME", ZENOH_RUNTIME_DEFAULT);
    }
    let a = Args::parse();
    init_logs(&a.log_format);
    let r = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(anyhow::Error::from)
        .and_then(|rt| rt.block_on(serve(a)));
    // An error (a configuration that cannot be used, a store that cannot be opened) is one
    // line, with its causes, and no backtrace.
    if let Err(e) = r {
        eprintln!("scancorrd: error: {e:#}");
        std::process::exit(2);
    }
}

/// Logs on stderr: text (colour only when stderr is a terminal and `NO_COLOR` is not set: never
/// in a file or a pipe) or JSON lines (never colour; values typed: numbers and booleans as
/// JSON's, see the fields of `server`).
fn init_logs(format: &str) {
    use std::io::IsTerminal;
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| "info,zenoh=warn".into());
    let b = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    if format == "json" {
        b.json().flatten_event(true).with_ansi(false).init();
    } else {
        let colour = std::io::stderr().is_terminal()
            && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty());
        b.with_ansi(colour).init();
    }
}

async fn serve(a: Args) -> Result<()> {
    let mut cfg = match &a.config {
        Some(p) => scancorrd::Config::load(p)?,
        None => scancorrd::Config::default(),
    };
    if !a.listen.is_empty() {
        cfg.listen = a.listen;
    }
    if let Some(d) = a.data_dir {
        cfg.data_dir = d;
    }
    if let Some(w) = a.workers {
        cfg.workers = w;
    }
    let shutdown = async {
        #[cfg(unix)]
        {
            let mut term =
                tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
                    .expect("signal handler");
            tokio::select! { _ = tokio::signal::ctrl_c() => {}, _ = term.recv() => {} }
        }
        #[cfg(not(unix))]
        {
            let _ = tokio::signal::ctrl_c().await;
        }
    };
    scancorrd::run(cfg, shutdown).await?;
    Ok(())
}
