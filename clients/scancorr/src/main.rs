//! `scancorr` — the command-line tool: demo, benchmarks, calibration documents (and, as the
//! project grows, the simulator, bag correction, the model lab and the bus tools).
//!
//! Thin by design: every command parses arguments, calls the libraries and prints. Errors are
//! reported once, here, with their context chain.

mod bench;
mod demo;
mod synth;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use scancorr_core::Calibration;
use std::path::PathBuf;

#[derive(Parser)]
#[command(name = "scancorr", version, about = "Real-time correction of scanning CMM measurements")]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Run the main job on embedded defaults and print what it shows.
    Demo {
        /// Print the summary as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Benchmarks that print their figures.
    #[command(subcommand)]
    Bench(BenchCmd),
    /// Calibration documents.
    #[command(subcommand)]
    Calib(CalibCmd),
}

#[derive(Subcommand)]
enum BenchCmd {
    /// Throughput of the pure core with every effect enabled (one thread).
    Core {
        /// Print JSON (`samples_per_s`, …).
        #[arg(long)]
        json: bool,
        /// Scale samples per repetition.
        #[arg(long, default_value_t = 300_000)]
        points: usize,
        /// Repetitions (the best and the median are reported).
        #[arg(long, default_value_t = 5)]
        repeat: usize,
    },
}

#[derive(Subcommand)]
enum CalibCmd {
    /// Validate a calibration document; prints what is wrong, naming the field.
    Check {
        /// The JSON document.
        #[arg(long)]
        file: PathBuf,
        /// Also require it to be for this machine.
        #[arg(long)]
        machine: Option<String>,
    },
    /// Print an example document (nominal model only) for a machine.
    Example {
        /// Machine id.
        #[arg(long, default_value = "m1")]
        machine: String,
        /// Include every effect of the library (zero parameters).
        #[arg(long)]
        all_effects: bool,
    },
}

fn main() -> std::process::ExitCode {
    match run(Cli::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<()> {
    match cli.cmd {
        Cmd::Demo { json } => demo::run(json),
        Cmd::Bench(BenchCmd::Core { json, points, repeat }) => bench::core(points, repeat, json),
        Cmd::Calib(CalibCmd::Check { file, machine }) => {
            let text = std::fs::read_to_string(&file).with_context(|| format!("reading {}", file.display()))?;
            let cal = Calibration::from_json(&text).with_context(|| format!("{}", file.display()))?;
            cal.build().with_context(|| format!("{}", file.display()))?;
            if let Some(m) = machine {
                cal.check_machine(&m)?;
            }
            println!(
                "{}: valid — machine {}, version {}, {} effect(s)",
                file.display(),
                cal.machine_id,
                cal.version,
                cal.effects.len()
            );
            Ok(())
        }
        Cmd::Calib(CalibCmd::Example { machine, all_effects }) => {
            let cal = if all_effects { synth::all_effects_calibration(&machine) } else { Calibration::example(&machine) };
            println!("{}", cal.to_json());
            Ok(())
        }
    }
}
