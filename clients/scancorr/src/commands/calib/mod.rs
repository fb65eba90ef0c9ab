//! `scancorr calib …`: calibration documents — checked and printed here, put to, fetched
//! from, rolled back in and listed by scancorrd over the bus, and the nominal one written from
//! a data sheet (`nominal`).

pub mod nominal;

use crate::shared::{bus, human, output, synth};
use anyhow::{Context, Result};
use clap::Subcommand;
use scancorr_core::Calibration;
use std::path::PathBuf;

#[derive(Subcommand)]
pub enum CalibCmd {
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
    Nominal(nominal::NominalArgs),
    /// Print an example document for a machine: the nominal model without effects, or with
    /// `--all-effects` every effect of the library with small non-zero example parameters.
    Example {
        /// Machine id.
        #[arg(long, default_value = "m1")]
        machine: String,
        /// Include every effect of the library, with the benchmark's small example parameters
        /// (non-zero: each effect corrects something).
        #[arg(long)]
        all_effects: bool,
    },
}

/// Runs a `calib` command.
pub fn exec(cmd: CalibCmd) -> Result<()> {
    match cmd {
        CalibCmd::Check { file, machine } => {
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
        CalibCmd::Nominal(a) => nominal::run(a),
        CalibCmd::Put {
            machine,
            file,
            json,
            bus,
        } => {
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
        CalibCmd::Get {
            machine,
            version,
            file,
            json: _,
            bus,
        } => {
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
        CalibCmd::Rollback {
            machine,
            to,
            json,
            bus,
        } => {
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
        CalibCmd::History { machine, json, bus } => {
            output::check_machine("--machine", &machine)?;
            let key = scancorr_proto::calibration_key(&bus.prefix, &machine);
            let reply = bus::query(&bus, format!("{key}?history"))?;
            match serde_json::from_str::<serde_json::Value>(&reply) {
                Ok(v) if !json => outln!("{}", human::history(&v).trim_end())?,
                _ => outln!("{reply}")?,
            }
            Ok(())
        }
        CalibCmd::Example {
            machine,
            all_effects,
        } => {
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
