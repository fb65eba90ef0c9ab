//! Files the CLI writes, and what it prints: nothing is ever lost.
//!
//! * [`AtomicOutput`]: an output file is written to `<name>.tmp-<pid>` in the same folder and
//!   renamed over the final name by [`AtomicOutput::commit`] once it is complete; dropped
//!   without a commit (an error, a panic), the temporary file is removed and whatever had the
//!   final name before is untouched. Creating it early checks that the folder is writable
//!   before any work is done. The temporary file is created exclusively (`O_CREAT|O_EXCL`,
//!   which never follows a symlink: a link planted under that name is left alone and another
//!   name taken) and written through the handle that created it, never reopened by name.
//! * An existing file is never replaced unless asked: an output flag (`--out`, `--report`, …)
//!   naming a file that exists is refused before any work, unless `--force` (or
//!   `SCANCORR_FORCE=1` in the environment) is given. `-` names standard output for text
//!   outputs (a report, a calibration, a CSV): the output is written there once complete, and
//!   what the command would print goes to stderr instead; a bag (written with seeks) refuses
//!   it.
//! * [`refuse_same_file`]: an output that is one of the command's inputs (the same path, or
//!   the same file through a symlink or a hard link) is refused before anything is written.
//! * [`csv_text`], [`header_name`], [`one_line`]: text from a bag or a document put into a
//!   CSV cell (quoted per RFC 4180, a formula neutralised), a CSV header (sanitised) or a
//!   comment line (control characters escaped).
//! * [`private_dir`]: a fresh folder of our own for a tool's scratch files.
//! * [`outln!`]: printing to stdout that turns a closed pipe (`scancorr … | head`) into a
//!   quiet exit instead of a panic.

use anyhow::{bail, Context, Result};
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

static FORCE: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);
static STDOUT_TAKEN: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// `--force`: outputs may replace existing files (also `SCANCORR_FORCE=1`).
pub fn set_force(on: bool) {
    FORCE.store(on, std::sync::atomic::Ordering::Relaxed);
}

fn force() -> bool {
    FORCE.load(std::sync::atomic::Ordering::Relaxed)
        || std::env::var("SCANCORR_FORCE").is_ok_and(|v| v == "1")
}

/// Whether an output goes to standard output (`--out -`): then what the command prints goes
/// to stderr.
pub fn stdout_taken() -> bool {
    STDOUT_TAKEN.load(std::sync::atomic::Ordering::Relaxed)
}

/// An output file written under a temporary name and renamed when complete.
pub struct AtomicOutput {
    /// The name the user gave (for messages).
    shown: PathBuf,
    /// Where the file lands on commit (the target of a symlink the user named).
    dest: PathBuf,
    /// The temporary file in the same folder (the output itself when `direct`).
    tmp: PathBuf,
    /// Written in place: not a regular file (`/dev/null`, a FIFO), which cannot be replaced.
    direct: bool,
    /// The temporary file, as created (`None` when `direct`).
    file: Option<fs::File>,
    committed: bool,
    /// `-`: standard output; the content, written there on commit.
    stdout: Option<std::sync::Mutex<Vec<u8>>>,
}

impl AtomicOutput {
    /// [`AtomicOutput::new`] for an optional output flag (`None`: not asked for).
    pub fn optional(flag: &str, path: Option<&Path>) -> Result<Option<AtomicOutput>> {
        path.map(|p| AtomicOutput::new(flag, p)).transpose()
    }

    /// Prepares `path` (named `flag` in messages, e.g. `--out`): refuses a folder, creates the
    /// temporary file next to it (so a missing or read-only folder fails now).
    pub fn new(flag: &str, path: &Path) -> Result<AtomicOutput> {
        if path.as_os_str().is_empty() {
            bail!("{flag}: an empty file name");
        }
        if path.as_os_str() == "-" {
            if STDOUT_TAKEN.swap(true, std::sync::atomic::Ordering::Relaxed) {
                bail!("{flag} -: standard output is already another output's");
            }
            return Ok(AtomicOutput {
                shown: PathBuf::from("standard output"),
                dest: path.to_path_buf(),
                tmp: path.to_path_buf(),
                direct: true,
                file: None,
                committed: false,
                stdout: Some(Default::default()),
            });
        }
        // A device or a pipe (`--out /dev/null`) is written in place, never replaced.
        if let Ok(m) = fs::metadata(path) {
            if !m.is_file() && !m.is_dir() {
                return Ok(AtomicOutput {
                    shown: path.to_path_buf(),
                    dest: path.to_path_buf(),
                    tmp: path.to_path_buf(),
                    direct: true,
                    file: None,
                    committed: false,
                    stdout: None,
                });
            }
            // A file the user named by a flag is replaced only when asked to.
            if m.is_file() && flag.starts_with("--") && !force() {
                bail!(
                    "{flag} {}: the file exists; give --force to replace it, or choose another name",
                    path.display()
                );
            }
        }
        // Writing through a symlink updates the file it points to, as `>` would.
        let dest = match fs::symlink_metadata(path) {
            Ok(m) if m.file_type().is_symlink() => fs::canonicalize(path).unwrap_or(path.into()),
            _ => path.to_path_buf(),
        };
        if dest.is_dir() {
            bail!("{flag} {}: is a folder, not a file", path.display());
        }
        let name = dest
            .file_name()
            .with_context(|| format!("{flag} {}: not a file name", path.display()))?;
        let (tmp, file) = create_exclusive(&dest, name).with_context(|| {
            format!(
                "{flag} {}: cannot write in {}",
                path.display(),
                folder_of(&dest).display()
            )
        })?;
        Ok(AtomicOutput {
            shown: path.to_path_buf(),
            dest,
            tmp,
            direct: false,
            file: Some(file),
            committed: false,
            stdout: None,
        })
    }

    /// The temporary file (to read back what was written; write through [`Self::file`]).
    pub fn path(&self) -> &Path {
        &self.tmp
    }

    /// A handle to write the output through: the temporary file as it was created (empty,
    /// unless written already), or the device or pipe itself when written in place.
    pub fn file(&self) -> Result<fs::File> {
        if self.stdout.is_some() {
            bail!("`-` (standard output) is for text outputs; this one is written with seeks: give a file name");
        }
        match &self.file {
            Some(f) => f.try_clone(),
            None => fs::OpenOptions::new().write(true).open(&self.tmp),
        }
        .with_context(|| format!("writing {}", self.shown.display()))
    }

    /// [`Self::file`] for an output written from start to end (text): with `-`, standard
    /// output itself.
    pub fn stream(&self) -> Result<fs::File> {
        if self.stdout.is_some() {
            use std::os::fd::AsFd;
            let fd = std::io::stdout()
                .as_fd()
                .try_clone_to_owned()
                .context("writing to standard output")?;
            return Ok(fs::File::from(fd));
        }
        self.file()
    }

    /// The name the user gave.
    pub fn shown(&self) -> &Path {
        &self.shown
    }

    /// Writes `bytes` as the whole content (to the temporary file).
    pub fn write_all(&self, bytes: impl AsRef<[u8]>) -> Result<()> {
        use std::io::{Seek, SeekFrom};
        let context = || format!("writing {}", self.shown.display());
        if let Some(buf) = &self.stdout {
            let mut b = buf.lock().unwrap_or_else(|e| e.into_inner());
            b.clear();
            b.extend_from_slice(bytes.as_ref());
            return Ok(());
        }
        match &self.file {
            Some(f) => {
                let mut f = f;
                f.set_len(0).with_context(context)?;
                f.seek(SeekFrom::Start(0)).with_context(context)?;
                f.write_all(bytes.as_ref()).with_context(context)
            }
            None => fs::write(&self.tmp, bytes).with_context(context),
        }
    }

    /// Makes the file complete: flushed to disk and renamed over the final name (keeping the
    /// permissions of a file it replaces).
    pub fn commit(mut self) -> Result<()> {
        if let Some(buf) = self.stdout.take() {
            self.committed = true;
            let b = buf.into_inner().unwrap_or_else(|e| e.into_inner());
            let mut out = std::io::stdout().lock();
            return match out.write_all(&b).and_then(|_| out.flush()) {
                Ok(()) => Ok(()),
                Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Err(StdoutClosed.into()),
                Err(e) => Err(anyhow::Error::new(e).context("writing to standard output")),
            };
        }
        if self.direct {
            self.committed = true;
            return Ok(());
        }
        let f = self
            .file
            .take()
            .with_context(|| format!("writing {}", self.shown.display()))?;
        f.sync_all()
            .with_context(|| format!("writing {}", self.shown.display()))?;
        if let Ok(old) = fs::metadata(&self.dest) {
            let _ = f.set_permissions(old.permissions());
        }
        drop(f);
        fs::rename(&self.tmp, &self.dest)
            .with_context(|| format!("writing {}", self.shown.display()))?;
        self.committed = true;
        Ok(())
    }
}

impl Drop for AtomicOutput {
    fn drop(&mut self) {
        if !self.committed && !self.direct {
            let _ = fs::remove_file(&self.tmp);
        }
    }
}

/// Commits every output (after all of them are complete).
pub fn commit_all(outs: impl IntoIterator<Item = Option<AtomicOutput>>) -> Result<()> {
    for o in outs.into_iter().flatten() {
        o.commit()?;
    }
    Ok(())
}

/// Writes a whole file atomically (`flag` names it in messages).
pub fn write_file(flag: &str, path: &Path, bytes: impl AsRef<[u8]>) -> Result<()> {
    let o = AtomicOutput::new(flag, path)?;
    o.write_all(bytes)?;
    o.commit()
}

/// Creates the temporary file for `dest` exclusively: `<name>.tmp-<pid>`, or when something
/// (a stale file, a planted symlink) already has that name, `<name>.tmp-<pid>-<n>`; whatever
/// had the name is left as it was. `create_new` is `O_CREAT|O_EXCL`, which fails on an
/// existing name even when it is a symlink (dangling or not) instead of following it.
fn create_exclusive(dest: &Path, name: &std::ffi::OsStr) -> std::io::Result<(PathBuf, fs::File)> {
    let pid = std::process::id();
    let mut last = None;
    for n in 0..64 {
        let mut tmp_name = name.to_os_string();
        if n == 0 {
            tmp_name.push(format!(".tmp-{pid}"));
        } else {
            tmp_name.push(format!(".tmp-{pid}-{n}"));
        }
        let tmp = dest.with_file_name(tmp_name);
        match fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&tmp)
        {
            Ok(f) => return Ok((tmp, f)),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => last = Some(e),
            Err(e) => return Err(e),
        }
    }
    Err(last.unwrap_or_else(|| std::io::Error::other("no free temporary name")))
}

/// Creates a fresh folder of our own (mode 0700) named `<prefix>-<pid>` in the system's
/// temporary folder, or `<prefix>-<pid>-<n>` when that name is taken: a folder someone else
/// made in advance (with symlinks in it) is never used.
pub fn private_dir(prefix: &str) -> Result<PathBuf> {
    let base = std::env::temp_dir();
    let pid = std::process::id();
    for n in 0..64 {
        let d = base.join(if n == 0 {
            format!("{prefix}-{pid}")
        } else {
            format!("{prefix}-{pid}-{n}")
        });
        let mut b = fs::DirBuilder::new();
        #[cfg(unix)]
        {
            use std::os::unix::fs::DirBuilderExt;
            b.mode(0o700);
        }
        match b.create(&d) {
            Ok(()) => return Ok(d),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            Err(e) => {
                return Err(anyhow::Error::new(e).context(format!("creating {}", d.display())))
            }
        }
    }
    bail!("no free folder name {prefix}-{pid}-… in {}", base.display())
}

/// Removes a folder, with what is in it, when dropped.
pub struct RemoveDir(pub PathBuf);

impl Drop for RemoveDir {
    fn drop(&mut self) {
        let _ = fs::remove_dir_all(&self.0);
    }
}

fn folder_of(p: &Path) -> PathBuf {
    match p.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// The absolute, symlink-free form of a path that may not exist yet: its longest existing
/// ancestor resolved, the rest appended (`.` dropped, `..` taken lexically: nothing below a
/// missing folder can be a symlink).
fn resolved(p: &Path) -> Option<PathBuf> {
    use std::path::Component;
    if let Ok(c) = fs::canonicalize(p) {
        return Some(c);
    }
    let abs = if p.is_absolute() {
        p.to_path_buf()
    } else {
        std::env::current_dir().ok()?.join(p)
    };
    let parts: Vec<Component> = abs.components().collect();
    for i in (1..parts.len()).rev() {
        let Ok(mut out) = fs::canonicalize(parts[..i].iter().collect::<PathBuf>()) else {
            continue;
        };
        for c in &parts[i..] {
            match c {
                Component::ParentDir => {
                    out.pop();
                }
                Component::Normal(n) => out.push(n),
                _ => {}
            }
        }
        return Some(out);
    }
    None
}

/// What a path names, for comparing outputs with inputs: an existing file's device and inode
/// (so the same file through a symlink or a hard link compares equal), otherwise the place it
/// would be created at.
#[derive(PartialEq, Eq)]
enum FileId {
    Inode(u64, u64),
    Place(PathBuf),
}

fn file_id(p: &Path) -> FileId {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        if let Ok(m) = fs::metadata(p) {
            return FileId::Inode(m.dev(), m.ino());
        }
    }
    FileId::Place(resolved(p).unwrap_or_else(|| p.to_path_buf()))
}

/// Whether `a` and `b` name the same file: the same resolved path, or (when both exist) the
/// same device and inode (a hard link).
#[cfg(test)]
fn same_file(a: &Path, b: &Path) -> bool {
    file_id(a) == file_id(b)
}

/// Refuses an output that is one of the inputs, or the same file as another output.
/// `outputs` and `inputs` are (flag, path) pairs, e.g. `("--out", out)`, `("--bag", bag)`.
pub fn refuse_same_file(outputs: &[(&str, &Path)], inputs: &[(&str, &Path)]) -> Result<()> {
    let out_ids: Vec<FileId> = outputs.iter().map(|(_, p)| file_id(p)).collect();
    let in_ids: Vec<FileId> = inputs.iter().map(|(_, p)| file_id(p)).collect();
    for (i, (oflag, out)) in outputs.iter().enumerate() {
        for (j, (iflag, inp)) in inputs.iter().enumerate() {
            if out_ids[i] == in_ids[j] {
                bail!(
                    "{oflag} {} is the same file as the input {iflag} {}: writing it would destroy the input; choose another output file",
                    out.display(),
                    inp.display()
                );
            }
        }
        for (k, (oflag2, out2)) in outputs.iter().enumerate().skip(i + 1) {
            if out_ids[i] == out_ids[k] {
                bail!(
                    "{oflag} {} and {oflag2} {} are the same file: one would overwrite the other",
                    out.display(),
                    out2.display()
                );
            }
        }
    }
    Ok(())
}

/// A text field as one CSV cell (RFC 4180): quoted when it holds a comma, a quote or a line
/// break (quotes doubled); a cell a spreadsheet would take for a formula (starting with `=`,
/// `+`, `-`, `@`, a tab or a carriage return) is prefixed with `'` and quoted, as OWASP
/// recommends against CSV injection. Only for text (names, ids): numbers are written as
/// they are.
pub fn csv_text(s: &str) -> String {
    let formula = s.starts_with(['=', '+', '-', '@', '\t', '\r']);
    if formula {
        format!("\"'{}\"", s.replace('"', "\"\""))
    } else if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

/// A name (an effect id, a machine) made fit for a CSV header: every control character,
/// comma, quote and semicolon replaced by `_`. Put it through [`csv_text`] as well.
pub fn header_name(s: &str) -> String {
    s.chars()
        .map(|c| {
            if c.is_control() || matches!(c, ',' | '"' | ';') {
                '_'
            } else {
                c
            }
        })
        .collect()
}

/// Text (a file name, a machine) made fit for one line of a comment header: control
/// characters (line breaks above all) escaped as `\n`, `\u{1b}`, ….
pub fn one_line(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        if c.is_control() {
            out.extend(c.escape_default());
        } else {
            out.push(c);
        }
    }
    out
}

/// stdout was closed by its reader (`scancorr … | head`): the command stops quietly.
#[derive(Debug)]
pub struct StdoutClosed;

impl std::fmt::Display for StdoutClosed {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("stdout closed")
    }
}

impl std::error::Error for StdoutClosed {}

/// Writes to stdout; a closed pipe becomes [`StdoutClosed`], another failure an error. When an
/// output is standard output (`--out -`), to stderr instead.
pub fn write_stdout(args: std::fmt::Arguments<'_>) -> Result<()> {
    if stdout_taken() {
        let mut err = std::io::stderr().lock();
        return err
            .write_fmt(args)
            .and_then(|_| err.flush())
            .context("writing to stderr");
    }
    let mut out = std::io::stdout().lock();
    match out.write_fmt(args).and_then(|_| out.flush()) {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Err(StdoutClosed.into()),
        Err(e) => Err(anyhow::Error::new(e).context("writing to stdout")),
    }
}

/// `println!` that returns a `Result` (use with `?`): a closed stdout stops the command
/// quietly instead of panicking.
macro_rules! outln {
    () => { $crate::shared::output::write_stdout(format_args!("\n")) };
    ($($t:tt)*) => { $crate::shared::output::write_stdout(format_args!("{}\n", format_args!($($t)*))) };
}

/// `print!` that returns a `Result` (see [`outln!`]).
macro_rules! out {
    ($($t:tt)*) => { $crate::shared::output::write_stdout(format_args!($($t)*)) };
}

/// Checks a machine id from a flag (`--machine`) against the name grammar.
pub fn check_machine(flag: &str, m: &str) -> Result<()> {
    scancorr_proto::names::check_machine(m).map_err(|e| anyhow::anyhow!("{flag}: {e}"))
}

/// Checks a key-expression prefix from `--prefix`.
pub fn check_prefix(p: &str) -> Result<()> {
    scancorr_proto::names::check_prefix(p).map_err(|e| anyhow::anyhow!("--prefix: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uncommitted_output_leaves_the_old_file() {
        let d = std::env::temp_dir().join(format!("scancorr-output-{}", std::process::id()));
        fs::create_dir_all(&d).unwrap();
        let f = d.join("a.json");
        fs::write(&f, "old").unwrap();
        {
            let o = AtomicOutput::new("the test's output", &f).unwrap();
            o.write_all("new").unwrap();
            assert_eq!(fs::read_to_string(&f).unwrap(), "old");
        }
        assert_eq!(fs::read_to_string(&f).unwrap(), "old");
        assert_eq!(fs::read_dir(&d).unwrap().count(), 1, "temporary removed");
        let o = AtomicOutput::new("the test's output", &f).unwrap();
        o.write_all("new").unwrap();
        o.commit().unwrap();
        assert_eq!(fs::read_to_string(&f).unwrap(), "new");
        assert_eq!(fs::read_dir(&d).unwrap().count(), 1);
        // Same file through a hard link and a symlink; another file is fine.
        let h = d.join("h.json");
        fs::hard_link(&f, &h).unwrap();
        #[cfg(unix)]
        std::os::unix::fs::symlink(&f, d.join("s.json")).unwrap();
        assert!(same_file(&f, &h));
        #[cfg(unix)]
        assert!(same_file(&d.join("s.json"), &f));
        assert!(same_file(&d.join("./a.json"), &f));
        assert!(!same_file(&d.join("b.json"), &f));
        assert!(refuse_same_file(&[("--out", &h)], &[("--calib", &f)]).is_err());
        assert!(refuse_same_file(&[("--out", &d.join("b.json"))], &[("--calib", &f)]).is_ok());
        // Paths below a folder that does not exist yet compare by where they would be.
        assert!(same_file(
            &d.join("new/x/../a.json"),
            &d.join("new/./a.json")
        ));
        assert!(!same_file(&d.join("new/a.json"), &d.join("new/b.json")));
        fs::remove_dir_all(&d).ok();
    }

    #[cfg(unix)]
    #[test]
    fn a_planted_temporary_symlink_is_never_followed() {
        let d = std::env::temp_dir().join(format!("scancorr-output-link-{}", std::process::id()));
        let _ = fs::remove_dir_all(&d);
        fs::create_dir_all(&d).unwrap();
        let victim = d.join("victim.txt");
        fs::write(&victim, "precious").unwrap();
        let out = d.join("out.json");
        let planted = d.join(format!("out.json.tmp-{}", std::process::id()));
        std::os::unix::fs::symlink(&victim, &planted).unwrap();
        // A dangling one as well: O_EXCL refuses it too (it would create the target).
        let dangling = d.join(format!("out.json.tmp-{}-1", std::process::id()));
        std::os::unix::fs::symlink(d.join("created.txt"), &dangling).unwrap();
        let o = AtomicOutput::new("--out", &out).unwrap();
        assert_ne!(o.path(), planted);
        assert_ne!(o.path(), dangling);
        o.write_all("new").unwrap();
        o.commit().unwrap();
        assert_eq!(fs::read_to_string(&victim).unwrap(), "precious");
        assert!(!d.join("created.txt").exists());
        assert_eq!(fs::read_to_string(&out).unwrap(), "new");
        assert!(!fs::symlink_metadata(&out).unwrap().file_type().is_symlink());
        fs::remove_dir_all(&d).ok();
    }

    #[test]
    fn csv_cells_and_names() {
        assert_eq!(csv_text("ring"), "ring");
        assert_eq!(csv_text("a,b"), "\"a,b\"");
        assert_eq!(
            csv_text("=HYPERLINK(\"http://x\",\"y\")"),
            "\"'=HYPERLINK(\"\"http://x\"\",\"\"y\"\")\""
        );
        for f in ["+1", "-1", "@SUM(A1)", "\tx", "\rx"] {
            assert!(csv_text(f).starts_with("\"'"), "{f:?}");
        }
        assert_eq!(header_name("a,b\"c\nd;e\u{7}"), "a_b_c_d_e_");
        assert_eq!(one_line("a\nb\r\u{1b}"), "a\\nb\\r\\u{1b}");
    }
}

/// A one-line progress report on stderr for long work, redrawn in place at most every 0.25 s,
/// only when stderr is a terminal (a log or a pipe gets the closing line alone).
pub struct Progress {
    tty: bool,
    last: Option<std::time::Instant>,
    shown: bool,
}

impl Progress {
    /// A progress line (drawn only on a terminal).
    pub fn new() -> Progress {
        use std::io::IsTerminal;
        Progress {
            tty: std::io::stderr().is_terminal(),
            last: None,
            shown: false,
        }
    }
    /// Redraws the line with `msg()` when it is due (`msg` is called only then).
    pub fn tick(&mut self, msg: impl FnOnce() -> String) {
        if !self.tty || self.last.is_some_and(|t| t.elapsed().as_millis() < 250) {
            return;
        }
        self.last = Some(std::time::Instant::now());
        let mut e = std::io::stderr().lock();
        let _ = write!(e, "\r\x1b[2K{}", msg());
        let _ = e.flush();
        self.shown = true;
    }
    /// Clears the line.
    pub fn finish(&mut self) {
        if self.shown {
            let mut e = std::io::stderr().lock();
            let _ = write!(e, "\r\x1b[2K");
            let _ = e.flush();
            self.shown = false;
        }
    }
}

impl Default for Progress {
    fn default() -> Self {
        Progress::new()
    }
}

impl Drop for Progress {
    fn drop(&mut self) {
        self.finish();
    }
}

/// When the command started (the first call to [`stage`] or [`started`]).
static STARTED: std::sync::OnceLock<std::time::Instant> = std::sync::OnceLock::new();

/// Marks the command's start (for [`stage`]'s elapsed times).
pub fn started() {
    STARTED.get_or_init(std::time::Instant::now);
}

/// Says which stage long work has reached — `[  3.2 s] fitting …` — on stderr when it is a
/// terminal; a log or a pipe gets nothing (the result says what was done).
pub fn stage(msg: &str) {
    use std::io::IsTerminal;
    let t0 = *STARTED.get_or_init(std::time::Instant::now);
    if std::io::stderr().is_terminal() {
        eprintln!("[{:>6.1} s] {msg}", t0.elapsed().as_secs_f64());
    }
}

/// Refuses outputs that are inputs (or each other), then prepares every output (a temporary
/// file next to each, so an unwritable folder fails before the work).
pub(crate) fn outputs<const N: usize>(
    outs: [(&str, Option<&Path>); N],
    inputs: &[(&str, &Path)],
) -> Result<[Option<AtomicOutput>; N]> {
    let named: Vec<(&str, &Path)> = outs
        .iter()
        .filter_map(|(f, p)| p.map(|p| (*f, p)))
        .collect();
    refuse_same_file(&named, inputs)?;
    crate::shared::provenance::register(inputs);
    let mut v = Vec::with_capacity(N);
    for (f, p) in outs {
        v.push(AtomicOutput::optional(f, p)?);
    }
    Ok(v.try_into().unwrap_or_else(|_| unreachable!("N outputs")))
}

/// Writes `text` to a prepared output; an HTML report gets the provenance block.
pub(crate) fn put(o: &Option<AtomicOutput>, text: impl AsRef<[u8]>) -> Result<()> {
    if let Some(o) = o {
        let t = text.as_ref();
        if t.starts_with(b"<!doctype html>") {
            let doc = String::from_utf8_lossy(t);
            o.write_all(crate::shared::provenance::insert(
                &doc,
                &crate::shared::provenance::now_rfc3339(),
            ))?;
        } else {
            o.write_all(t)?;
        }
    }
    Ok(())
}
