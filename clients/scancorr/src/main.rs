//! `scancorr` — the command-line tool: demo, benchmarks, calibration documents (and, as the
//! project grows, the simulator, bag correction, the model lab and the bus tools).
//!
//! Thin by design: every command parses arguments, calls the libraries and prints. Errors are
//! reported once, here, with their context chain.

#[macro_use]
mod output;
mod bench;
mod benchfleet;
mod benchlab;
mod benchlive;
mod benchproc;
mod bus;
mod calibcmd;
mod calibsep;
mod demo;
mod export;
mod human;
mod importcmd;
mod labcmd;
mod nominalcmd;
mod offline;
mod plancmd;
mod platecmd;
mod platefile;
mod plotdata;
mod provenance;
mod report;
mod shapecmd;
mod simcmd;
mod simsep;
mod synth;
mod thermalcmd;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use scancorr_core::Calibration;
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
    Import(importcmd::ImportArgs),
    /// The model lab: compare, diagnose, add, fit, history.
    #[command(subcommand)]
    Lab(labcmd::LabCmd),
    /// Measuring procedures: measured parameters, with uncertainties, into a new version.
    #[command(subcommand)]
    Calibrate(calibcmd::CalibrateCmd),
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
    },
}

#[derive(clap::Args)]
struct SimCli {
    /// Scan program: ring, ring-speeds, campaign, part, dynamics, tips, probe-force,
    /// probe-force-quarter, probe-force-approach, probe-force-sine, geometry, straightedge; or a straightness
    /// error-separation measurement: straightness-three-probe, straightness-two-probe,
    /// straightness-shear-stage.
    #[arg(long, default_value = "ring")]
    program: String,
    /// Seed of the run (noise, temperatures).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Seed of the machine (its true parameters).
    #[arg(long, default_value_t = 1)]
    machine_seed: u64,
    /// Machine id in the streams.
    #[arg(long, default_value = "m1")]
    machine: String,
    /// Output bag (with --live: optional, a temporary bag is used).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Ground truth (JSON): every true parameter, the true surfaces, the true calibration.
    #[arg(long)]
    truth: Option<PathBuf>,
    /// Starting calibration (JSON): the true model without the hidden effects.
    #[arg(long)]
    calib_out: Option<PathBuf>,
    /// The machine's data sheet (JSON), what a buyer gets: per axis the time constant as its
    /// maker states it (30 % off the machine's), the travel; the streaming period, the
    /// machine id. For `scancorr calib nominal --datasheet`.
    #[arg(long)]
    datasheet_out: Option<PathBuf>,
    /// The probe and stylus catalogue (JSON): the probe's response, per tip the stylus as
    /// listed (not as built) with its material's expansion coefficient. For `scancorr calib
    /// nominal --catalogue`.
    #[arg(long)]
    catalogue_out: Option<PathBuf>,
    /// Place the program's artifact at x,y,z (mm).
    #[arg(long, allow_hyphen_values = true)]
    position: Option<String>,
    /// Keep EFFECT in the machine but leave it out of the starting calibration (repeatable).
    #[arg(long)]
    hide: Vec<String>,
    /// Scale an effect: EFFECT=FACTOR (0 switches it off; repeatable).
    #[arg(long)]
    effect: Vec<String>,
    /// Switch on physics outside the library: cyclic_error, backlash, latching, probe_lobing, rigid_body, squareness (repeatable).
    #[arg(long = "with")]
    with: Vec<String>,
    /// Inject a fault: servo-drift, collision, stall.
    #[arg(long)]
    fault: Option<String>,
    /// Fault onset, s (default: mid-way through the first fast scan).
    #[arg(long)]
    fault_at: Option<f64>,
    /// Repeat the program until this many minutes have passed.
    #[arg(long)]
    minutes: Option<f64>,
    /// Stream circles as points: command samples without arc centre and radius (the
    /// machine moves the same; the corrector takes arcs from the estimated path).
    #[arg(long)]
    no_arcs: bool,
    /// Command, scale and probe rate, Hz.
    #[arg(long, default_value_t = 1000.0)]
    rate: f64,
    /// Samples per message.
    #[arg(long, default_value_t = 100)]
    batch: usize,
    /// Print a JSON summary.
    #[arg(long)]
    json: bool,
    /// Publish on the bus as a machine controller would (paced by sample time), instead of
    /// only writing the bag (`--out` then keeps a copy).
    #[arg(long)]
    live: bool,
    /// With --live: speed (1.0 real time, `max` as fast as possible).
    #[arg(long, default_value = "1.0")]
    live_rate: String,
    /// With straightness-three-probe: the reversal measurement (the straightedge turned over
    /// about its length; same stations, probes and offsets).
    #[arg(long)]
    reversal: bool,
    /// With straightness-…: lines stepped across the face (25 mm apart along z), for its
    /// flatness.
    #[arg(long, default_value_t = 1)]
    lines: usize,
    #[command(flatten)]
    bus: bus::Bus,
}

#[derive(Subcommand)]
enum ShapeCmd {
    /// Orthogonal-distance least-squares fit of points (ASCII x y z rows; a first line with
    /// only the point count is accepted).
    Fit {
        /// circle, sphere, line or plane.
        #[arg(long)]
        kind: String,
        /// The points file (`x y z` or `x y` rows), or `-` for standard input.
        #[arg(long)]
        points: PathBuf,
        /// Print JSON (`center`, `normal`, `diameter`, `rms`).
        #[arg(long)]
        json: bool,
    },
}

#[derive(Subcommand)]
enum BenchCmd {
    /// Honesty of the calibration procedures' uncertainties: each procedure on `--runs`
    /// simulated measurements of one machine from the nominal model; the share of parameters
    /// within 2σ and within max(3σ, 5 %) of the simulator's truth.
    Procedures {
        /// Procedures (tips, probe-force, dynamics, straightness: three probes with a
        /// reversal and the shear stage, every station against the truth; dynamic-map: every
        /// bin of its maps against the runs' scatter).
        #[arg(long, default_values_t = ["tips".to_string(), "probe-force".to_string(), "dynamics".to_string()])]
        procedure: Vec<String>,
        /// Runs (run seeds 1…N).
        #[arg(long, default_value_t = 20)]
        runs: u64,
        /// The simulated machine.
        #[arg(long, default_value_t = 41)]
        machine_seed: u64,
        /// Print JSON per procedure (`within_2sigma`, `within_3sigma_or_5pct`, `worst`, …).
        #[arg(long)]
        json: bool,
    },
    /// Honesty of the lab's uncertainties: on `--machines` simulated machines (seeds no test
    /// uses), the lab's fitted parameters (`lab fit` of the true effect list from zero, `lab
    /// add` of the ranked-first move with one effect hidden, `lab discover` from nominal)
    /// against the simulator's truth: the share within 2σ and within max(3σ, 5 %).
    LabCoverage {
        /// Machines (seeds --first-seed …).
        #[arg(long, default_value_t = 10)]
        machines: u64,
        /// The first machine seed.
        #[arg(long, default_value_t = 101)]
        first_seed: u64,
        /// Paths: fit, add, discover (comma-separated; discover takes about a minute per machine).
        #[arg(long, default_values_t = ["discover".to_string(), "add".to_string(), "fit".to_string()], value_delimiter = ',')]
        paths: Vec<String>,
        /// Print JSON per path (`within_2sigma`, `within_3sigma_or_5pct`, `worst`, …).
        #[arg(long)]
        json: bool,
    },
    /// `lab discover` on the default campaign from the nominal model: time, steps, final
    /// error, peak memory.
    Discover {
        /// Print JSON (`seconds`, `steps`, `final`, `peak_rss_kb`).
        #[arg(long)]
        json: bool,
        /// Most moves of the loop (the default runs it to the end; fewer times its first steps).
        #[arg(long, default_value_t = 20, value_parser = clap::value_parser!(u16).range(1..))]
        max_steps: u16,
    },
    /// Throughput of the pure core (one thread): every effect and the campaign's, or a calibration
    /// of yours; with `--per-effect`, what each effect costs.
    Core {
        /// Print JSON (`samples_per_s`, …).
        #[arg(long)]
        json: bool,
        /// Scale samples per repetition.
        #[arg(long, default_value_t = 300_000)]
        points: usize,
        /// Repetitions (the best and the median are reported); with `--per-effect`, also its
        /// rounds.
        #[arg(long, default_value_t = 5)]
        repeat: usize,
        /// Time this calibration (JSON) instead of the every-effect and the campaign ones, on
        /// a ring at the centre of its travel, with its first tip and its sensors.
        #[arg(long)]
        calib: Option<PathBuf>,
        /// Also what each effect costs: ns per point with every effect less without it,
        /// timed in rounds (median and range), and what the effects share.
        #[arg(long)]
        per_effect: bool,
    },
    /// One scancorrd process serving many machines at 1 kHz each in real time: delivered
    /// points, seq gaps, latency, memory and CPU per machine.
    Fleet {
        /// Print JSON (`points_per_s`, `kept_up`, `rss_per_machine_bytes`, `core_state_bytes_max`, …).
        #[arg(long)]
        json: bool,
        /// Machines (with `--largest`: the largest fleet probed).
        #[arg(long, default_value_t = 1000)]
        machines: usize,
        /// Seconds of scanning per machine (1 kHz).
        #[arg(long, default_value_t = 10.0)]
        seconds: f64,
        /// Controller batch period, ms (one message per stream per period).
        #[arg(long, default_value_t = 100)]
        batch_ms: u64,
        /// The service's `max_pending_samples` (per stream per machine).
        #[arg(long, default_value_t = 256)]
        max_pending: usize,
        /// Wall-clock pace, fraction of real time (below 1 when this machine cannot generate
        /// the whole fleet's load besides serving it).
        #[arg(long, default_value_t = 1.0)]
        pace: f64,
        /// Through a `scancorr-router` (scancorrd, controllers and consumer its clients), as
        /// a shop floor deploys it.
        #[arg(long)]
        router: bool,
        /// The service's correcting worker shards (0: one per core).
        #[arg(long, default_value_t = 0)]
        workers: usize,
        /// Controller links: the machines are spread over this many zenoh sessions (each its
        /// own connection to the service and its own thread, paced on its own), as controllers
        /// on a shop floor each have their own (one link could not publish 1 000 machines'
        /// batches within a period here; at most one per machine).
        #[arg(long, default_value_t = 4)]
        links: usize,
        /// Search for the largest fleet that keeps real time with these `--workers`, by
        /// bisection over `--from` … `--machines` in steps of `--step`, each size run up to
        /// `--runs` times (it keeps up when every run did). Takes minutes: each run is one
        /// fleet measurement.
        #[arg(long)]
        largest: bool,
        /// With `--largest`: the smallest fleet probed.
        #[arg(long, default_value_t = 100, requires = "largest")]
        from: usize,
        /// With `--largest`: the step between the fleet sizes probed, machines.
        #[arg(long, default_value_t = 50, requires = "largest")]
        step: usize,
        /// With `--largest`: runs per fleet size.
        #[arg(long, default_value_t = 2, requires = "largest")]
        runs: usize,
    },
    /// The bare relay `bench live` compares against (run by it as a child process).
    #[command(hide = true)]
    Relay {
        /// Port to listen on (127.0.0.1).
        #[arg(long)]
        port: u16,
        /// Key prefix: `<prefix>/*/raw/*` is relayed to `<key>/out`.
        #[arg(long, default_value = "bench")]
        prefix: String,
    },
    /// A bare zenoh relay against scancorrd on loopback: throughput, ratio, latency.
    Live {
        /// Print JSON (`relay_samples_per_s`, `service_samples_per_s`, `ratio`, `service_added_latency_us`, … each as min/median/max over the rounds).
        #[arg(long)]
        json: bool,
        /// Scale instants to send per round (×3 streams plus temperatures).
        #[arg(long, default_value_t = 30_000)]
        points: usize,
        /// Alternating rounds of each measurement (throughput, latency).
        #[arg(long, default_value_t = 5)]
        rounds: usize,
    },
    /// `scancorr correct` end to end on a simulated campaign bag: read, decode, correct,
    /// encode, write.
    Correct {
        /// Print JSON (`samples_per_s`, …).
        #[arg(long)]
        json: bool,
        /// Repetitions (the best and the median are reported).
        #[arg(long, default_value_t = 3)]
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
    /// Send a calibration to scancorrd: validated, stored as a new version, made current.
    Put {
        /// Machine.
        #[arg(long)]
        machine: String,
        /// The JSON document.
        #[arg(long)]
        file: PathBuf,
        /// Print JSON (the service's reply) instead of text.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        bus: bus::Bus,
    },
    /// Fetch the current (or a given) calibration version from scancorrd.
    Get {
        /// Machine.
        #[arg(long)]
        machine: String,
        /// A given version.
        #[arg(long)]
        version: Option<u64>,
        /// Write it here instead of printing.
        #[arg(long)]
        file: Option<PathBuf>,
        /// Accepted for uniformity: the document is JSON either way.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        bus: bus::Bus,
    },
    /// Make an earlier version current again, as a new version (its parent the current one;
    /// the audit trail records who asked and when).
    Rollback {
        /// Machine.
        #[arg(long)]
        machine: String,
        /// The version to make current again.
        #[arg(long)]
        to: u64,
        /// Print JSON (the service's reply) instead of text.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        bus: bus::Bus,
    },
    /// The versions scancorrd keeps for a machine.
    History {
        /// Machine.
        #[arg(long)]
        machine: String,
        /// Print JSON (the service's reply) instead of text.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        bus: bus::Bus,
    },
    /// Write a machine's nominal calibration (version 1, no effects) from its data sheet
    /// (time constants, travel) and the probe and stylus catalogue — the start of the
    /// procedures and the lab (`scancorr sim --datasheet-out --catalogue-out` writes both for a
    /// simulated machine).
    Nominal(nominalcmd::NominalArgs),
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
        // The reader of stdout went away (`scancorr … | head`): stop quietly, as a command
        // whose output is no longer wanted. Every file was committed before printing.
        Err(e) if e.is::<output::StdoutClosed>() => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<()> {
    match cli.cmd {
        Cmd::Demo { with, dir, json } => demo::run(&with, dir, json),
        Cmd::Bench(BenchCmd::Core {
            json,
            points,
            repeat,
            calib,
            per_effect,
        }) => bench::core(&bench::CoreOptions {
            points,
            repeat,
            calib,
            per_effect,
            json,
        }),
        Cmd::Bench(BenchCmd::Correct { json, repeat }) => bench::correct(repeat, json),
        Cmd::Bench(BenchCmd::Discover { json, max_steps }) => demo::bench(json, max_steps.into()),
        Cmd::Bench(BenchCmd::LabCoverage {
            machines,
            first_seed,
            paths,
            json,
        }) => benchlab::run(&benchlab::Options {
            machines,
            first_seed,
            paths: benchlab::paths(&paths),
            json,
        }),
        Cmd::Bench(BenchCmd::Procedures {
            procedure,
            runs,
            machine_seed,
            json,
        }) => benchproc::run(&procedure, machine_seed, runs, json),
        Cmd::Bench(BenchCmd::Live {
            json,
            points,
            rounds,
        }) => benchlive::run(points, rounds, json),
        Cmd::Bench(BenchCmd::Relay { port, prefix }) => {
            output::check_prefix(&prefix)?;
            benchlive::relay(port, &prefix)
        }
        Cmd::Bench(BenchCmd::Fleet {
            json,
            machines,
            seconds,
            batch_ms,
            max_pending,
            pace,
            router,
            workers,
            links,
            largest,
            from,
            step,
            runs,
        }) => {
            let p = benchfleet::Params {
                machines,
                seconds,
                batch_ms,
                max_pending,
                pace,
                router,
                workers,
                links,
                json,
            };
            if largest {
                let search = benchfleet::Search {
                    from,
                    to: machines,
                    step,
                    runs,
                };
                benchfleet::largest(p, search)
            } else {
                benchfleet::run(p)
            }
        }
        Cmd::Calib(CalibCmd::Check { file, machine }) => {
            if let Some(m) = &machine {
                output::check_machine("--machine", m)?;
            }
            let text = std::fs::read_to_string(&file)
                .with_context(|| format!("reading {}", file.display()))?;
            let cal =
                Calibration::from_json(&text).with_context(|| format!("{}", file.display()))?;
            cal.build().with_context(|| format!("{}", file.display()))?;
            if let Some(m) = machine {
                cal.check_machine(&m)?;
            }
            outln!(
                "{}: valid — machine {}, version {}, {} effect(s)",
                file.display(),
                cal.machine_id,
                cal.version,
                cal.effects.len()
            )?;
            Ok(())
        }
        Cmd::Calib(CalibCmd::Nominal(a)) => nominalcmd::run(a),
        Cmd::Lab(c) => labcmd::run(c),
        Cmd::Calibrate(c) => calibcmd::run(c),
        Cmd::Proto { out } => {
            output::write_file("--out", &out, scancorr_proto::FILE_DESCRIPTOR_SET)?;
            eprintln!(
                "{}: FileDescriptorSet of package {} ({} bytes)",
                out.display(),
                scancorr_proto::PACKAGE,
                scancorr_proto::FILE_DESCRIPTOR_SET.len()
            );
            Ok(())
        }
        Cmd::Calib(CalibCmd::Put {
            machine,
            file,
            json,
            bus,
        }) => {
            let reply = bus::calib_put(&bus, &machine, &file)?;
            if json {
                outln!("{reply}")?;
            } else {
                match serde_json::from_str::<serde_json::Value>(&reply) {
                    Ok(v) => outln!(
                        "{machine}: stored and made current\n{}",
                        human::object(&v, 2).trim_end()
                    )?,
                    Err(_) => outln!("{reply}")?,
                }
            }
            Ok(())
        }
        Cmd::Calib(CalibCmd::Get {
            machine,
            version,
            file,
            json: _,
            bus,
        }) => {
            output::check_machine("--machine", &machine)?;
            bus.check()?;
            let key = scancorr_proto::calibration_key(&bus.prefix, &machine);
            let sel = match version {
                Some(v) => format!("{key}?version={v}"),
                None => key,
            };
            // The file is prepared (its folder checked) before asking.
            let out = file
                .as_deref()
                .map(|f| output::AtomicOutput::new("--file", f))
                .transpose()?;
            let doc = bus::query(&bus, sel)?;
            match out {
                Some(o) => {
                    o.write_all(doc)?;
                    o.commit()?;
                }
                None => outln!("{doc}")?,
            }
            Ok(())
        }
        Cmd::Calib(CalibCmd::Rollback {
            machine,
            to,
            json,
            bus,
        }) => {
            output::check_machine("--machine", &machine)?;
            bus.check()?;
            let key = scancorr_proto::calibration_write_key(&bus.prefix, &machine);
            let reply = bus::ask_as_user(&bus, format!("{key}?rollback={to}"), None)?;
            if json {
                outln!("{reply}")?;
            } else {
                match serde_json::from_str::<serde_json::Value>(&reply) {
                    Ok(v) => outln!(
                        "{machine}: version {to} made current again\n{}",
                        human::object(&v, 2).trim_end()
                    )?,
                    Err(_) => outln!("{reply}")?,
                }
            }
            Ok(())
        }
        Cmd::Calib(CalibCmd::History { machine, json, bus }) => {
            output::check_machine("--machine", &machine)?;
            let key = scancorr_proto::calibration_key(&bus.prefix, &machine);
            let reply = bus::query(&bus, format!("{key}?history"))?;
            match serde_json::from_str::<serde_json::Value>(&reply) {
                Ok(v) if !json => outln!("{}", human::history(&v).trim_end())?,
                _ => outln!("{reply}")?,
            }
            Ok(())
        }
        Cmd::Health { json, bus } => {
            let all = bus::health(&bus)?;
            if json {
                outln!("{}", serde_json::Value::Array(all))?;
            } else {
                for h in &all {
                    outln!(
                        "scancorrd {} (zid {}): ready, up {} s, {} machine(s){}{}",
                        h["version"].as_str().unwrap_or("?"),
                        h["zid"].as_str().unwrap_or("?"),
                        h["uptime_s"],
                        h["machines"],
                        match h["quarantined"].as_array() {
                            Some(q) if !q.is_empty() => format!(
                                ", quarantined: {}",
                                q.iter()
                                    .filter_map(|v| v.as_str())
                                    .collect::<Vec<_>>()
                                    .join(", ")
                            ),
                            _ => String::new(),
                        },
                        human::router_link(&h["router_link"])
                    )?;
                }
            }
            Ok(())
        }
        Cmd::Status {
            machine: None,
            json,
            bus,
        } => {
            let list = bus::machines(&bus)?;
            if json {
                outln!("{}", serde_json::json!({ "machines": list }))?;
            } else {
                outln!("served: {} machine(s): {}", list.len(), list.join(", "))?;
            }
            Ok(())
        }
        Cmd::Status {
            machine: Some(machine),
            json,
            bus,
        } => {
            let reply = bus::status(&bus, &machine)?;
            match serde_json::from_str::<serde_json::Value>(&reply) {
                Ok(v) if !json => outln!("{}", human::object(&v, 0).trim_end())?,
                _ => outln!("{reply}")?,
            }
            Ok(())
        }
        Cmd::Replay {
            bag,
            speed,
            looping,
            json,
            bus,
        } => {
            let r = if speed == "max" {
                None
            } else {
                let v: f64 = speed
                    .parse()
                    .with_context(|| format!("--speed {speed}: a number (1.0 real time) or max"))?;
                anyhow::ensure!(v.is_finite() && v > 0.0, "--speed must be > 0");
                Some(v)
            };
            let r = bus::replay(&bus, &bag, r, looping)?;
            if json {
                outln!(
                    "{}",
                    serde_json::json!({"replayed_messages": r.sent, "not_delivered": r.not_delivered, "shed": r.shed, "bag": bag.display().to_string()})
                )?;
            } else {
                eprintln!(
                    "replayed {} message(s) from {}{}",
                    r.sent,
                    bag.display(),
                    r.said()
                );
            }
            Ok(())
        }
        Cmd::Record {
            keys,
            out,
            seconds,
            idle,
            count,
            json,
            bus,
        } => {
            let bound = bus::Bound {
                seconds,
                idle,
                count,
            };
            let n = bus::record(&bus, &keys, &out, bound)?;
            if json {
                outln!(
                    "{}",
                    serde_json::json!({"recorded_messages": n, "out": out.display().to_string()})
                )?;
            } else {
                eprintln!("recorded {n} message(s) → {}", out.display());
            }
            Ok(())
        }
        Cmd::Tail {
            machine,
            seconds,
            count,
            json,
            bus,
        } => bus::tail(
            &bus,
            &machine,
            bus::Bound {
                seconds,
                idle: None,
                count,
            },
            json,
        ),
        Cmd::Shape(ShapeCmd::Fit { kind, points, json }) => shapecmd::run(&kind, &points, json),
        Cmd::Export {
            bag,
            format,
            segment,
            machine,
            out,
            raw,
        } => {
            if let Some(m) = &machine {
                output::check_machine("--machine", m)?;
            }
            if raw {
                anyhow::ensure!(
                    segment.is_none() && format == "csv",
                    "--raw exports every raw stream as CSV: without --segment or --format"
                );
                return export::run_raw(&bag, machine.as_deref(), &out);
            }
            export::run(&bag, &format, segment, machine.as_deref(), &out)
        }
        Cmd::Import(a) => importcmd::run(a),
        Cmd::Sim(a) if simsep::is_separation(&a.program) => {
            simsep::refuse(
                &[
                    ("--hide", !a.hide.is_empty()),
                    ("--with", !a.with.is_empty()),
                    ("--fault", a.fault.is_some()),
                    ("--fault-at", a.fault_at.is_some()),
                    ("--minutes", a.minutes.is_some()),
                    ("--no-arcs", a.no_arcs),
                    ("--position", a.position.is_some()),
                    ("--calib-out", a.calib_out.is_some()),
                    ("--live", a.live),
                ],
                &a.program,
            )?;
            let mut guide = 1.0;
            for e in &a.effect {
                let (k, v) = simcmd::parse_effect(e)?;
                anyhow::ensure!(
                    k == "guide_straightness",
                    "--effect {e}: a separation measurement sees only the guide \
                     (--effect guide_straightness=F)"
                );
                guide = v;
            }
            let out = a.out.ok_or_else(|| anyhow::anyhow!("give --out FILE"))?;
            simsep::run(simsep::SepArgs {
                options: scancorr_sim::straightness::SeparationOptions {
                    program: a.program,
                    machine_seed: a.machine_seed,
                    seed: a.seed,
                    rate_hz: a.rate,
                    guide_factor: guide,
                    reversal: a.reversal,
                    lines: a.lines,
                },
                machine: a.machine,
                out,
                truth: a.truth,
                datasheet_out: a.datasheet_out,
                catalogue_out: a.catalogue_out,
                batch: a.batch,
                prefix: a.bus.prefix,
                json: a.json,
            })
        }
        Cmd::Sim(a) => {
            anyhow::ensure!(
                !a.reversal,
                "--reversal: only for straightness-three-probe (the straightedge turned over)"
            );
            anyhow::ensure!(
                a.lines == 1,
                "--lines: only for the straightness-… measurements (a surface in lines)"
            );
            output::check_machine("--machine", &a.machine)?;
            output::check_prefix(&a.bus.prefix)?;
            let mut effects = std::collections::BTreeMap::new();
            for e in &a.effect {
                let (k, v) = simcmd::parse_effect(e)?;
                effects.insert(k, v);
            }
            for e in &a.with {
                effects.insert(e.clone(), 1.0);
            }
            let options = scancorr_sim::Options {
                program: a.program,
                position: a
                    .position
                    .as_deref()
                    .map(simcmd::parse_position)
                    .transpose()?,
                machine_id: a.machine,
                machine_seed: a.machine_seed,
                seed: a.seed,
                rate_hz: a.rate,
                effects,
                hide: a.hide,
                fault: a.fault.as_deref().map(simcmd::parse_fault).transpose()?,
                fault_at_s: a.fault_at,
                minutes: a.minutes,
                no_arcs: a.no_arcs,
                ..Default::default()
            };
            let live = a.live;
            let rate = if !live || a.live_rate == "max" {
                None
            } else {
                let v: f64 = a
                    .live_rate
                    .parse()
                    .with_context(|| format!("--live-rate {}: a number or max", a.live_rate))?;
                anyhow::ensure!(v.is_finite() && v > 0.0, "--live-rate must be > 0");
                Some(v)
            };
            let keep = a.out.is_some();
            // The bag of a live run without --out: in a folder of our own, removed when done.
            let mut _live_dir = None;
            let out = match (&a.out, live) {
                (Some(p), _) => p.clone(),
                // Removed when done (never committed).
                (None, true) => {
                    let d = output::RemoveDir(output::private_dir("scancorr-live")?);
                    let p = d.0.join("live.mcap");
                    _live_dir = Some(d);
                    p
                }
                (None, false) => anyhow::bail!("give --out FILE (or --live to publish on the bus)"),
            };
            // Live: the bus first, so that a missing service fails before the simulation.
            let conn = if live {
                a.bus.check()?;
                Some(bus::connect(&a.bus)?)
            } else {
                None
            };
            let written = simcmd::simulate(
                simcmd::SimArgs {
                    options,
                    out: out.clone(),
                    truth: a.truth,
                    calib_out: a.calib_out,
                    datasheet_out: a.datasheet_out,
                    catalogue_out: a.catalogue_out,
                    batch: a.batch,
                    prefix: a.bus.prefix.clone(),
                    json: a.json,
                },
                true,
            )?;
            let unkept = written.commit(keep)?;
            if let Some(conn) = conn {
                let bag = unkept.as_ref().map(|o| o.path()).unwrap_or(&out);
                let r = conn.replay(&a.bus, bag, rate, false)?;
                eprintln!("published {} message(s) live{}", r.sent, r.said());
            }
            Ok(())
        }
        Cmd::Correct {
            bag,
            calib,
            out,
            json,
        } => {
            if let Some(o) = &out {
                output::refuse_same_file(&[("--out", o)], &[("--bag", &bag), ("--calib", &calib)])?;
            }
            let cal = offline::load_calibration(&calib)?;
            let (s, warnings) = offline::correct(&bag, &cal, out.as_deref())?;
            for w in warnings {
                eprintln!("warning: {w}");
            }
            for e in &s.inactive_effects {
                eprintln!(
                    "warning: effect `{e}` of the calibration contributed to none of the {} points: inactive for lack of its signal (e.g. no rotation for servo effects, no deflection for probe effects)",
                    s.points
                );
            }
            if json {
                outln!("{}", serde_json::to_string_pretty(&s)?)?;
            } else {
                outln!(
                    "{}: machine {}, calibration v{}: {} samples → {} points ({} flagged), {} alarm(s), dropped {:?}{} in {:.2} s ({:.2e} samples/s)",
                    bag.display(),
                    s.machine,
                    s.calibration_version,
                    s.samples,
                    s.points,
                    s.points_flagged,
                    s.alarms,
                    s.dropped,
                    if s.bad_messages > 0 { format!(", {} malformed message(s)", s.bad_messages) } else { String::new() }
                        + &if s.clock_resets > 0 { format!(", {} controller clock reset(s)", s.clock_resets) } else { String::new() },
                    s.seconds,
                    s.samples_per_s
                )?;
            }
            Ok(())
        }
        Cmd::Calib(CalibCmd::Example {
            machine,
            all_effects,
        }) => {
            output::check_machine("--machine", &machine)?;
            let cal = if all_effects {
                synth::all_effects_calibration(&machine)
            } else {
                Calibration::example(&machine)
            };
            outln!("{}", cal.to_json())?;
            Ok(())
        }
    }
}
