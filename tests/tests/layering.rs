//! The core is pure: no async runtime, no network stack anywhere in its dependency tree.

use std::process::Command;

#[test]
fn core_depends_on_no_tokio_and_no_zenoh() {
    let cargo = env!("CARGO");
    let root = concat!(env!("CARGO_MANIFEST_DIR"), "/..");
    let out = Command::new(cargo)
        .args([
            "tree",
            "-p",
            "scancorr-core",
            "-e",
            "normal,build",
            "--prefix",
            "none",
            "--offline",
        ])
        .current_dir(root)
        .output()
        .expect("cargo tree runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let tree = String::from_utf8_lossy(&out.stdout);
    assert!(tree.contains("scancorr-core"), "{tree}");
    assert!(tree.contains("nalgebra"), "the tree is real: {tree}");
    for banned in ["tokio", "zenoh", "async-std", "mio"] {
        assert!(
            !tree
                .lines()
                .any(|l| l.split_whitespace().next() == Some(banned)),
            "scancorr-core depends on {banned}:\n{tree}"
        );
    }
}

#[test]
fn core_forbids_unsafe_code() {
    let lib = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../service/core/src/lib.rs"
    ))
    .unwrap();
    assert!(lib.contains("#![forbid(unsafe_code)]"));
}

/// The simulator describes its machine with physics of its own: it may use the calibration's
/// document types (to write the true calibration), never the corrector's formulas — no
/// effect's hot path, no corrector, estimator, judgement, synthesis or discretised model.
#[test]
fn the_simulator_never_calls_the_correctors_formulas() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../clients/sim/src");
    let forbidden = [
        ".correction(",
        ".regressors(",
        "Corrector",
        "synthesize",
        "estimator",
        "judge",
        "Discrete",
        "effects::Effect",
        "BuiltEffect",
        ".build(",
        "osculating_arc",
        "machine_from_probe",
    ];
    let mut files = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().and_then(|e| e.to_str()) != Some("rs") {
            continue;
        }
        files += 1;
        let text = std::fs::read_to_string(&path).unwrap();
        for (n, line) in text.lines().enumerate() {
            let code = line.split("//").next().unwrap_or("");
            for f in forbidden {
                assert!(
                    !code.contains(f),
                    "{}:{}: the simulator uses `{f}` of the corrector: {line}",
                    path.display(),
                    n + 1
                );
            }
        }
    }
    assert!(files >= 4, "read {files} simulator sources");
}

/// Every file of a crate's `src` as a module path (`lab/select.rs` → `lab::select`,
/// `lab/mod.rs` → `lab`, `lib.rs`/`main.rs` → the root).
fn modules(src: &std::path::Path) -> Vec<(Vec<String>, String)> {
    let mut out = vec![];
    let mut stack = vec![src.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                if path.file_name().is_some_and(|n| n != "bin") {
                    stack.push(path);
                }
                continue;
            }
            if path.extension().and_then(|e| e.to_str()) != Some("rs") {
                continue;
            }
            let rel = path.strip_prefix(src).unwrap();
            let mut segs: Vec<String> = rel
                .iter()
                .map(|s| s.to_string_lossy().trim_end_matches(".rs").to_string())
                .collect();
            if matches!(segs.last().map(String::as_str), Some("mod")) {
                segs.pop();
            }
            if segs.len() == 1 && (segs[0] == "lib" || segs[0] == "main") {
                segs.clear();
            }
            let text = std::fs::read_to_string(&path).unwrap();
            // A file's unit tests are not part of its dependencies.
            // and a doc comment's link is not a dependency.
            let code: String = text
                .split("#[cfg(test)]")
                .next()
                .unwrap_or("")
                .lines()
                .map(|l| match l.find("//") {
                    Some(k) => &l[..k],
                    None => l,
                })
                .collect::<Vec<_>>()
                .join("\n");
            out.push((segs, code));
        }
    }
    out
}

/// Expands `a::{b, c::{d, e}}` into `a::b`, `a::c::d`, `a::c::e`.
fn expand(path: &str) -> Vec<String> {
    let path: String = path.chars().filter(|c| !c.is_whitespace()).collect();
    let Some(open) = path.find('{') else {
        return vec![path];
    };
    let (head, rest) = path.split_at(open);
    let inner = &rest[1..rest.rfind('}').unwrap_or(rest.len())];
    let mut parts = vec![];
    let (mut depth, mut start) = (0, 0);
    for (i, c) in inner.char_indices() {
        match c {
            '{' => depth += 1,
            '}' => depth -= 1,
            ',' if depth == 0 => {
                parts.push(&inner[start..i]);
                start = i + 1;
            }
            _ => {}
        }
    }
    parts.push(&inner[start..]);
    parts
        .into_iter()
        .filter(|p| !p.is_empty())
        .flat_map(|p| expand(&format!("{head}{p}")))
        .collect()
}

/// The module files each file refers to through `crate::…`, `super::…` or `self::…` paths
/// (in `use` trees and inline), resolved to the longest known module; a file's own
/// ancestors (the `mod.rs` or crate root that declares it) are not counted.
fn edges(
    mods: &[(Vec<String>, String)],
    is_mod_rs: &dyn Fn(&[String]) -> bool,
) -> Vec<(usize, usize)> {
    let known: std::collections::HashMap<&[String], usize> = mods
        .iter()
        .enumerate()
        .map(|(i, (p, _))| (p.as_slice(), i))
        .collect();
    let mut out = vec![];
    for (i, (me, code)) in mods.iter().enumerate() {
        let mut paths = vec![];
        for stmt in code.split(';') {
            let s = stmt.trim_start();
            let s = s
                .strip_prefix("pub(crate) ")
                .or(s.strip_prefix("pub "))
                .unwrap_or(s);
            if let Some(u) = s.trim_start().strip_prefix("use ") {
                paths.extend(expand(u));
            }
        }
        // A `mod.rs` or crate root names its children by bare paths (`child::Item`).
        if is_mod_rs(me) {
            for (child, _) in mods
                .iter()
                .filter(|(p, _)| p.len() == me.len() + 1 && p.starts_with(me))
            {
                let name = format!("{}::", child.last().unwrap());
                for (k, _) in code.match_indices(&name) {
                    let before = code[..k].chars().next_back();
                    if !before.is_some_and(|c| c.is_alphanumeric() || c == '_' || c == ':') {
                        paths.push(format!(
                            "self::{}",
                            &code[k..]
                                .split(|c: char| !(c.is_alphanumeric() || c == '_' || c == ':'))
                                .next()
                                .unwrap_or("")
                        ));
                    }
                }
            }
        }
        for (k, _) in code
            .match_indices("crate::")
            .chain(code.match_indices("super::"))
        {
            let tail: String = code[k..]
                .chars()
                .take_while(|c| c.is_alphanumeric() || *c == '_' || *c == ':')
                .collect();
            paths.push(tail);
        }
        for p in paths {
            let segs: Vec<&str> = p.split("::").filter(|s| !s.is_empty()).collect();
            let mut base: Vec<String> = match segs.first() {
                Some(&"crate") => vec![],
                Some(&"super") | Some(&"self") => {
                    let mut b = me.clone();
                    if !is_mod_rs(me) || segs[0] == "super" {
                        b.pop();
                    }
                    b
                }
                _ => continue,
            };
            let mut rest = &segs[1..];
            while rest.first() == Some(&"super") {
                base.pop();
                rest = &rest[1..];
            }
            let mut target = None;
            let mut cur = base.clone();
            if let Some(&j) = known.get(cur.as_slice()) {
                target = Some(j);
            }
            for s in rest {
                cur.push(s.to_string());
                match known.get(cur.as_slice()) {
                    Some(&j) => target = Some(j),
                    None => break,
                }
            }
            if let Some(j) = target {
                let ancestor = mods[j].0.len() < me.len() && me.starts_with(&mods[j].0);
                if j != i && !ancestor {
                    out.push((i, j));
                }
            }
        }
    }
    out.sort();
    out.dedup();
    out
}

/// No two source files of a crate depend on each other, directly or round a longer circle
/// (a shared type lives in its own room, below both users).
#[test]
fn no_circle_between_the_files_of_a_crate() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let mut circles = vec![];
    let mut files = 0;
    for krate in [
        "service/core",
        "service/scancorrd",
        "clients/scancorr",
        "clients/sim",
        "clients/bag",
    ] {
        let src = root.join(krate).join("src");
        let mods = modules(&src);
        files += mods.len();
        let mod_rs: std::collections::HashSet<Vec<String>> = mods
            .iter()
            .map(|(p, _)| p.clone())
            .filter(|p| p.is_empty() || src.join(p.join("/")).join("mod.rs").exists())
            .collect();
        let e = edges(&mods, &|p| mod_rs.contains(p));
        // Tarjan's strongly connected components.
        let n = mods.len();
        let adj: Vec<Vec<usize>> = (0..n)
            .map(|i| e.iter().filter(|(a, _)| *a == i).map(|(_, b)| *b).collect())
            .collect();
        let (mut index, mut low, mut on) = (vec![usize::MAX; n], vec![0; n], vec![false; n]);
        let (mut stack, mut next) = (vec![], 0);
        fn visit(
            v: usize,
            adj: &[Vec<usize>],
            st: (
                &mut Vec<usize>,
                &mut Vec<usize>,
                &mut Vec<bool>,
                &mut Vec<usize>,
                &mut usize,
            ),
            out: &mut Vec<Vec<usize>>,
        ) {
            let (index, low, on, stack, next) = st;
            index[v] = *next;
            low[v] = *next;
            *next += 1;
            stack.push(v);
            on[v] = true;
            for &w in &adj[v] {
                if index[w] == usize::MAX {
                    visit(
                        w,
                        adj,
                        (&mut *index, &mut *low, &mut *on, &mut *stack, &mut *next),
                        out,
                    );
                    low[v] = low[v].min(low[w]);
                } else if on[w] {
                    low[v] = low[v].min(index[w]);
                }
            }
            if low[v] == index[v] {
                let mut comp = vec![];
                while let Some(w) = stack.pop() {
                    on[w] = false;
                    comp.push(w);
                    if w == v {
                        break;
                    }
                }
                if comp.len() > 1 {
                    out.push(comp);
                }
            }
        }
        let mut comps = vec![];
        for v in 0..n {
            if index[v] == usize::MAX {
                visit(
                    v,
                    &adj,
                    (&mut index, &mut low, &mut on, &mut stack, &mut next),
                    &mut comps,
                );
            }
        }
        for c in comps {
            let names: Vec<String> = c
                .iter()
                .map(|&i| format!("{krate}/src/{}", mods[i].0.join("/")))
                .collect();
            let why: Vec<String> = e
                .iter()
                .filter(|(a, b)| c.contains(a) && c.contains(b))
                .map(|(a, b)| format!("{} → {}", mods[*a].0.join("::"), mods[*b].0.join("::")))
                .collect();
            circles.push(format!("{}\n    ({})", names.join(" ↔ "), why.join(", ")));
        }
    }
    assert!(files > 100, "the walk found the sources ({files} files)");
    assert!(
        circles.is_empty(),
        "files that depend on each other:\n{}",
        circles.join("\n")
    );
}

/// The CLI by command family: no command's module uses another family's (what they share
/// lives in `shared/`), and neither `shared/` nor `report/` uses a command.
#[test]
fn no_cli_command_imports_another() {
    let src = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../clients/scancorr/src");
    let mods = modules(&src);
    assert!(
        mods.len() > 30,
        "the walk found the CLI ({} files)",
        mods.len()
    );
    let mut bad = vec![];
    for (path, code) in &mods {
        let family = match path.first().map(String::as_str) {
            Some("commands") => path.get(1).cloned(),
            Some("shared") | Some("report") => None,
            _ => continue,
        };
        for (k, _) in code.match_indices("commands::") {
            let other: String = code[k + "commands::".len()..]
                .chars()
                .take_while(|c| c.is_alphanumeric() || *c == '_')
                .collect();
            let ok = family.as_deref() == Some(other.as_str());
            if !ok {
                bad.push(format!("{} uses commands::{other}", path.join("/")));
            }
        }
    }
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

/// Every `.rs` file below `dir` with its text, passing over `target/`, `third_party/` (not
/// ours) and hidden folders.
fn rust_sources(dir: &std::path::Path) -> Vec<(std::path::PathBuf, String)> {
    let (mut out, mut stack) = (vec![], vec![dir.to_path_buf()]);
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).unwrap() {
            let path = entry.unwrap().path();
            let name = path.file_name().unwrap().to_string_lossy().to_string();
            if path.is_dir() {
                if !(name.starts_with('.') || name == "target" || name == "third_party") {
                    stack.push(path);
                }
            } else if name.ends_with(".rs") {
                let text = std::fs::read_to_string(&path).unwrap();
                out.push((path, text));
            }
        }
    }
    out
}

/// The `run`/`exec` functions of a file, each as (name, first line, length in lines): from
/// the `fn` line to the `}` at the same indentation (the sources are rustfmt-formatted); a
/// function whose end is not found is reported with length `usize::MAX`.
fn run_functions(text: &str) -> Vec<(String, usize, usize)> {
    let lines: Vec<&str> = text.lines().collect();
    let mut out = vec![];
    for (i, line) in lines.iter().enumerate() {
        let body = line.trim_start();
        let indent = &line[..line.len() - body.len()];
        let body = body
            .strip_prefix("pub ")
            .or_else(|| {
                body.strip_prefix("pub(")
                    .and_then(|b| b.split_once(") ").map(|(_, r)| r))
            })
            .unwrap_or(body);
        let Some(rest) = body.strip_prefix("fn ") else {
            continue;
        };
        let name: String = rest
            .chars()
            .take_while(|c| c.is_alphanumeric() || *c == '_')
            .collect();
        if name != "run" && name != "exec" {
            continue;
        }
        let close = format!("{indent}}}");
        let len = lines[i..]
            .iter()
            .position(|l| *l == close)
            .map_or(usize::MAX, |k| k + 1);
        out.push((name, i + 1, len));
    }
    out
}

/// Every command's `run`/`exec` (`clients/scancorr/src/commands/**`) is under 150 lines: the
/// arguments in, a call into the library, the printing out — the logic lives below.
#[test]
fn every_commands_run_is_under_150_lines() {
    let dir =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../clients/scancorr/src/commands");
    let (mut found, mut long) = (0, vec![]);
    for (path, text) in rust_sources(&dir) {
        let code = text.split("#[cfg(test)]").next().unwrap_or("");
        for (name, line, len) in run_functions(code) {
            found += 1;
            if len >= 150 {
                long.push(format!(
                    "{}:{line}: `fn {name}` is {} lines",
                    path.strip_prefix(&dir).unwrap().display(),
                    if len == usize::MAX {
                        "?".into()
                    } else {
                        len.to_string()
                    }
                ));
            }
        }
    }
    assert!(
        found >= 30,
        "the walk found the commands' run/exec ({found})"
    );
    assert!(
        long.is_empty(),
        "commands whose run/exec is 150 lines or more:\n{}",
        long.join("\n")
    );
}

/// Every Rust source of the workspace (all crates, their tests, benches, examples and the
/// fuzz targets; not `target/`, not `third_party/`, not generated code) over 1 000 lines opens
/// with a `//!` line naming the one concern it holds — a long file stays long only for a
/// reason it states, otherwise it is split. The test can only check that such a first line is
/// there (a `//!` line with words in it); whether it names a *single* concern is the
/// reviewer's to judge.
#[test]
fn every_file_over_1000_lines_names_its_concern_first() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let (mut files, mut bad) = (0, vec![]);
    for (path, text) in rust_sources(&root) {
        if text.lines().take(5).any(|l| l.contains("@generated")) {
            continue;
        }
        files += 1;
        let n = text.lines().count();
        let first = text.lines().next().unwrap_or("");
        let words = first
            .strip_prefix("//!")
            .map_or(0, |t| t.split_whitespace().count());
        if n > 1000 && words < 3 {
            bad.push(format!(
                "{} ({n} lines) opens with {first:?}",
                path.strip_prefix(&root).unwrap().display()
            ));
        }
    }
    assert!(
        files > 150,
        "the walk found the workspace's sources ({files} files)"
    );
    assert!(
        bad.is_empty(),
        "files over 1 000 lines that do not name their concern in a first `//!` line:\n{}",
        bad.join("\n")
    );
}
