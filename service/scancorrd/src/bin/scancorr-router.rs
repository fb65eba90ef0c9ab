//! `scancorr-router`: a zenoh router built on zenoh's router mode, loading the same JSON5
//! configuration `zenohd` does (`deploy/router.json5`: TLS with client certificates, access
//! control by certificate common name). The project ships it so that a router for tests and
//! small installs is built from crates with the rest (no `zenohd` install).
//!
//! ```text
//! scancorr-router -c deploy/router.json5 [--listen ENDPOINT]...
//! ```
//! Runs until SIGTERM or Ctrl-C. A configuration error is one line on stderr and exit 2.

use clap::Parser;
use std::path::PathBuf;

#[derive(Parser)]
#[command(
    name = "scancorr-router",
    version,
    about = "zenoh router (router mode) from a zenohd JSON5 configuration"
)]
struct Args {
    /// zenoh configuration file (JSON5), as `zenohd -c` takes.
    #[arg(short, long)]
    config: PathBuf,
    /// Replace the file's listen endpoints.
    #[arg(long)]
    listen: Vec<String>,
}

fn main() {
    let a = Args::parse();
    let rt = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
    {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("scancorr-router: cannot start a runtime: {e}");
            std::process::exit(1);
        }
    };
    if let Err(e) = rt.block_on(run(a)) {
        eprintln!("scancorr-router: {e}");
        std::process::exit(2);
    }
}

async fn run(a: Args) -> Result<(), String> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let mut cfg =
        zenoh::Config::from_file(&a.config).map_err(|e| format!("{}: {e}", a.config.display()))?;
    cfg.insert_json5("mode", "\"router\"")
        .map_err(|e| format!("mode: {e}"))?;
    if !a.listen.is_empty() {
        let eps = serde_json::to_string(&a.listen).map_err(|e| e.to_string())?;
        cfg.insert_json5("listen/endpoints", &eps)
            .map_err(|e| format!("--listen: {e}"))?;
    }
    let session = zenoh::open(cfg)
        .await
        .map_err(|e| format!("{}: {e}", a.config.display()))?;
    eprintln!(
        "scancorr-router {}: routing (zid {}) with {}",
        env!("CARGO_PKG_VERSION"),
        session.zid(),
        a.config.display()
    );
    let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .map_err(|e| e.to_string())?;
    tokio::select! {
        _ = term.recv() => {}
        _ = tokio::signal::ctrl_c() => {}
    }
    session.close().await.map_err(|e| e.to_string())?;
    Ok(())
}
