//! The provenance block of every HTML report: when and by which tool it was made, from which
//! files (each with its size and SHA-256), for which machine and calibration version, and
//! which artifact certificates the bags name — so a report printed and filed months later
//! still says what it is a claim about.
//!
//! Every command declares its inputs once, when it prepares its outputs
//! ([`crate::shared::output::outputs`] calls [`register`]); a report written through
//! [`crate::shared::output::put`] gets the block inserted before its closing `</body>`.

use sha2::{Digest, Sha256};
use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

static INPUTS: Mutex<Vec<(String, PathBuf)>> = Mutex::new(Vec::new());

/// Declares the command's inputs (flag, path); repeated declarations are kept once.
pub fn register(inputs: &[(&str, &Path)]) {
    let mut v = INPUTS.lock().unwrap_or_else(|e| e.into_inner());
    for (f, p) in inputs {
        if !v.iter().any(|(g, q)| g == f && q == p) {
            v.push((f.to_string(), p.to_path_buf()));
        }
    }
}

fn sha256(p: &Path) -> std::io::Result<(u64, String)> {
    let mut f = std::fs::File::open(p)?;
    let mut h = Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    let mut n = 0u64;
    loop {
        let k = f.read(&mut buf)?;
        if k == 0 {
            break;
        }
        n += k as u64;
        h.update(&buf[..k]);
    }
    Ok((n, format!("{:x}", h.finalize())))
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// The block, as HTML.
pub fn html(generated: &str) -> String {
    let inputs = INPUTS.lock().unwrap_or_else(|e| e.into_inner()).clone();
    let mut rows = String::new();
    let mut machine_cal = vec![];
    let mut certificates = vec![];
    for (flag, p) in &inputs {
        let (size, hash) = if p.is_dir() {
            ("folder".to_string(), String::new())
        } else {
            match sha256(p) {
                Ok((n, h)) => (format!("{n} B"), h),
                Err(e) => (format!("unreadable: {e}"), String::new()),
            }
        };
        rows += &format!(
            "<tr><td>{}</td><td>{}</td><td>{}</td><td><code>{}</code></td></tr>",
            esc(flag),
            esc(&p.display().to_string()),
            esc(&size),
            hash
        );
        if flag == "--calib" {
            if let Some(v) = std::fs::read_to_string(p)
                .ok()
                .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
            {
                machine_cal.push(format!(
                    "machine {}, calibration version {}",
                    v["machine_id"].as_str().unwrap_or("?"),
                    v["version"]
                ));
            }
        }
        if flag == "--bag" || flag == "--validate" {
            let Ok(bag) = scancorr_bag::BagReader::open(p) else {
                continue;
            };
            // The program's features with their certificates, where the bag has the record.
            let program = bag
                .metadata()
                .iter()
                .find(|m| m.name == "scancorr.program")
                .and_then(|m| m.entries.get("json"))
                .and_then(|j| serde_json::from_str::<serde_json::Value>(j).ok());
            if let Some(features) = program.as_ref().and_then(|v| v["features"].as_array()) {
                let mut seen: Vec<String> = vec![];
                for f in features {
                    let what = match (
                        f["certificate_diameter_mm"].as_f64(),
                        f["nominal_diameter_mm"].as_f64(),
                    ) {
                        (Some(c), _) => format!(
                            "{} certified Ø{c} mm",
                            f["artifact"].as_str().unwrap_or("?")
                        ),
                        (None, Some(d)) if d > 0.0 => format!(
                            "{} nominal Ø{d} mm (no certificate)",
                            f["artifact"].as_str().unwrap_or("?")
                        ),
                        _ => format!("{} (no certificate)", f["artifact"].as_str().unwrap_or("?")),
                    };
                    if !seen.contains(&what) {
                        seen.push(what);
                    }
                }
                certificates.push(format!("{}: {}", p.display(), seen.join(", ")));
                continue;
            }
            if let Ok(Some(a)) = bag.artifact() {
                let what = match (a.certificate_mm, a.diameter_mm) {
                    (Some(c), _) => format!("{} certified {c} mm", a.kind.as_str()),
                    (None, Some(d)) => {
                        format!("{} nominal Ø{d} mm (no certificate)", a.kind.as_str())
                    }
                    _ => format!("{} (no certificate)", a.kind.as_str()),
                };
                let serial = a
                    .extra
                    .get("serial")
                    .map(|s| format!(", serial {s}"))
                    .unwrap_or_default();
                certificates.push(format!("{}: {what}{serial}", p.display()));
            }
        }
    }
    let command: Vec<String> = std::env::args().map(|a| esc(&a)).collect();
    format!(
        "<h2>Provenance</h2><table class=\"provenance\"><tr><td>generated</td><td colspan=\"3\">{}</td></tr>\
         <tr><td>tool</td><td colspan=\"3\">scancorr {}</td></tr>\
         <tr><td>command</td><td colspan=\"3\"><code>{}</code></td></tr>\
         <tr><td>calibration</td><td colspan=\"3\">{}</td></tr>\
         <tr><td>artifacts</td><td colspan=\"3\">{}</td></tr>\
         <tr><th>input</th><th>file</th><th>size</th><th>SHA-256</th></tr>{rows}</table>",
        esc(generated),
        env!("CARGO_PKG_VERSION"),
        command.join(" "),
        esc(&if machine_cal.is_empty() { "—".to_string() } else { machine_cal.join("; ") }),
        esc(&if certificates.is_empty() { "—".to_string() } else { certificates.join("; ") }),
    )
}

/// `html` with the block inserted before `</body>` (unchanged if it has none).
pub fn insert(html_doc: &str, generated: &str) -> String {
    match html_doc.rfind("</body>") {
        Some(i) => format!("{}{}{}", &html_doc[..i], html(generated), &html_doc[i..]),
        None => html_doc.to_string(),
    }
}

/// Now, RFC 3339 UTC: a report's date and a new version's `created`.
pub(crate) fn now_rfc3339() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0) as i64;
    scancorr_core::calib::rfc3339_utc(secs)
}
