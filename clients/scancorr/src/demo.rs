//! `scancorr demo`: the main job on embedded defaults — the model lab's loop on a simulated
//! machine with one effect hidden from its calibration.
//!
//! 1. Simulate the calibration campaign on machine m1 with the effect hidden, and a held-out
//!    `ring-speeds` run at a position the campaign did not use.
//! 2. Compare the starting calibration with the artifacts: where it fails.
//! 3. Diagnose: rank the missing effects by the held-out residual they explain.
//! 4. Add the best one, fit it, write calibration version 2.
//! 5. Show the error falling, and correct the held-out bag with each version.

use crate::{labcmd, offline, simcmd};
use anyhow::{Context, Result};
use scancorr_core::lab::analysis;
use scancorr_core::lab::dataset::{self, BuildOptions};
use std::path::{Path, PathBuf};

pub fn run(hide: &str, dir: Option<PathBuf>, json: bool) -> Result<()> {
    let keep = dir.is_some();
    let dir = dir.unwrap_or_else(|| {
        std::env::temp_dir().join(format!("scancorr-demo-{}", std::process::id()))
    });
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let say = |s: String| -> Result<()> {
        if !json {
            outln!("{s}")?;
        }
        Ok(())
    };
    let p = |f: &str| dir.join(f);
    say(format!("scancorr demo — the model lab on a simulated CMM with `{hide}` hidden from its calibration\n"))?;
    say("1. simulating the calibration campaign (rings at 3 positions × 4 speeds × 2 directions, sphere with 2 styli, straightedge, drifting temperature) …".into())?;
    sim(
        "campaign",
        1,
        None,
        hide,
        &p("campaign.mcap"),
        Some(&p("truth.json")),
        Some(&p("v1.json")),
    )?;
    say("   and a held-out ring-speeds run at (550, 300, −250), another seed …".into())?;
    sim(
        "ring-speeds",
        2,
        Some([550.0, 300.0, -250.0]),
        hide,
        &p("heldout.mcap"),
        None,
        None,
    )?;

    let cal1 = offline::load_calibration(&p("v1.json"))?;
    let bags = labcmd::load_bags(
        &[p("campaign.mcap")],
        &[p("heldout.mcap")],
        &cal1.machine_id,
    )?;
    let opts = BuildOptions {
        sensors: ["stylus", "scale_x", "scale_y", "scale_z", "air"]
            .iter()
            .map(|s| s.to_string())
            .collect(),
        ..Default::default()
    };
    let ds1 = dataset::build(&bags, &cal1, &opts)?;
    let cmp = analysis::compare(&ds1)?;
    say(format!(
        "\n2. compare v1 ({} effects) with the artifacts: deviation RMS {:.3} µm, PV {:.3} µm, noise floor {:.3} µm",
        cal1.effects.len(),
        cmp.rms_um,
        cmp.pv_um,
        cmp.noise_floor_um
    ))?;
    for b in cmp.failures.iter().take(4) {
        say(format!(
            "   fails at {:<20} {:<28} RMS {:.3} µm",
            b.feature, b.bin, b.rms_um
        ))?;
    }
    let dg = analysis::diagnose(&ds1)?;
    say("\n3. diagnose: candidates ranked by the held-out residual they explain".into())?;
    for c in dg.candidates.iter().take(5) {
        say(format!(
            "   {:<36} explains {:>5.1} %  held-out {:.3} → {:.3} µm  {}",
            c.effect,
            c.explained * 100.0,
            c.heldout_rms_before_um,
            c.heldout_rms_after_um,
            if c.significant { "significant" } else { "" }
        ))?;
    }
    for c in &dg.confounded {
        say(format!(
            "   confounded: {} / {} — separate them by {}",
            c.effects[0],
            c.effects[1],
            c.separate_by.join("; ")
        ))?;
    }
    for s in &dg.unexplained {
        say(format!(
            "   unexplained structure: {} along {} ({:.3} µm) → custom terms {}",
            s.kind,
            s.axis,
            s.amplitude_um,
            s.custom_terms.join(" ")
        ))?;
    }
    let best = dg
        .candidates
        .iter()
        .find(|c| c.significant)
        .context("no significant candidate: nothing to add")?;
    say(format!(
        "\n4. add {} and fit it (with the artifact placements, held-out data kept apart)",
        best.effect
    ))?;
    let prep = analysis::prepare(&ds1)?;
    let cfg = analysis::candidate(&best.effect, &ds1)?;
    let fit = analysis::fit_effects(&ds1, &prep, &[cfg])?;
    let mut cal2 = cal1.clone();
    cal2.effects
        .push(fit.configs.last().expect("one effect").clone());
    cal2.version = 2;
    cal2.parent_version = Some(1);
    let ds2 = dataset::build(&bags, &cal2, &opts)?;
    let after = analysis::prepare(&ds2)?;
    cal2.note = format!(
        "demo: lab add {}: held-out RMS {:.3} → {:.3} µm",
        best.effect, prep.rms_held_um, after.rms_held_um
    );
    cal2.metrics = [
        ("rms_um".to_string(), after.rms_fit_um),
        ("heldout_rms_um".to_string(), after.rms_held_um),
    ]
    .into();
    crate::output::write_file("v2.json", &p("v2.json"), cal2.to_json())?;
    for prm in fit.params.last().into_iter().flatten().take(6) {
        match prm.sigma {
            Some(s) => say(format!(
                "   {:<44} {:>11.4e} ± {:.1e}",
                prm.name, prm.value, s
            ))?,
            None => say(format!(
                "   {:<44} {:>11.4e} (not determined by this data)",
                prm.name, prm.value
            ))?,
        }
    }
    say("\n5. the error falls (held-out ring-speeds run, deviation RMS):".into())?;
    let max = prep.rms_held_um.max(after.rms_held_um).max(1e-9);
    let bar = |v: f64| "█".repeat(((v / max) * 48.0).round().max(1.0) as usize);
    say(format!(
        "   v1 nominal + {} effects   {:>7.3} µm {}",
        cal1.effects.len(),
        prep.rms_held_um,
        bar(prep.rms_held_um)
    ))?;
    say(format!(
        "   v2 + {:<21} {:>7.3} µm {}",
        best.effect.split(':').next().unwrap_or(""),
        after.rms_held_um,
        bar(after.rms_held_um)
    ))?;
    say(format!(
        "   noise floor               {:>7.3} µm",
        ds1.noise_floor_um
    ))?;
    let (s1, _) = offline::correct(&p("heldout.mcap"), &cal1, None)?;
    let (s2, _) = offline::correct(&p("heldout.mcap"), &cal2, None)?;
    say(format!(
        "   (corrected {} points of the held-out bag with each version; no alarm: {} / {})",
        s2.points, s1.alarms, s2.alarms
    ))?;
    if json {
        outln!(
            "{}",
            serde_json::json!({
                "hidden": hide,
                "best": best.effect,
                "heldout_rms_before_um": prep.rms_held_um,
                "heldout_rms_after_um": after.rms_held_um,
                "noise_floor_um": ds1.noise_floor_um,
                "dir": if keep { Some(dir.display().to_string()) } else { None },
            })
        )?;
    }
    if keep {
        say(format!("\nfiles in {} (bags, truth.json, v1.json, v2.json); try: scancorr lab diagnose --bag {} --calib {} --report report.html", dir.display(), p("campaign.mcap").display(), p("v1.json").display()))?;
    } else {
        std::fs::remove_dir_all(&dir).ok();
    }
    Ok(())
}

fn sim(
    program: &str,
    seed: u64,
    position: Option<[f64; 3]>,
    hide: &str,
    out: &Path,
    truth: Option<&Path>,
    calib: Option<&Path>,
) -> Result<()> {
    let options = scancorr_sim::Options {
        program: program.into(),
        seed,
        position,
        hide: if scancorr_sim::LIBRARY_EFFECTS.contains(&hide) {
            vec![hide.to_string()]
        } else {
            vec![]
        },
        effects: if scancorr_sim::EXTRA_EFFECTS.contains(&hide) {
            [(hide.to_string(), 1.0)].into()
        } else {
            Default::default()
        },
        ..Default::default()
    };
    simcmd::run_quiet(simcmd::SimArgs {
        options,
        out: out.to_path_buf(),
        truth: truth.map(Path::to_path_buf),
        calib_out: calib.map(Path::to_path_buf),
        batch: 100,
        prefix: scancorr_proto::DEFAULT_PREFIX.into(),
        json: false,
    })
}
