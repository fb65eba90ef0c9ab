//! `scancorr sim`: simulate a CMM scanning a program (the simulation itself is
//! `shared::simulate`), or a straightness error-separation measurement (`separation`).

pub mod separation;

use crate::shared::{bus, output, simulate};
use anyhow::{Context, Result};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct SimCli {
    /// Scan program: ring, ring-speeds, campaign, part, dynamics, tips, probe-force,
    /// probe-force-quarter, probe-force-approach, probe-force-sine, geometry, straightedge; or a straightness
    /// error-separation measurement: straightness-three-probe, straightness-two-probe,
    /// straightness-shear-stage, straightness-shear-unequal.
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
    /// Switch on physics outside the library: cyclic_error, backlash, latching, probe_lobing, rigid_body, squareness, deflection_quadratic (P quadratic in X), force_probe (a force probe: preloaded springs, the stylus bending with the force, the force on the wire) (repeatable).
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

/// Runs `scancorr sim`.
pub fn exec(a: SimCli) -> Result<()> {
    if separation::is_separation(&a.program) {
        exec_separation(a)
    } else {
        exec_scan(a)
    }
}

/// A straightness error-separation measurement.
fn exec_separation(a: SimCli) -> Result<()> {
    separation::refuse(
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
        let (k, v) = simulate::parse_effect(e)?;
        anyhow::ensure!(
            k == "guide_straightness",
            "--effect {e}: a separation measurement sees only the guide \
                     (--effect guide_straightness=F)"
        );
        guide = v;
    }
    let out = a.out.ok_or_else(|| anyhow::anyhow!("give --out FILE"))?;
    separation::run(separation::SepArgs {
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

/// A scan program: the bag, the truth and the calibration; with `--live`, on the bus too.
fn exec_scan(a: SimCli) -> Result<()> {
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
        let (k, v) = simulate::parse_effect(e)?;
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
            .map(simulate::parse_position)
            .transpose()?,
        machine_id: a.machine,
        machine_seed: a.machine_seed,
        seed: a.seed,
        rate_hz: a.rate,
        effects,
        hide: a.hide,
        fault: a.fault.as_deref().map(simulate::parse_fault).transpose()?,
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
    let written = simulate::simulate(
        simulate::SimArgs {
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
