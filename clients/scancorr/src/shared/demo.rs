//! The demo's loop, shared by `scancorr demo` and `scancorr bench discover`: the model lab's
//! loop on a simulated machine from the start a user has: its nominal model.
//!
//! 1. Simulate the calibration campaign on machine m1 (every effect of the library active in
//!    the machine) and a held-out `ring-speeds` run at a position the campaign did not use.
//! 2. The starting calibration is the machine's nominal model only: the data sheet's axis time
//!    constants (30 % off), the styli at their qualified lengths (here the
//!    simulator's: `scancorr calibrate tips` measures them on a machine), no effects.
//! 3. Compare it with the artifacts: where it fails.
//! 4. `lab discover`: refit the nominal model, then diagnose, add (swap, drop) the best
//!    candidate and refit everything until nothing significant is left; each step a version.
//! 5. Show the error falling to the noise floor, what the campaign could not separate, and
//!    correct the held-out bag with the first and the last version.

use crate::shared::{bags, calib, simulate};
use anyhow::{Context, Result};
use scancorr_core::lab::analysis;
use scancorr_core::lab::dataset::{self, BuildOptions};
use scancorr_core::lab::discover::{self, Step};
use scancorr_core::transfer::TransferFunction;
use std::path::Path;

/// The demo's loop in `dir` (at most `max_steps` moves): its JSON summary; `keep` keeps its
/// files; `json` prints no steps.
pub fn run_in(
    with: &[String],
    dir: &Path,
    keep: bool,
    json: bool,
    max_steps: usize,
) -> Result<serde_json::Value> {
    let say = |s: String| -> Result<()> {
        if !json {
            outln!("{s}")?;
        }
        Ok(())
    };
    let p = |f: &str| dir.join(f);
    say("scancorr demo — the model lab from a nominal model to the noise floor, on a simulated CMM\n".into())?;
    say("1. simulating the calibration campaign (rings at 3 positions × 4 speeds × 2 directions, sphere with 2 styli, straightedge, drifting temperature) …".into())?;
    sim(
        "campaign",
        1,
        None,
        with,
        &p("campaign.mcap"),
        Some(&p("truth.json")),
        Some(&p("sim-start.json")),
    )?;
    say("   and a held-out ring-speeds run at (550, 300, −250), another seed …".into())?;
    sim(
        "ring-speeds",
        2,
        Some([550.0, 300.0, -250.0]),
        with,
        &p("heldout.mcap"),
        None,
        None,
    )?;

    // The user's start: the nominal model with data-sheet time constants (30 % off).
    let mut start = calib::load_calibration(&p("sim-start.json"))?;
    for tf in [
        &mut start.nominal.axes.x,
        &mut start.nominal.axes.y,
        &mut start.nominal.axes.z,
    ] {
        if let TransferFunction::FirstOrder { tau_s } = tf {
            *tau_s *= 1.3;
        }
    }
    start.note = "nominal model: data-sheet time constants, qualified styli, no effects".into();
    crate::shared::output::write_file("v1.json", &p("v1.json"), start.to_json())?;
    say(format!(
        "\n2. the start: the nominal model only ({} styli, time constants from the data sheet), no effects",
        start.geometry.tips.len()
    ))?;

    let bags = bags::load_bags(
        &[p("campaign.mcap")],
        &[p("heldout.mcap")],
        &start.machine_id,
    )?;
    let build = BuildOptions {
        sensors: ["stylus", "scale_x", "scale_y", "scale_z", "air"]
            .iter()
            .map(|s| s.to_string())
            .collect(),
        ..Default::default()
    };
    let build_opts = build.clone();
    let ds1 = dataset::build(&bags, &start, &build)?;
    let cmp = analysis::compare(&ds1)?;
    say(format!(
        "\n3. compare v1 with the artifacts: deviation RMS {:.3} µm, PV {:.3} µm, noise floor {:.3} µm",
        cmp.rms_um, cmp.pv_um, cmp.noise_floor_um
    ))?;
    for b in cmp.failures.iter().take(4) {
        say(format!(
            "   fails at {:<20} {:<28} RMS {:.3} µm",
            b.feature, b.bin, b.rms_um
        ))?;
    }

    say("\n4. lab discover: refit the nominal model; then diagnose, add the best candidate, refit everything — until nothing significant is left".into())?;
    let t0 = std::time::Instant::now();
    let opts = discover::Options {
        build,
        max_steps,
        created: String::new(),
    };
    let out_dir = p("steps");
    std::fs::create_dir_all(&out_dir).with_context(|| format!("creating {}", out_dir.display()))?;
    let mut on_step = |s: &Step| -> std::result::Result<(), scancorr_core::lab::LabError> {
        crate::shared::output::write_file(
            "steps",
            &out_dir.join(format!("v{}.json", s.version)),
            s.calibration.to_json(),
        )
        .map_err(|e| scancorr_core::lab::LabError::Data(format!("{e:#}")))?;
        if !json {
            let what = match &s.replaces {
                Some(r) => format!("{} {} for {r}", s.action, s.effect),
                None => format!("{} {}", s.action, s.effect),
            };
            let _ = outln!(
                "   step {:>2} (v{:<2}) {:<44} held-out {:>7.3} → {:>7.3} µm",
                s.index,
                s.version,
                what,
                s.heldout_rms_before_um,
                s.heldout_rms_um
            );
        }
        Ok(())
    };
    let mut on_progress = |_: &str| {};
    let d = discover::discover(&bags, &start, &opts, &mut on_step, &mut on_progress)?;
    let secs = t0.elapsed().as_secs_f64();
    let f = &d.r#final;
    say(format!("   stopped after {secs:.1} s: {}", d.stopped))?;

    say("\n5. the error falls (held-out ring-speeds run, deviation RMS):".into())?;
    let max = d.start_heldout_rms_um.max(1e-9);
    let bar = |v: f64| "█".repeat(((v / max) * 48.0).round().max(1.0) as usize);
    say(format!(
        "   v1  {:<29} {:>7.3} µm {}",
        "nominal model (start)",
        d.start_heldout_rms_um,
        bar(d.start_heldout_rms_um)
    ))?;
    for s in &d.steps {
        say(format!(
            "   v{:<2} {:<29} {:>7.3} µm {}",
            s.version,
            format!("{} {}", s.action, s.effect.split(':').next().unwrap_or("")),
            s.heldout_rms_um,
            bar(s.heldout_rms_um)
        ))?;
    }
    say(format!(
        "   {:<33} {:>7.3} µm   (final: {:.2}× the floor)",
        "noise floor",
        f.noise_floor_um,
        f.heldout_rms_um / f.noise_floor_um.max(1e-9)
    ))?;
    for c in &d.confounded {
        say(format!(
            "   confounded on this campaign: {} and {} — to separate them: {}",
            c.effects[0],
            c.effects[1],
            c.separate_by.join("; ")
        ))?;
    }
    if !d.unidentifiable.is_empty() {
        say(format!(
            "   {} parameter(s) this campaign cannot determine (kept at minimum-norm values)",
            d.unidentifiable.len()
        ))?;
    }
    for s in &d.unexplained {
        say(format!(
            "   left unexplained: {} along {} ({:.3} µm) → custom terms {}",
            s.kind,
            s.axis,
            s.amplitude_um,
            s.custom_terms.join(" ")
        ))?;
    }
    let last = &d
        .steps
        .last()
        .context("the loop made no version")?
        .calibration;
    crate::shared::output::write_file("calibration.json", &p("calibration.json"), last.to_json())?;
    let (s1, _) = bags::correct(&p("heldout.mcap"), &start, None)?;
    let (s2, _) = bags::correct(&p("heldout.mcap"), last, None)?;
    say(format!(
        "   (corrected {} points of the held-out bag with v1 and v{}; alarms: {} / {})",
        s2.points, last.version, s1.alarms, s2.alarms
    ))?;
    // The reports: the start against the artifacts, and the loop (error fall, before and
    // after on the held-out circles).
    let mut reports = vec![];
    if keep {
        let ds2 = dataset::build(&bags, last, &build_opts)?;
        let cmp2 = analysis::compare(&ds2)?;
        crate::shared::provenance::register(&[
            ("--bag", p("campaign.mcap").as_path()),
            ("--validate", p("heldout.mcap").as_path()),
            ("--calib", p("v1.json").as_path()),
        ]);
        for (name, html) in [
            (
                "compare-v1.html",
                crate::report::compare(&start, &ds1, &cmp, None),
            ),
            (
                "discover.html",
                crate::report::discover(&start, &d, Some(((&ds1, &cmp), (&ds2, &cmp2)))),
            ),
        ] {
            let o = Some(crate::shared::output::AtomicOutput::new(
                "report",
                &p(name),
            )?);
            crate::shared::output::put(&o, html)?;
            crate::shared::output::commit_all([o])?;
            reports.push(p(name));
        }
    }
    let summary = serde_json::json!({
        "with": with,
        "steps": d.steps,
        "confounded": d.confounded,
        "final": d.r#final,
        "start_heldout_rms_um": d.start_heldout_rms_um,
        "seconds": secs,
        "dir": if keep { Some(dir.display().to_string()) } else { None },
    });
    if keep {
        say(format!(
            "\nfiles in {} (bags, truth.json, v1.json, steps/, calibration.json)",
            dir.display()
        ))?;
        for r in &reports {
            say(format!("report: {}", r.display()))?;
        }
        say(format!(
            "\nnext:\n  open {} (the error fall, before and after on the held-out circles)\n  scancorr lab diagnose --bag {} --validate {} --calib {} --report diagnose.html   # what is left\n  scancorr correct --bag {} --calib {} --out corrected.mcap && scancorr export --bag corrected.mcap --format xyz --out points.xyz   # the corrected points, for other software\n  scancorr calibrate tips|probe-force|dynamics …   # measure a real machine's parameters instead (README: Calibration procedures)",
            p("discover.html").display(),
            p("campaign.mcap").display(),
            p("heldout.mcap").display(),
            p("calibration.json").display(),
            p("heldout.mcap").display(),
            p("calibration.json").display()
        ))?;
    }
    Ok(summary)
}

fn sim(
    program: &str,
    seed: u64,
    position: Option<[f64; 3]>,
    with: &[String],
    out: &Path,
    truth: Option<&Path>,
    calib: Option<&Path>,
) -> Result<()> {
    for w in with {
        anyhow::ensure!(
            scancorr_sim::EXTRA_EFFECTS.contains(&w.as_str()),
            "--with {w}: known physics beyond the default machine: {}",
            scancorr_sim::EXTRA_EFFECTS.join(", ")
        );
    }
    let options = scancorr_sim::Options {
        program: program.into(),
        seed,
        position,
        // The start the demo builds is the nominal model: every library effect left out.
        hide: scancorr_sim::LIBRARY_EFFECTS
            .iter()
            .map(|s| s.to_string())
            .collect(),
        effects: with.iter().map(|w| (w.clone(), 1.0)).collect(),
        ..Default::default()
    };
    simulate::run_quiet(simulate::SimArgs {
        options,
        out: out.to_path_buf(),
        truth: truth.map(Path::to_path_buf),
        calib_out: calib.map(Path::to_path_buf),
        datasheet_out: None,
        catalogue_out: None,
        batch: 100,
        prefix: scancorr_proto::DEFAULT_PREFIX.into(),
        json: false,
    })
}
