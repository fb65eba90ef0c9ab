//! `scancorr` — the command-line tool: demo, benchmarks, calibration documents (and, as the
//! project grows, the simulator, bag correction, the model lab and the bus tools).
//!
//! Thin by design: every command parses arguments, calls the libraries and prints. Errors are
//! reported once, here, with their context chain.

// The `bench fleet` JSON summary is one large `serde_json::json!`, deeper than the default 128.
#![recursion_limit = "256"]

#[macro_use]
mod shared;
mod commands;
mod report;

use anyhow::Result;
use clap::{Parser, Subcommand};
use commands::{bench::BenchCmd, calib::CalibCmd, shape::ShapeCmd, sim::SimCli};
use shared::bus;
use std::path::PathBuf;

#[derive(Parser)]
#[command(
    name = "scancorr",
    version,
    about = "Real-time correction of scanning CMM measurements"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
    /// Let output flags (--out, --report, …) replace files that exist (also SCANCORR_FORCE=1);
    /// without it an existing file is refused. `--out -` writes a text output to stdout.
    #[arg(long, global = true)]
    force: bool,
}

#[derive(Subcommand)]
enum Cmd {
    /// The main job on embedded defaults: the model lab's loop on a simulated machine with a
    /// hidden effect — compare, diagnose, add, and the error falling.
    Demo {
        /// Switch on physics the default machine does not have (repeatable): probe_lobing,
        /// rigid_body, cyclic_error, backlash, latching.
        #[arg(long)]
        with: Vec<String>,
        /// Keep the bags and calibrations in this folder.
        #[arg(long)]
        dir: Option<PathBuf>,
        /// Print a JSON summary.
        #[arg(long)]
        json: bool,
    },
    /// Benchmarks that print their figures.
    #[command(subcommand)]
    Bench(BenchCmd),
    /// Calibration documents.
    #[command(subcommand)]
    Calib(CalibCmd),
    /// The wire contract: write the protobuf FileDescriptorSet (for consumers in other
    /// languages that build message classes from it).
    Proto {
        /// Output file (`.bin`).
        #[arg(long)]
        out: PathBuf,
    },
    /// Least-squares geometry fits (the ones the lab uses).
    #[command(subcommand)]
    Shape(ShapeCmd),
    /// Corrected points of a bag as ASCII: CSV (every point, every field, the per-effect
    /// breakdown) or x y z rows of the contact points (vendor CMM software, numpy).
    Export {
        /// A bag of corrected points (`scancorr correct … --out` or `scancorr record`).
        #[arg(long)]
        bag: PathBuf,
        /// csv or xyz.
        #[arg(long, default_value = "csv")]
        format: String,
        /// Only this scan segment.
        #[arg(long)]
        segment: Option<u32>,
        /// The machine, when the bag holds several.
        #[arg(long)]
        machine: Option<String>,
        /// Output file.
        #[arg(long)]
        out: PathBuf,
        /// The raw streams instead: one wide CSV (t_ns, one row per time) and its mapping
        /// beside (F.map.json; the bag's records as F.meta.json) for `scancorr import`.
        #[arg(long)]
        raw: bool,
    },
    /// A recorded table (CSV or whitespace columns: a controller's trace, a data logger, CMM
    /// software) into a bag of the raw streams, through a column mapping.
    Import(commands::import::ImportArgs),
    /// The model lab: compare, diagnose, add, fit, history.
    #[command(subcommand)]
    Lab(commands::lab::LabCmd),
    /// Measuring procedures: measured parameters, with uncertainties, into a new version.
    #[command(subcommand)]
    Calibrate(commands::calibrate::CalibrateCmd),
    /// A machine's status in scancorrd (samples, points, drops, alarms, version, stalls).
    Status {
        /// Machine (without: the machines the services on the bus serve).
        #[arg(long)]
        machine: Option<String>,
        /// Print JSON (the service's reply) instead of text.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        bus: bus::Bus,
    },
    /// Every scancorrd on the bus: version, uptime, machines served, readiness (non-zero
    /// exit when none answers).
    Health {
        /// Print JSON (one object per service) instead of text.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        bus: bus::Bus,
    },
    /// Publish a bag's raw streams on the bus, paced by sample time.
    Replay {
        /// The bag.
        #[arg(long)]
        bag: PathBuf,
        /// Playback speed: 1.0 real time, 2.0 twice as fast, `max` as fast as possible (sim's
        /// `--rate` is a sample rate; this is not).
        #[arg(long, default_value = "1.0")]
        speed: String,
        /// Start again at the end.
        #[arg(long = "loop")]
        looping: bool,
        /// Print a JSON summary on stdout.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        bus: bus::Bus,
    },
    /// Record key expressions from the bus into a bag.
    Record {
        /// Key expressions, e.g. 'cmm/m1/**'.
        #[arg(long)]
        keys: String,
        /// Output bag.
        #[arg(long)]
        out: PathBuf,
        /// Stop after this many seconds.
        #[arg(long)]
        seconds: Option<f64>,
        /// Stop after this many seconds without a message (once something arrived).
        #[arg(long)]
        idle: Option<f64>,
        /// Stop after this many messages.
        #[arg(long)]
        count: Option<u64>,
        /// Print a JSON summary on stdout.
        #[arg(long)]
        json: bool,
        /// Leave out the Foxglove channels `correct` also writes (corrected points and alarms
        /// recorded, as `<prefix>/<machine>/foxglove/…`).
        #[arg(long)]
        no_foxglove: bool,
        /// A bag whose program (`scancorr.program` record) gives the nominal features: the
        /// Foxglove scene and each point's deviation (the record is copied into the bag).
        #[arg(long, value_name = "BAG")]
        nominal: Option<PathBuf>,
        #[command(flatten)]
        bus: bus::Bus,
    },
    /// Show a machine's corrected points and alarms as they arrive.
    Tail {
        /// Machine.
        #[arg(long, default_value = "m1")]
        machine: String,
        /// Stop after this many seconds.
        #[arg(long)]
        seconds: Option<f64>,
        /// Stop after this many messages (point batches and alarms).
        #[arg(long)]
        count: Option<u64>,
        /// One JSON object per point and alarm (JSON lines) instead of text.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        bus: bus::Bus,
    },
    /// Serve the bus's corrected points and alarms to Foxglove (WebSocket on localhost).
    View(commands::view::Args),
    /// Simulate a CMM scanning a program; write a bag, the ground truth and a calibration.
    Sim(SimCli),
    /// Correct a bag offline through the core; write points and alarms to a bag.
    Correct {
        /// Input bag (MCAP).
        #[arg(long)]
        bag: PathBuf,
        /// Calibration document (JSON).
        #[arg(long)]
        calib: PathBuf,
        /// Output bag for corrected points and alarms.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Print the summary as JSON (`samples`, `points`, `dropped`, `alarms`).
        #[arg(long)]
        json: bool,
        /// Leave out the Foxglove channels (`<prefix>/<machine>/foxglove/…`: points coloured
        /// by deviation, the nominal features, alarms, the machine frame).
        #[arg(long)]
        no_foxglove: bool,
    },
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    shared::output::set_force(cli.force);
    match run(cli) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        // The reader of stdout went away (`scancorr … | head`): stop quietly, as a command
        // whose output is no longer wanted. Every file was committed before printing.
        Err(e) if e.is::<shared::output::StdoutClosed>() => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// Dispatches a command to its module under `commands`.
fn run(cli: Cli) -> Result<()> {
    match cli.cmd {
        Cmd::Demo { with, dir, json } => commands::demo::exec(&with, dir, json),
        Cmd::Bench(c) => commands::bench::exec(c),
        Cmd::Calib(c) => commands::calib::exec(c),
        Cmd::Proto { out } => commands::proto::exec(out),
        Cmd::Shape(c) => commands::shape::exec(c),
        Cmd::Export {
            bag,
            format,
            segment,
            machine,
            out,
            raw,
        } => commands::export::exec(bag, format, segment, machine, out, raw),
        Cmd::Import(a) => commands::import::run(a),
        Cmd::Lab(c) => commands::lab::exec(c),
        Cmd::Calibrate(c) => commands::calibrate::exec(c),
        Cmd::Status { machine, json, bus } => commands::bus::status(machine, json, bus),
        Cmd::Health { json, bus } => commands::bus::health(json, bus),
        Cmd::Replay {
            bag,
            speed,
            looping,
            json,
            bus,
        } => commands::bus::replay(bag, speed, looping, json, bus),
        Cmd::Record {
            keys,
            out,
            seconds,
            idle,
            count,
            json,
            no_foxglove,
            nominal,
            bus,
        } => commands::bus::record(
            keys,
            out,
            seconds,
            idle,
            count,
            json,
            (no_foxglove, nominal),
            bus,
        ),
        Cmd::Tail {
            machine,
            seconds,
            count,
            json,
            bus,
        } => commands::bus::tail(machine, seconds, count, json, bus),
        Cmd::View(a) => commands::view::exec(a),
        Cmd::Sim(a) => commands::sim::exec(a),
        Cmd::Correct {
            bag,
            calib,
            out,
            json,
            no_foxglove,
        } => commands::correct::exec(bag, calib, out, json, no_foxglove),
    }
}
