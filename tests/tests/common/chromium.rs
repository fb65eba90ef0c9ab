//! Headless Chromium for the HTML reports (shared by `report_html.rs` and the README's demo
//! check in `readme_blocks.rs`): Chromium from `scripts/chromium.sh`, the DOM it built, what it
//! laid out (a harness page measuring each plot), screenshots, and the checks of the polar
//! plots every report shares: a curve per run, a colour per run never repeated in a plot,
//! clockwise dashed, the "after" on its own scale and the legend painted as the drawing.

use super::*;
use serde_json::Value;
use std::fs::File;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Chromium is killed (with its whole process group) after this long.
pub const CHROMIUM_TIMEOUT: Duration = Duration::from_secs(60);
pub const WINDOW: (u32, u32) = (1200, 3000);

/// Flags every Chromium run needs on a headless machine without network (without the
/// networking ones it waits on the network).
pub const FLAGS: &[&str] = &[
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
pub fn chromium() -> PathBuf {
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
pub fn file_url(p: &Path) -> String {
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
pub fn run_chromium(chrome: &Path, dir: &Path, tag: &str, args: &[String]) -> String {
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

pub fn tail(s: &str) -> String {
    let lines: Vec<&str> = s.lines().collect();
    lines[lines.len().saturating_sub(30)..].join("\n")
}

/// The DOM after Chromium loaded and laid out `page`.
pub fn dump_dom(chrome: &Path, dir: &Path, tag: &str, page: &Path, extra: &[&str]) -> String {
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
pub fn screenshot(chrome: &Path, dir: &Path, tag: &str, page: &Path) -> Vec<u8> {
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
pub fn plots(doc: &str) -> Vec<(String, String)> {
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

pub fn of_kind<'a>(p: &'a [(String, String)], kind: &str) -> Vec<&'a str> {
    p.iter()
        .filter(|(k, _)| k == kind)
        .map(|(_, s)| s.as_str())
        .collect()
}

/// The document with every `<svg>…</svg>` removed.
pub fn without_plots(doc: &str) -> String {
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
pub fn assert_self_contained(name: &str, html: &str) {
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
pub fn tags(doc: &str) -> impl Iterator<Item = &str> {
    doc.split('<')
        .skip(1)
        .filter_map(|s| s.split('>').next())
        .filter(|t| !t.starts_with('/') && !t.starts_with('!'))
}

/// A page of this test's (not the report's) that loads `report` in an iframe and writes what
/// the browser laid out as JSON into `<pre id="result">`.
pub const HARNESS: &str = r#"<!doctype html><html><head><meta charset="utf-8"></head><body>
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
pub fn layout(chrome: &Path, dir: &Path, report: &str) -> Value {
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

pub fn num(v: &Value) -> f64 {
    v.as_f64().unwrap_or(f64::NAN)
}

/// Checks common to every laid-out plot; returns the plots of `kind`.
pub fn laid_out<'a>(name: &str, lay: &'a Value, kind: &str) -> Vec<&'a Value> {
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
pub fn check_polars(name: &str, polars: &[&Value]) -> Vec<usize> {
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
pub fn rgb(c: &str) -> [f64; 3] {
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
pub fn check_trace_colours(name: &str, polars: &[&Value]) -> usize {
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
pub fn drawn_divisions(svg: &str) -> f64 {
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
pub fn check_bars(name: &str, charts: &[&Value]) -> (Vec<String>, Vec<String>) {
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

/// HSL lightness (0…1) of a colour the browser computed.
fn lightness(c: &str) -> f64 {
    let [r, g, b] = rgb(c);
    let (hi, lo) = (r.max(g).max(b), r.min(g).min(b));
    (hi + lo) / 2.0 / 255.0
}

/// `attr="…"` of the first tag in `s` that has it.
fn attr<'a>(s: &'a str, a: &str) -> Option<&'a str> {
    s.split(&format!(" {a}=\"")).nth(1)?.split('"').next()
}

/// Each polar plot's figure as drawn and as its caption says: the legend lists the plot's
/// traces in the drawing's order, each in its path's colour (the colour the caption's line
/// stands for is the curve's); the caption promises a colour per setting and speed never
/// repeated, counter-clockwise lighter and solid, clockwise darker and dashed, and names no
/// other colour scheme (no red/blue): each holds in the drawing. Returns the most distinct
/// speeds in one plot.
pub fn check_polar_captions(name: &str, html: &str) -> usize {
    let mut most_speeds = 0;
    let figures: Vec<&str> = html
        .split("<figure>")
        .skip(1)
        .map(|f| f.split("</figure>").next().unwrap())
        .filter(|f| f.contains("data-plot=\"polar\""))
        .collect();
    assert!(!figures.is_empty(), "{name}: no polar plot");
    for (i, fig) in figures.iter().enumerate() {
        let (svg, caption) = fig.split_once("</svg>").unwrap();
        let paths: Vec<&str> = svg
            .split("<path ")
            .skip(1)
            .filter(|p| attr(p, "data-layer") != Some("measured"))
            .collect();
        let legend: Vec<&str> = caption
            .split("<li>")
            .skip(1)
            .filter_map(|li| attr(li, "style")?.strip_prefix("color:"))
            .collect();
        let strokes: Vec<&str> = paths.iter().map(|p| attr(p, "stroke").unwrap()).collect();
        assert_eq!(
            legend, strokes,
            "{name}: polar plot {i}: the legend's colours are not the curves'"
        );
        let low = caption.to_lowercase();
        assert!(
            low.contains("never repeated")
                && low.contains("counter-clockwise lighter and solid")
                && low.contains("clockwise darker and dashed")
                && !low.contains(" red")
                && !low.contains(" blue"),
            "{name}: polar plot {i}: the caption does not say how the curves are drawn: {caption}"
        );
        let mut speeds = std::collections::BTreeSet::new();
        for p in &paths {
            let dashed = attr(p, "stroke-dasharray").is_some();
            assert_eq!(
                dashed,
                attr(p, "data-direction") == Some("cw"),
                "{name}: polar plot {i}: {:?} dashed {dashed}",
                attr(p, "data-trace")
            );
            speeds.insert(attr(p, "data-speed-mm-s").unwrap().to_string());
        }
        most_speeds = most_speeds.max(speeds.len());
        // The same setting and speed both ways: the counter-clockwise curve the lighter.
        let run = |p: &str| {
            [
                "data-speed-mm-s",
                "data-tip",
                "data-a1-deg",
                "data-a2-deg",
                "data-deflection-mm",
            ]
            .map(|a| attr(p, a).unwrap_or("").to_string())
        };
        for a in paths
            .iter()
            .filter(|p| attr(p, "data-direction") == Some("ccw"))
        {
            for b in paths
                .iter()
                .filter(|p| attr(p, "data-direction") == Some("cw"))
            {
                if run(a) == run(b) {
                    let hex = |p: &str| {
                        let h = attr(p, "stroke").unwrap().trim_start_matches('#');
                        let v = |k: usize| u8::from_str_radix(&h[k..k + 2], 16).unwrap();
                        format!("rgb({}, {}, {})", v(0), v(2), v(4))
                    };
                    assert!(
                        lightness(&hex(a)) > lightness(&hex(b)) + 0.05,
                        "{name}: polar plot {i}: {:?} counter-clockwise is not the lighter",
                        attr(a, "data-trace")
                    );
                }
            }
        }
    }
    most_speeds
}

/// The "after" plots of a before/after report on their own scale: finer than the before's, the
/// magnification stated in the plot and its caption, and the residual left drawn over at
/// least one division (readable, not a perfect circle). Returns the after plots checked.
pub fn check_after_scale(name: &str, html: &str) -> usize {
    let p = plots(html);
    let polar = of_kind(&p, "polar");
    let role = |s: &str| attr(s, "data-role").unwrap_or("").to_string();
    let before: Vec<&&str> = polar.iter().filter(|s| role(s) == "before").collect();
    let after: Vec<&&str> = polar.iter().filter(|s| role(s) == "after").collect();
    assert!(
        !after.is_empty() && before.len() == after.len(),
        "{name}: {} before and {} after plots",
        before.len(),
        after.len()
    );
    let upd = |s: &str| -> f64 { attr(s, "data-um-per-div").unwrap().parse().unwrap() };
    for (b, a) in before.iter().zip(&after) {
        let (ub, ua) = (upd(b), upd(a));
        let drawn = drawn_divisions(a);
        assert!(
            drawn >= 1.0,
            "{name}: an after plot ({ua} µm/div) draws the residual over {drawn:.2} division(s): unreadable"
        );
        if ua < ub {
            let m = attr(a, "data-magnification").unwrap_or_else(|| {
                panic!("{name}: an after plot finer than its before states no magnification")
            });
            assert!(
                (m.parse::<f64>().unwrap() - ub / ua).abs() < 0.01 * ub / ua
                    && html.contains(&format!("magnified {m}× against the before's")),
                "{name}: after ×{m} ({ua} against {ub} µm/div) not stated"
            );
        }
    }
    after.len()
}

/// The demo's reports (issue 47's acceptance): `compare-v1.html` and `discover.html` as
/// `scancorr demo`, run in `dir`, wrote them in `dir/scancorr-demo/`, and `diagnose.html`
/// written by the `lab diagnose` line the demo printed as its next step (`demo_out`, its
/// output), run as printed in `dir`. Each is
/// self-contained, laid out and screenshotted by Chromium; in every polar plot each run (speed
/// and setting, each direction) is painted in its own colour, the legend and caption as drawn;
/// some plot holds more than six runs (where a palette of six would wrap);
/// discover's "after" plots are on their own, stated, readable scale. Returns a failure
/// instead of panicking, so that the README test reports it with its blocks.
pub fn check_demo_reports(dir: &Path, demo_out: &str) -> Option<String> {
    let dir = dir.to_path_buf();
    let out = demo_out.to_string();
    let r = std::panic::catch_unwind(move || demo_reports(&dir, &out));
    r.err().map(|e| {
        e.downcast_ref::<String>()
            .cloned()
            .or_else(|| e.downcast_ref::<&str>().map(|s| s.to_string()))
            .unwrap_or_else(|| "the demo's reports check panicked".into())
    })
}

fn demo_reports(dir: &Path, demo_out: &str) {
    let t0 = Instant::now();
    let line = demo_out
        .lines()
        .map(str::trim)
        .find(|l| l.starts_with("scancorr lab diagnose "))
        .unwrap_or_else(|| {
            panic!("the demo printed no `scancorr lab diagnose` next step:\n{demo_out}")
        });
    let cmd = line.split("  #").next().unwrap().trim();
    let args: Vec<&str> = cmd.split_whitespace().skip(1).collect();
    assert!(args.contains(&"--report"), "{cmd}");
    ok(dir, &args);
    eprintln!(
        "demo reports: `{cmd}` in {:.1} s",
        t0.elapsed().as_secs_f64()
    );
    // The three side by side (the harness page loads a report beside it).
    let work = dir;
    let dir = &work.join("demo-reports");
    std::fs::create_dir_all(dir).unwrap();
    for (from, name) in [
        ("scancorr-demo/compare-v1.html", "compare-v1.html"),
        ("scancorr-demo/discover.html", "discover.html"),
        ("diagnose.html", "diagnose.html"),
    ] {
        std::fs::copy(work.join(from), dir.join(name))
            .unwrap_or_else(|e| panic!("{}: {e}", work.join(from).display()));
    }
    let chrome = chromium();
    let t1 = Instant::now();
    let (mut speeds, mut most_runs) = (0, 0);
    for name in ["compare-v1.html", "discover.html", "diagnose.html"] {
        let html = std::fs::read_to_string(dir.join(name))
            .unwrap_or_else(|e| panic!("{}: {e}", dir.join(name).display()));
        assert_self_contained(name, &html);
        let s = check_polar_captions(name, &html);
        speeds = speeds.max(s);
        let afters = if name == "discover.html" {
            check_after_scale(name, &html)
        } else {
            0
        };
        let lay = layout(&chrome, dir, name);
        let polars = laid_out(name, &lay, "polar");
        assert_eq!(
            polars.len(),
            of_kind(&plots(&html), "polar").len(),
            "{name}: polar plots laid out"
        );
        check_polars(name, &polars);
        let runs = check_trace_colours(name, &polars);
        most_runs = most_runs.max(runs);
        let png = screenshot(&chrome, dir, &format!("shot-{name}"), &dir.join(name));
        // (An empty page of this size is a PNG of a few kB; these reports' are hundreds.)
        assert!(
            png.len() > 100_000,
            "{name}: the screenshot looks empty ({} bytes)",
            png.len()
        );
        eprintln!(
            "demo {name}: {} polar plot(s) ({afters} after), up to {runs} runs and {s} speeds in one, each its own colour; screenshot {} kB",
            polars.len(),
            png.len() / 1000
        );
    }
    // A palette of six would repeat past six runs: the most runs in one plot outnumber it.
    assert!(
        most_runs > 6,
        "the demo's reports draw at most {most_runs} runs in one plot ({speeds} speeds): the palette is not tested past six"
    );
    eprintln!(
        "demo reports rendered in {:.1} s",
        t1.elapsed().as_secs_f64()
    );
}
