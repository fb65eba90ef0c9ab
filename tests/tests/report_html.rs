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
use common::*;
use serde_json::Value;
use std::fs::File;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Chromium is killed (with its whole process group) after this long.
const CHROMIUM_TIMEOUT: Duration = Duration::from_secs(60);
const WINDOW: (u32, u32) = (1200, 3000);

/// Flags every Chromium run needs on a headless machine without network (without the
/// networking ones it waits on the network).
const FLAGS: &[&str] = &[
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-default-apps",
    "--disable-extensions",
    "--mute-audio",
];

/// The path of Chromium from `scripts/chromium.sh` (installing it if needed), or a failure
/// that says why.
fn chromium() -> PathBuf {
    let script = root().join("scripts/chromium.sh");
    let t = Instant::now();
    let o = Command::new("bash")
        .arg(&script)
        .stdin(Stdio::null())
        .output()
        .unwrap_or_else(|e| panic!("cannot run {}: {e}", script.display()));
    let stdout = String::from_utf8_lossy(&o.stdout);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(
        o.status.success(),
        "headless Chromium is required to test the HTML reports and {} could not provide it \
         ({}):\n{stderr}\nInstall it (Debian: `apt-get install chromium`) or put a `chromium` on PATH.",
        script.display(),
        o.status
    );
    let path = PathBuf::from(
        stdout
            .lines()
            .last()
            .unwrap_or_else(|| panic!("{} printed no path:\n{stderr}", script.display()))
            .trim(),
    );
    assert!(
        path.exists(),
        "{} printed `{}`, which does not exist",
        script.display(),
        path.display()
    );
    eprintln!(
        "chromium: {} (ready in {:.1} s)",
        path.display(),
        t.elapsed().as_secs_f64()
    );
    path
}

/// `file://` URL of an absolute path.
fn file_url(p: &Path) -> String {
    let mut s = String::from("file://");
    for b in p.to_str().expect("UTF-8 path").bytes() {
        if b.is_ascii_alphanumeric() || b"/-_.~".contains(&b) {
            s.push(b as char);
        } else {
            s.push_str(&format!("%{b:02X}"));
        }
    }
    s
}

/// Runs Chromium with `args` and a fresh profile in `dir`, stdout to a file; kills it (and its
/// children) after [`CHROMIUM_TIMEOUT`]. Returns stdout; panics with stderr on failure.
fn run_chromium(chrome: &Path, dir: &Path, tag: &str, args: &[String]) -> String {
    let profile = dir.join(format!("profile-{tag}"));
    let _ = std::fs::remove_dir_all(&profile);
    std::fs::create_dir_all(&profile).unwrap();
    let (out, err) = (
        dir.join(format!("chromium-{tag}.out")),
        dir.join(format!("chromium-{tag}.err")),
    );
    let mut child = Command::new(chrome)
        .args(FLAGS)
        .arg(format!("--user-data-dir={}", profile.display()))
        .args(args)
        .current_dir(dir)
        .stdin(Stdio::null())
        .stdout(File::create(&out).unwrap())
        .stderr(File::create(&err).unwrap())
        .process_group(0)
        .spawn()
        .unwrap_or_else(|e| panic!("cannot start {}: {e}", chrome.display()));
    let start = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if start.elapsed() > CHROMIUM_TIMEOUT {
            let _ = Command::new("kill")
                .args(["-KILL", "--", &format!("-{}", child.id())])
                .status();
            let _ = child.kill();
            let _ = child.wait();
            panic!(
                "chromium {args:?} did not finish within {CHROMIUM_TIMEOUT:?}; stderr:\n{}",
                tail(&std::fs::read_to_string(&err).unwrap_or_default())
            );
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let _ = std::fs::remove_dir_all(&profile);
    let stderr = std::fs::read_to_string(&err).unwrap_or_default();
    assert!(
        status.success(),
        "chromium {args:?} failed ({status}):\n{}",
        tail(&stderr)
    );
    std::fs::read_to_string(&out).unwrap()
}

fn tail(s: &str) -> String {
    let lines: Vec<&str> = s.lines().collect();
    lines[lines.len().saturating_sub(30)..].join("\n")
}

/// The DOM after Chromium loaded and laid out `page`.
fn dump_dom(chrome: &Path, dir: &Path, tag: &str, page: &Path, extra: &[&str]) -> String {
    let mut args: Vec<String> = extra.iter().map(|s| s.to_string()).collect();
    args.push("--dump-dom".into());
    args.push(file_url(page));
    let dom = run_chromium(chrome, dir, tag, &args);
    assert!(
        dom.trim_end().ends_with("</html>"),
        "chromium dumped an incomplete DOM for {}:\n{}",
        page.display(),
        &dom[..dom.len().min(2000)]
    );
    dom
}

/// A screenshot of `page`; returns the PNG's bytes.
fn screenshot(chrome: &Path, dir: &Path, tag: &str, page: &Path) -> Vec<u8> {
    let png = dir.join(format!("{tag}.png"));
    let _ = std::fs::remove_file(&png);
    run_chromium(
        chrome,
        dir,
        tag,
        &[
            format!("--screenshot={}", png.display()),
            format!("--window-size={},{}", WINDOW.0, WINDOW.1),
            "--hide-scrollbars".into(),
            file_url(page),
        ],
    );
    let bytes = std::fs::read(&png)
        .unwrap_or_else(|e| panic!("chromium wrote no screenshot {}: {e}", png.display()));
    assert!(
        bytes.len() > 24 && bytes.starts_with(b"\x89PNG\r\n\x1a\n") && &bytes[12..16] == b"IHDR",
        "{} is not a PNG",
        png.display()
    );
    let be = |i: usize| u32::from_be_bytes(bytes[i..i + 4].try_into().unwrap());
    assert_eq!(
        (be(16), be(20)),
        WINDOW,
        "{}: screenshot size",
        png.display()
    );
    bytes
}

/// The `<svg …>…</svg>` elements of a document: (data-plot, markup).
fn plots(doc: &str) -> Vec<(String, String)> {
    let mut v = Vec::new();
    let mut rest = doc;
    while let Some(i) = rest.find("<svg") {
        let end = rest[i..]
            .find("</svg>")
            .map(|j| i + j + 6)
            .expect("unclosed <svg>");
        let svg = &rest[i..end];
        let open = &svg[..svg.find('>').unwrap()];
        let kind = open
            .split("data-plot=\"")
            .nth(1)
            .and_then(|s| s.split('"').next())
            .unwrap_or("")
            .to_string();
        v.push((kind, svg.to_string()));
        rest = &rest[end..];
    }
    v
}

fn of_kind<'a>(p: &'a [(String, String)], kind: &str) -> Vec<&'a str> {
    p.iter()
        .filter(|(k, _)| k == kind)
        .map(|(_, s)| s.as_str())
        .collect()
}

/// The document with every `<svg>…</svg>` removed.
fn without_plots(doc: &str) -> String {
    let mut s = String::new();
    let mut rest = doc;
    while let Some(i) = rest.find("<svg") {
        s.push_str(&rest[..i]);
        let j = rest[i..].find("</svg>").expect("unclosed <svg>");
        rest = &rest[i + j + 6..];
    }
    s + rest
}

/// The report is one self-contained file: no script, nothing fetched or linked. The one URL an
/// inline SVG may carry is its namespace name, which is never fetched.
fn assert_self_contained(name: &str, html: &str) {
    let low = html.to_ascii_lowercase();
    let scrubbed = low.replace("xmlns=\"http://www.w3.org/2000/svg\"", "");
    for bad in [
        "http://", "https://", "<script", " src=", "href=", "<link", "<img", "<iframe", "<object",
        "<embed", "@import", "url(", " on",
    ] {
        // " on" catches event-handler attributes (onload=…) only inside tags.
        let hit = if bad == " on" {
            tags(&scrubbed).any(|t| {
                t.split_whitespace()
                    .skip(1)
                    .any(|a| a.starts_with("on") && a.contains('='))
            })
        } else {
            scrubbed.contains(bad)
        };
        assert!(!hit, "{name}: not self-contained, contains `{bad}`");
    }
}

/// The opening tags of a document (`<name attr…`), without the brackets.
fn tags(doc: &str) -> impl Iterator<Item = &str> {
    doc.split('<')
        .skip(1)
        .filter_map(|s| s.split('>').next())
        .filter(|t| !t.starts_with('/') && !t.starts_with('!'))
}

/// A page of this test's (not the report's) that loads `report` in an iframe and writes what
/// the browser laid out as JSON into `<pre id="result">`.
const HARNESS: &str = r#"<!doctype html><html><head><meta charset="utf-8"></head><body>
<iframe id="r" src="REPORT" width="1200" height="3000"></iframe>
<script>
window.addEventListener('load', function () {
  var out = {};
  try {
    var w = document.getElementById('r').contentWindow, d = w.document;
    out.title = d.title;
    out.resources = w.performance.getEntriesByType('resource').map(function (e) { return e.name; });
    out.plots = Array.prototype.map.call(d.querySelectorAll('svg'), function (s) {
      var r = s.getBoundingClientRect();
      return {
        kind: s.getAttribute('data-plot'),
        width: r.width, height: r.height,
        visible: w.getComputedStyle(s).visibility === 'visible' && w.getComputedStyle(s).display !== 'none',
        paths: Array.prototype.map.call(s.querySelectorAll('path'), function (p) {
          var b = p.getBBox();
          var cs = w.getComputedStyle(p);
          return { stroke: cs.stroke, dash: cs.strokeDasharray, layer: p.getAttribute('data-layer'),
                   direction: p.getAttribute('data-direction'), run: p.getAttribute('data-trace'),
                   length: p.getTotalLength(), width: b.width, height: b.height };
        }),
        rects: Array.prototype.map.call(s.querySelectorAll('rect'), function (p) {
          var b = p.getBBox();
          return { failing: p.getAttribute('data-failing'), fill: w.getComputedStyle(p).fill, width: b.width, height: b.height };
        })
      };
    });
  } catch (e) { out.error = String(e); }
  var pre = document.createElement('pre');
  pre.id = 'result';
  pre.textContent = JSON.stringify(out);
  document.body.appendChild(pre);
});
</script></body></html>"#;

/// What the browser laid out for `report` (see [`HARNESS`]).
fn layout(chrome: &Path, dir: &Path, report: &str) -> Value {
    let page = dir.join(format!("harness-{report}"));
    std::fs::write(&page, HARNESS.replace("REPORT", report)).unwrap();
    let tag = format!("layout-{report}");
    // The harness reads the report's document across file:// URLs.
    let dom = dump_dom(
        chrome,
        dir,
        &tag,
        &page,
        &["--allow-file-access-from-files"],
    );
    let json = dom
        .split("<pre id=\"result\">")
        .nth(1)
        .and_then(|s| s.split("</pre>").next())
        .unwrap_or_else(|| panic!("{report}: the harness wrote no result:\n{}", tail(&dom)));
    let json = json
        .replace("&lt;", "<")
        .replace("&gt;", ">")
        .replace("&nbsp;", "\u{a0}")
        .replace("&amp;", "&");
    let v: Value = serde_json::from_str(&json)
        .unwrap_or_else(|e| panic!("{report}: harness result is not JSON ({e}): {json}"));
    assert!(
        v.get("error").is_none(),
        "{report}: the harness could not inspect the report: {}",
        v["error"]
    );
    v
}

fn num(v: &Value) -> f64 {
    v.as_f64().unwrap_or(f64::NAN)
}

/// Checks common to every laid-out plot; returns the plots of `kind`.
fn laid_out<'a>(name: &str, lay: &'a Value, kind: &str) -> Vec<&'a Value> {
    let res = lay["resources"].as_array().unwrap();
    assert!(res.is_empty(), "{name}: the report fetched {res:?}");
    let plots = lay["plots"].as_array().unwrap();
    for p in plots {
        assert!(
            p["visible"].as_bool() == Some(true)
                && num(&p["width"]) >= 50.0
                && num(&p["height"]) >= 30.0,
            "{name}: a {} plot is not laid out visibly: {p}",
            p["kind"]
        );
    }
    plots.iter().filter(|p| p["kind"] == kind).collect()
}

/// Polar plots: every curve has a length and spans most of the plot. Returns the number of
/// curves per plot.
fn check_polars(name: &str, polars: &[&Value]) -> Vec<usize> {
    polars
        .iter()
        .map(|p| {
            let paths = p["paths"].as_array().unwrap();
            for c in paths {
                assert!(
                    num(&c["length"]) > 100.0
                        && num(&c["width"]) > 40.0
                        && num(&c["height"]) > 20.0,
                    "{name}: a polar curve is (nearly) empty: {c}"
                );
            }
            paths.len()
        })
        .collect()
}

/// `rgb(r, g, b)` as the browser computes a colour.
fn rgb(c: &str) -> [f64; 3] {
    let v: Vec<f64> = c
        .trim_start_matches("rgba(")
        .trim_start_matches("rgb(")
        .trim_end_matches(')')
        .split(',')
        .filter_map(|x| x.trim().parse().ok())
        .collect();
    assert!(v.len() >= 3, "not a colour: {c}");
    [v[0], v[1], v[2]]
}

/// The colours the browser paints the traces of each polar plot with: every run of a plot
/// (a speed, a setting, a direction) has its own colour, no two closer than a plainly visible
/// step, the measured layer under a prediction excepted (it repeats its run's colour, faint);
/// clockwise runs are dashed, counter-clockwise ones solid. Returns the most runs in one plot.
fn check_trace_colours(name: &str, polars: &[&Value]) -> usize {
    let mut most = 0;
    for (i, p) in polars.iter().enumerate() {
        let paths: Vec<&Value> = p["paths"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|c| c["layer"] != "measured")
            .collect();
        most = most.max(paths.len());
        for (a, pa) in paths.iter().enumerate() {
            let dashed = pa["dash"].as_str().unwrap_or("none") != "none";
            assert_eq!(
                dashed,
                pa["direction"] == "cw",
                "{name}: polar plot {i}: {} dashed {dashed}",
                pa["run"]
            );
            for pb in &paths[a + 1..] {
                let (ca, cb) = (
                    rgb(pa["stroke"].as_str().unwrap()),
                    rgb(pb["stroke"].as_str().unwrap()),
                );
                let d =
                    ((ca[0] - cb[0]).powi(2) + (ca[1] - cb[1]).powi(2) + (ca[2] - cb[2]).powi(2))
                        .sqrt();
                assert!(
                    d >= 20.0,
                    "{name}: polar plot {i}: `{}` ({}) and `{}` ({}) are painted alike",
                    pa["run"],
                    pa["stroke"],
                    pb["run"],
                    pb["stroke"]
                );
            }
        }
    }
    most
}

/// The largest deviation a polar plot draws, in its divisions: the farthest any point of a
/// curve lies from the certified circle (radius 100 px at the centre (200, 200); 20 px a
/// division).
fn drawn_divisions(svg: &str) -> f64 {
    svg.split("<path ")
        .skip(1)
        .filter(|p| !p.contains("data-layer=\"measured\""))
        .filter_map(|p| p.split(" d=\"").nth(1)?.split('"').next())
        .flat_map(|d| d.split_whitespace())
        .filter_map(|xy| {
            let (x, y) = xy.trim_start_matches(['M', 'L']).split_once(',')?;
            let (x, y): (f64, f64) = (x.parse().ok()?, y.parse().ok()?);
            Some((((x - 200.0).powi(2) + (y - 200.0).powi(2)).sqrt() - 100.0).abs() / 20.0)
        })
        .fold(0.0, f64::max)
}

/// Bar charts: every bar has a size; returns (fills of failing bars, fills of others).
fn check_bars(name: &str, charts: &[&Value]) -> (Vec<String>, Vec<String>) {
    let (mut hot, mut cold) = (Vec::new(), Vec::new());
    for c in charts {
        let rects = c["rects"].as_array().unwrap();
        assert!(
            !rects.is_empty(),
            "{name}: a {} chart has no bars",
            c["kind"]
        );
        for r in rects {
            assert!(
                num(&r["width"]) > 0.0 && num(&r["height"]) > 5.0,
                "{name}: a bar is not drawn: {r}"
            );
            let fill = r["fill"].as_str().unwrap_or("").to_string();
            if r["failing"] == "true" {
                hot.push(fill);
            } else {
                cold.push(fill);
            }
        }
    }
    (hot, cold)
}

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
    ok(
        &d,
        &[
            &["lab", "add", "accel_deflection"][..],
            &lab,
            &["--out", "next.json", "--report", "add.html"],
        ]
        .concat(),
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
    assert!(most >= 8, "compare.html: at most {most} runs in a plot");
}
