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

#[tokio::main]
async fn main() -> Result<()> {
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
