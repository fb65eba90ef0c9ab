//! The lab's HTML reports render in a real browser with the plots the issue asks for: the polar
//! deviation plot of each ring (before and after in `lab add`), the residual against each
//! feature with the failing bins highlighted, the candidate ranking and the error-fall chart.
//!
//! A campaign is simulated with `accel_deflection` left out of the starting calibration, then
//! `lab diagnose`, `lab add accel_deflection` and `lab history` write their reports, and
//! `calibrate tips`, `calibrate probe-force` and `calibrate dynamics` theirs on their simulated measurements. Each report
//! must be one self-contained file (no scripts, no external resource) and is rendered in
//! headless Chromium three ways:
//!
//! * `--dump-dom`: the rendered DOM holds the expected `<svg data-plot=…>` plots;
//! * a harness page (this test's, with a script; the report has none) loads the report in an
//!   iframe and measures what the browser laid out: every plot has a size, every polar plot's
//!   curves have a length and extent, failing bins are painted in a different colour from the
//!   others, and the report fetched no resource at all;
//! * `--screenshot`: a 1200×3000 PNG that is not blank and differs from the same page with its
//!   plots removed.
//!
//! Chromium comes from `scripts/chromium.sh` (installs the Debian package `chromium` with
//! apt-get if it is missing). If it cannot be installed the test fails: it does not skip.

mod common;
use common::chromium::*;
use common::*;
use serde_json::Value;
use std::time::Instant;

#[test]
fn reports_render_in_headless_chromium() {
    let t0 = Instant::now();
    let d = scratch("report-html");
    ok(
        &d,
        &[
            "sim",
            "--program",
            "campaign",
            "--seed",
            "1",
            "--hide",
            "accel_deflection",
            "--out",
            "c.mcap",
            "--calib-out",
            "start.json",
        ],
    );
    ok(
        &d,
        &[
            "sim",
            "--program",
            "ring-speeds",
            "--seed",
            "2",
            "--position",
            "550,300,-250",
            "--out",
            "v.mcap",
        ],
    );
    let lab = [
        "--bag",
        "c.mcap",
        "--validate",
        "v.mcap",
        "--calib",
        "start.json",
    ];
    ok(
        &d,
        &[
            &["lab", "diagnose"][..],
            &lab,
            &["--report", "diagnose.html"],
        ]
        .concat(),
    );
    let added = ok(
        &d,
        &[
            &["lab", "add", "accel_deflection"][..],
            &lab,
            &["--out", "next.json", "--report", "add.html"],
        ]
        .concat(),
    );
    // Asked by its kind, `lab add` says which variant it added, and that variant is the one
    // written (issue 47: it used to add another than it said), in the version's note and the
    // report alike.
    let vname = added
        .lines()
        .find_map(|l| l.strip_prefix("added "))
        .and_then(|l| l.split(" → ").next())
        .unwrap_or_else(|| panic!("lab add names no variant:\n{added}"));
    let next: Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("next.json")).unwrap()).unwrap();
    let effect = next["effects"]
        .as_array()
        .unwrap()
        .iter()
        .find(|e| e["kind"] == "accel_deflection")
        .unwrap_or_else(|| panic!("no accel_deflection in next.json: {next:#}"));
    let variant = vname.split(" (").next().unwrap();
    let order: u64 = variant
        .split("order=")
        .nth(1)
        .map_or(0, |o| o.split(',').next().unwrap().parse().unwrap());
    assert!(
        variant.starts_with("accel_deflection")
            && (effect["diagonal"] == false) == variant.contains("full")
            && effect["position"]["order"].as_u64().unwrap_or(0) == order,
        "lab add said `{vname}` and wrote {effect}"
    );
    assert!(
        next["note"]
            .as_str()
            .unwrap()
            .starts_with(&format!("lab add {vname}")),
        "{}",
        next["note"]
    );
    let cal = d.join("calibs");
    std::fs::create_dir_all(&cal).unwrap();
    for f in ["start.json", "next.json"] {
        std::fs::copy(d.join(f), cal.join(f)).unwrap();
    }
    ok(
        &d,
        &[
            "lab",
            "history",
            "--calib-dir",
            "calibs",
            "--report",
            "history.html",
        ],
    );
    // The calibration procedures' reports, each from the nominal start a user has (no
    // effects, catalogue styli, data-sheet time constants).
    for (program, bag, proc, report) in [
        ("tips", "t.mcap", "tips", "tips.html"),
        ("dynamics", "d.mcap", "dynamics", "dynamics.html"),
        ("probe-force", "pf.mcap", "probe-force", "probe-force.html"),
    ] {
        measure_from_nominal(&d, program, "1", "1", bag, true);
        ok(
            &d,
            &[
                "calibrate",
                proc,
                "--bag",
                bag,
                "--calib",
                "nominal.json",
                "--out",
                &format!("{proc}.json"),
                "--report",
                report,
            ],
        );
    }
    eprintln!("reports written in {:.1} s", t0.elapsed().as_secs_f64());

    let chrome = chromium();
    let t1 = Instant::now();

    // Reference screenshot: an empty page.
    let blank = d.join("blank.html");
    std::fs::write(&blank, "<!doctype html><html><body></body></html>").unwrap();
    let blank_png = screenshot(&chrome, &d, "blank", &blank);

    for name in [
        "diagnose.html",
        "add.html",
        "history.html",
        "tips.html",
        "dynamics.html",
        "probe-force.html",
    ] {
        let path = d.join(name);
        let html = std::fs::read_to_string(&path).unwrap();
        assert_self_contained(name, &html);
        // Every fitted parameter named with a unit of the one table (issue 47, item 4).
        for table in html.split("<table data-params=\"1\">").skip(1) {
            let table = table.split("</table>").next().unwrap();
            for row in table.split("<tr><td>").skip(1) {
                let name = row.split("</td>").next().unwrap().replace("&amp;", "&");
                if let Err(e) = scancorr_core::units::check_name(&name) {
                    panic!("{name}: {e}");
                }
            }
        }

        // (a) The DOM Chromium built from the file.
        let dom = dump_dom(&chrome, &d, &format!("dom-{name}"), &path, &[]);
        let p = plots(&dom);
        let count = |k: &str| of_kind(&p, k).len();
        assert_eq!(
            plots(&html).len(),
            p.len(),
            "{name}: the rendered DOM lost plots"
        );
        // (b) What it laid out.
        let lay = layout(&chrome, &d, name);
        assert_eq!(
            lay["plots"].as_array().unwrap().len(),
            p.len(),
            "{name}: plots laid out vs in the DOM"
        );

        match name {
            "diagnose.html" => {
                assert!(
                    count("polar") >= 3,
                    "{name}: expected a polar plot per ring (≥ 3), got {}",
                    count("polar")
                );
                assert_eq!(count("ranking"), 1, "{name}: the candidate ranking");
                assert!(
                    of_kind(&p, "ranking")[0].contains("<rect"),
                    "{name}: the ranking has no bars"
                );
                let residual = of_kind(&p, "residual");
                assert!(!residual.is_empty(), "{name}: no residual chart");
                assert!(
                    residual.iter().any(|s| s.contains("data-failing=\"true\"")),
                    "{name}: accel_deflection is hidden, yet no residual bin is marked failing"
                );
                let polars = laid_out(name, &lay, "polar");
                assert!(
                    check_polars(name, &polars).iter().all(|&n| n >= 1),
                    "{name}: a polar plot without a curve"
                );
                let most = check_trace_colours(name, &polars);
                check_polar_captions(name, &html);
                eprintln!("{name}: up to {most} runs in one polar plot, each its own colour");
                // The sphere, scanned with two styli and one of them at two head angles, is
                // one trace per setting: never tip 1 and tip 2 pooled in one curve.
                let settings = |svg: &str| -> std::collections::BTreeSet<String> {
                    svg.split("<path ")
                        .skip(1)
                        .filter_map(|p| {
                            let a = |k: &str| p.split(&format!("{k}=\"")).nth(1)?.split('"').next();
                            Some(format!(
                                "{}/{}/{}",
                                a("data-tip")?,
                                a("data-a1-deg")?,
                                a("data-a2-deg")?
                            ))
                        })
                        .collect()
                };
                assert!(
                    of_kind(&p, "polar").iter().any(|s| settings(s).len() >= 2),
                    "{name}: no plot separates the sphere's styli or head angles"
                );
                assert!(
                    html.contains("data-trace=\"CCW") && html.contains(", tip "),
                    "{name}: traces not labelled with their setting"
                );
                let (hot, cold) = check_bars(name, &laid_out(name, &lay, "residual"));
                assert!(!hot.is_empty(), "{name}: no failing bar laid out");
                for f in &hot {
                    assert!(
                        !cold.contains(f),
                        "{name}: failing bins are painted like the others ({f})"
                    );
                }
                check_bars(name, &laid_out(name, &lay, "ranking"));
                // The best candidate's predicted residual drawn over the measurement, per
                // ring: each plot holds both layers, and what the candidate (the hidden
                // effect) predicts is rounder than what was measured.
                let predicted: Vec<&str> = of_kind(&p, "polar")
                    .into_iter()
                    .filter(|s| s.contains("data-role=\"predicted\""))
                    .collect();
                assert!(
                    predicted.len() >= 3,
                    "{name}: a prediction plot per ring, got {}",
                    predicted.len()
                );
                let circ = |s: &str, layer: &str| -> f64 {
                    s.split("<path ")
                        .filter(|p| p.contains(&format!("data-layer=\"{layer}\"")))
                        .filter_map(|p| {
                            p.split("data-circularity-um=\"")
                                .nth(1)?
                                .split('"')
                                .next()?
                                .parse::<f64>()
                                .ok()
                        })
                        .sum()
                };
                let (m, q): (f64, f64) = predicted
                    .iter()
                    .map(|s| (circ(s, "measured"), circ(s, "predicted")))
                    .fold((0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1));
                eprintln!("{name}: circularity summed over the traces: measured {m:.2} µm, predicted {q:.2} µm");
                assert!(
                    m > 0.0 && q < 0.8 * m,
                    "{name}: measured {m} µm, predicted {q} µm"
                );
                // The candidate's fitted parameters, with units and uncertainties, and names
                // a metrologist reads.
                assert!(html.contains("data-params"), "{name}: no parameter table");
                assert!(
                    html.contains("(mm per mm/s²)") && html.contains(" ± "),
                    "{name}: parameters without units or σ"
                );
                assert!(!html.contains("·1 ("), "{name}: a `·1` suffix");
            }
            "add.html" => {
                let polar = of_kind(&p, "polar");
                assert!(
                    polar.len() >= 3,
                    "{name}: expected a polar plot per ring (≥ 3), got {}",
                    polar.len()
                );
                // Before and after side by side, per ring, on the report's one scale, with
                // the same traces (direction × speed) in both.
                let attr = |s: &str, a: &str| -> String {
                    s.split(&format!("{a}=\""))
                        .nth(1)
                        .and_then(|x| x.split('"').next())
                        .unwrap_or("")
                        .to_string()
                };
                assert_eq!(polar.len() % 2, 0, "{name}: before/after pairs");
                // The before plots on one scale, the after plots on their own, finer one (the
                // residual left magnified, the magnification stated), each drawing what is
                // left over at least one division.
                let scale = attr(polar[0], "data-um-per-div");
                let after_scale = attr(polar[1], "data-um-per-div");
                let (b, a): (f64, f64) = (scale.parse().unwrap(), after_scale.parse().unwrap());
                assert!(a < b, "{name}: after {a} µm/div, before {b} µm/div");
                let ms = attr(polar[1], "data-magnification");
                let m: f64 = ms.parse().unwrap();
                assert!((m - b / a).abs() < 0.01 * m, "{name}: magnification {m}");
                assert!(
                    html.contains(&format!("magnified {ms}× against the before's")),
                    "{name}: the after's caption does not state its scale"
                );
                for pair in polar.chunks(2) {
                    assert_eq!(
                        attr(pair[1], "data-um-per-div"),
                        after_scale,
                        "{name}: one after scale"
                    );
                    let drawn = drawn_divisions(pair[1]);
                    assert!(
                        drawn >= 1.0,
                        "{name}: the after plot draws the residual over {drawn:.2} division(s): unreadable"
                    );
                }
                for pair in polar.chunks(2) {
                    assert_eq!(
                        (
                            attr(pair[0], "data-role").as_str(),
                            attr(pair[1], "data-role").as_str()
                        ),
                        ("before", "after"),
                        "{name}: a before and an after plot per ring"
                    );
                    assert_eq!(
                        attr(pair[0], "data-um-per-div"),
                        scale,
                        "{name}: one before scale"
                    );
                    let traces = |s: &str| s.matches("data-trace=").count();
                    assert!(
                        traces(pair[0]) >= 2 && traces(pair[0]) == traces(pair[1]),
                        "{name}: traces per direction and speed"
                    );
                }
                assert_eq!(count("error-fall"), 1, "{name}: the error-fall chart");
                let polars = laid_out(name, &lay, "polar");
                for (i, n) in check_polars(name, &polars).into_iter().enumerate() {
                    assert!(
                        n >= 2,
                        "{name}: polar plot {i}: a curve per direction and speed"
                    );
                }
                check_trace_colours(name, &polars);
                check_polar_captions(name, &html);
                check_after_scale(name, &html);
                let (_, bars) = check_bars(name, &laid_out(name, &lay, "error-fall"));
                assert!(
                    bars.len() >= 2,
                    "{name}: the error fall needs before and after"
                );
                check_bars(name, &laid_out(name, &lay, "residual"));
                assert!(
                    html.contains("data-params") && html.contains(" ± ") && !html.contains("·1 ("),
                    "{name}: the refitted parameters with units and uncertainties"
                );
            }
            "history.html" => {
                assert_eq!(count("error-fall"), 1, "{name}: the error-fall chart");
                let (_, bars) = check_bars(name, &laid_out(name, &lay, "error-fall"));
                assert!(
                    bars.len() >= 2,
                    "{name}: the error fall needs the starting version and the new one"
                );
            }
            "tips.html" => {
                assert_eq!(
                    count("tips-offsets"),
                    1,
                    "{name}: settings before and after"
                );
                assert_eq!(count("reference-drift"), 1, "{name}: the reference in time");
                let (_, bars) = check_bars(name, &laid_out(name, &lay, "tips-offsets"));
                assert_eq!(
                    bars.len(),
                    8,
                    "{name}: four crank settings, before and after"
                );
            }
            "dynamics.html" => {
                for k in ["delta-r-before", "delta-r-after", "p-along-x", "p-along-y"] {
                    assert_eq!(count(k), 1, "{name}: {k}");
                }
            }
            "probe-force.html" => {
                for k in ["radius-before", "radius-after"] {
                    assert_eq!(count(k), 1, "{name}: {k}");
                }
            }
            _ => unreachable!(),
        }

        // (c) Pixels: not blank, and the plots change them.
        let png = screenshot(&chrome, &d, &format!("shot-{name}"), &path);
        assert!(
            png.len() > 10_000 && png.len() > blank_png.len() && png != blank_png,
            "{name}: screenshot looks empty ({} bytes; empty page {} bytes)",
            png.len(),
            blank_png.len()
        );
        let bare = d.join(format!("bare-{name}"));
        std::fs::write(&bare, without_plots(&html)).unwrap();
        let bare_png = screenshot(&chrome, &d, &format!("bare-{name}"), &bare);
        assert_ne!(
            png, bare_png,
            "{name}: the screenshot is the same with the plots removed"
        );
        eprintln!(
            "{name}: {} plots ({} polar), screenshot {} kB (without plots {} kB, empty page {} kB)",
            p.len(),
            count("polar"),
            png.len() / 1000,
            bare_png.len() / 1000,
            blank_png.len() / 1000
        );
    }
    eprintln!(
        "rendered in {:.1} s; files in {}",
        t1.elapsed().as_secs_f64(),
        d.display()
    );
}

/// The compare report of a campaign with `servo_phase` left out of the calibration draws each
/// ring as a circular test does: one trace per direction and speed (not their mean, which
/// hides the mirror-image ovals of a servo mismatch), on a stated scale, with the certified
/// circle and the axes marked and each trace's circularity printed beside it; `lab compare
/// --json` lists the same traces.
#[test]
fn compare_report_draws_one_trace_per_direction_and_speed() {
    let d = scratch("report-compare-traces");
    ok(
        &d,
        &[
            "sim",
            "--program",
            "campaign",
            "--seed",
            "1",
            "--hide",
            "servo_phase",
            "--out",
            "c.mcap",
            "--calib-out",
            "start.json",
        ],
    );
    let args = ["lab", "compare", "--bag", "c.mcap", "--calib", "start.json"];
    ok(&d, &[&args[..], &["--report", "compare.html"]].concat());
    let j: Value = serde_json::from_str(&ok(&d, &[&args[..], &["--json"]].concat())).unwrap();
    let traces = j["traces"].as_array().expect("traces");
    // The campaign's rings: both directions at each of its speeds.
    let mut rings: std::collections::BTreeMap<u64, Vec<(i64, f64, f64)>> = Default::default();
    for t in traces.iter().filter(|t| t["artifact"] == "ring") {
        rings
            .entry(t["feature"].as_u64().unwrap())
            .or_default()
            .push((
                t["direction"].as_i64().unwrap(),
                t["speed_mm_s"].as_f64().unwrap(),
                t["circularity_um"].as_f64().unwrap(),
            ));
    }
    assert!(rings.len() >= 3, "{rings:?}");
    let fast_min = 60.0;
    for (f, ts) in &rings {
        let ccw = ts.iter().filter(|t| t.0 == 1).count();
        assert!(ccw >= 3 && ccw * 2 == ts.len(), "ring {f}: {ts:?}");
        for t in ts.iter().filter(|t| t.1 >= fast_min) {
            assert!(t.2 > 5.0, "ring {f}: the servo mismatch at speed: {t:?}");
        }
        for t in ts.iter().filter(|t| t.1 <= 10.0) {
            assert!(t.2 < 2.0, "ring {f}: slowly the mismatch is small: {t:?}");
        }
    }

    let chrome = chromium();
    let path = d.join("compare.html");
    let html = std::fs::read_to_string(&path).unwrap();
    assert_self_contained("compare.html", &html);
    // The summary names the model's effects in words (none: the nominal model).
    let start: Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("start.json")).unwrap()).unwrap();
    let said = match start["effects"].as_array().map_or(0, |a| a.len()) {
        0 => "(no effects: the nominal model)".to_string(),
        1 => "(1 effect: ".to_string(),
        n => format!("({n} effects: "),
    };
    assert!(html.contains(&said), "compare.html does not say {said}");
    let dom = dump_dom(&chrome, &d, "dom-compare", &path, &[]);
    let p = plots(&dom);
    let polar = of_kind(&p, "polar");
    assert_eq!(
        polar.len(),
        rings.len() + 1,
        "a polar plot per ring and the sphere"
    );
    for (svg, (f, ts)) in polar.iter().zip(&rings) {
        // One path per trace, each its own direction and speed; the axes and scale labelled.
        let drawn: Vec<(String, String, f64, String)> = svg
            .split("<path ")
            .skip(1)
            .map(|s| {
                let a = |k: &str| {
                    s.split(&format!("{k}=\""))
                        .nth(1)
                        .unwrap()
                        .split('"')
                        .next()
                        .unwrap()
                        .to_string()
                };
                (
                    a("data-direction"),
                    a("data-speed-mm-s"),
                    a("data-circularity-um").parse().unwrap(),
                    format!(
                        "{}/{}/{}/{}",
                        a("data-tip"),
                        a("data-a1-deg"),
                        a("data-a2-deg"),
                        a("data-deflection-mm")
                    ),
                )
            })
            .collect();
        assert_eq!(drawn.len(), ts.len(), "ring {f}: {drawn:?}");
        // One trace per run: direction, speed and setting (tip, head angles, deflection).
        let mut keys: Vec<_> = drawn
            .iter()
            .map(|x| (x.0.clone(), x.1.clone(), x.3.clone()))
            .collect();
        keys.sort();
        keys.dedup();
        assert_eq!(keys.len(), drawn.len(), "ring {f}: a trace per run");
        assert!(
            svg.contains("+X") && svg.contains("+Y") && svg.contains("µm/div"),
            "ring {f}"
        );
        assert!(svg.contains("data-um-per-div"), "ring {f}");
        for (dir, v, c, _) in &drawn {
            let t = ts
                .iter()
                .find(|t| {
                    (t.0 == 1) == (dir == "ccw")
                        && format!("{}", t.1) == *v
                        && (t.2 - c).abs() < 1e-3
                })
                .unwrap_or_else(|| panic!("ring {f}: {dir} {v} not in the JSON"));
            assert!(
                (t.2 - c).abs() < 1e-3,
                "ring {f}: {dir} {v}: {c} vs {}",
                t.2
            );
        }
    }
    // The circularity printed beside each trace (the figure's legend), the fast ones above
    // 5 µm on every ring.
    let figures: Vec<&str> = dom
        .split("<figure>")
        .skip(1)
        .map(|f| f.split("</figure>").next().unwrap())
        .collect();
    let mut n_ring_figures = 0;
    for fig in &figures {
        let legend: Vec<(String, f64)> = fig
            .split("<li>")
            .skip(1)
            .filter_map(|li| {
                let li = li.split("</li>").next()?;
                let c: f64 = li
                    .split("data-circularity-um=\"")
                    .nth(1)?
                    .split('"')
                    .next()?
                    .parse()
                    .ok()?;
                Some((li.to_string(), c))
            })
            .collect();
        assert_eq!(
            legend.len(),
            fig.matches("<path ").count(),
            "a legend line per trace: {fig}"
        );
        if !fig.contains("<b>ring") {
            continue;
        }
        n_ring_figures += 1;
        let fast: Vec<&(String, f64)> = legend
            .iter()
            .filter(|(li, _)| li.contains(" 60 mm/s") || li.contains(" 90 mm/s"))
            .collect();
        assert!(fast.len() >= 4 && fast.len() % 2 == 0, "{legend:?}");
        for (li, c) in fast {
            assert!(
                *c > 5.0 && li.contains("circularity") && li.contains("µm"),
                "{li}"
            );
        }
    }
    assert_eq!(n_ring_figures, rings.len());
    // Laid out: every trace drawn with a length and extent.
    let lay = layout(&chrome, &d, "compare.html");
    let polars = laid_out("compare.html", &lay, "polar");
    for n in check_polars("compare.html", &polars) {
        assert!(n >= 2);
    }
    let most = check_trace_colours("compare.html", &polars);
    check_polar_captions("compare.html", &html);
    assert!(most >= 8, "compare.html: at most {most} runs in a plot");
}
