//! `scancorr bench …`: benchmarks that print their figures — one module per benchmark, the
//! processes and figures they share in `harness`.

pub mod discover;
pub mod fleet;
pub mod harness;
pub mod lab_coverage;
pub mod live;
pub mod procedures;
pub mod relay;
pub mod throughput;

use anyhow::Result;
use clap::Subcommand;
use std::path::PathBuf;

#[derive(Subcommand)]
pub enum BenchCmd {
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
        /// Instead of timing: one pass with the points' contexts recorded, and a hash of every
        /// point, alarm, context and count it gave (equal hashes: equal output bit for bit).
        #[arg(long)]
        hash: bool,
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
        /// A bare relay in the service's place (`bench relay --inline`: the same keys, input
        /// messages and output bytes, no correction and no hand-over to shards): the bus's
        /// own cost per point on this machine, the floor under the service's.
        #[arg(long, conflicts_with = "router")]
        relay: bool,
        /// With `--relay`: effects in each relayed point's breakdown (default: as the
        /// service's, every effect's calibration's 8), to see what the breakdown's bytes cost.
        #[arg(long, requires = "relay")]
        relay_effects: Option<usize>,
        /// The service publishes the points without their per-effect breakdown
        /// (`publish_breakdown: false`).
        #[arg(long, conflicts_with = "relay")]
        no_breakdown: bool,
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
        /// Effects in each point's breakdown (default: every effect's calibration's count).
        #[arg(long)]
        effects: Option<usize>,
        /// Handle each message in the subscriber's callback (no worker thread).
        #[arg(long)]
        inline: bool,
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

/// Runs a benchmark.
pub fn exec(cmd: BenchCmd) -> Result<()> {
    // A benchmark has no output file of the user's: it writes only into scratch folders of its
    // own (`private_dir`), where each round replaces the round before's files, in this process
    // and in the `scancorr` processes it starts. Set before any thread is.
    crate::shared::output::set_force(true);
    std::env::set_var("SCANCORR_FORCE", "1");
    match cmd {
        BenchCmd::Core {
            json,
            points,
            repeat,
            calib,
            per_effect,
            hash,
        } => throughput::core(&throughput::CoreOptions {
            points,
            repeat,
            calib,
            per_effect,
            hash,
            json,
        }),
        BenchCmd::Correct { json, repeat } => throughput::correct(repeat, json),
        BenchCmd::Discover { json, max_steps } => discover::exec(json, max_steps.into()),
        BenchCmd::LabCoverage {
            machines,
            first_seed,
            paths,
            json,
        } => lab_coverage::run(&lab_coverage::Options {
            machines,
            first_seed,
            paths: lab_coverage::paths(&paths),
            json,
        }),
        BenchCmd::Procedures {
            procedure,
            runs,
            machine_seed,
            json,
        } => procedures::run(&procedure, machine_seed, runs, json),
        BenchCmd::Live {
            json,
            points,
            rounds,
        } => live::run(points, rounds, json),
        BenchCmd::Relay {
            port,
            prefix,
            effects,
            inline,
        } => {
            crate::shared::output::check_prefix(&prefix)?;
            relay::run(port, &prefix, &relay::Options { effects, inline })
        }
        BenchCmd::Fleet {
            json,
            machines,
            seconds,
            batch_ms,
            max_pending,
            pace,
            router,
            workers,
            links,
            relay,
            relay_effects,
            no_breakdown,
            largest,
            from,
            step,
            runs,
        } => {
            let p = fleet::Params {
                machines,
                seconds,
                batch_ms,
                max_pending,
                pace,
                router,
                workers,
                links,
                relay,
                relay_effects,
                no_breakdown,
                json,
            };
            if largest {
                let search = fleet::Search {
                    from,
                    to: machines,
                    step,
                    runs,
                };
                fleet::largest(p, search)
            } else {
                fleet::run(p)
            }
        }
    }
}
