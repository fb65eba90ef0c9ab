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
}

/// zenoh's runtimes unless `ZENOH_RUNTIME` says otherwise: four transmit workers. A link
/// whose subscriber stopped reading holds its queue lock while a publication waits for room,
/// and zenoh's transmit task for that link then blocks its worker; with one worker (zenoh's
/// default) every other link would wait too.
const ZENOH_RUNTIME_DEFAULT: &str = "(tx: (worker_threads: 4))";

fn main() -> Result<()> {
    // Read once by zenoh at its first use, so set before any thread or runtime exists.
    if std::env::var_os("ZENOH_RUNTIME").is_none() {
        std::env::set_var("ZENOH_RUNTIME", ZENOH_RUNTIME_DEFAULT);
    }
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?
        .block_on(serve())
}

async fn serve() -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "info,zenoh=warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let a = Args::parse();
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
