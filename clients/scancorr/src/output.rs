//! Files the CLI writes, and what it prints: nothing is ever lost.
//!
//! * [`AtomicOutput`]: an output file is written to `<name>.tmp-<pid>` in the same folder and
//!   renamed over the final name by [`AtomicOutput::commit`] once it is complete; dropped
//!   without a commit (an error, a panic), the temporary file is removed and whatever had the
//!   final name before is untouched. Creating it early checks that the folder is writable
//!   before any work is done.
//! * [`refuse_same_file`]: an output that is one of the command's inputs (the same path, or
//!   the same file through a symlink or a hard link) is refused before anything is written.
//! * [`outln!`]: printing to stdout that turns a closed pipe (`scancorr … | head`) into a
//!   quiet exit instead of a panic.

use anyhow::{bail, Context, Result};
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

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
    committed: bool,
}

impl AtomicOutput {
    /// Prepares `path` (named `flag` in messages, e.g. `--out`): refuses a folder, creates the
    /// temporary file next to it (so a missing or read-only folder fails now).
    pub fn new(flag: &str, path: &Path) -> Result<AtomicOutput> {
        if path.as_os_str().is_empty() {
            bail!("{flag}: an empty file name");
        }
        // A device or a pipe (`--out /dev/null`) is written in place, never replaced.
        if let Ok(m) = fs::metadata(path) {
            if !m.is_file() && !m.is_dir() {
                return Ok(AtomicOutput {
                    shown: path.to_path_buf(),
                    dest: path.to_path_buf(),
                    tmp: path.to_path_buf(),
                    direct: true,
                    committed: false,
                });
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
        let mut tmp_name = name.to_os_string();
        tmp_name.push(format!(".tmp-{}", std::process::id()));
        let tmp = dest.with_file_name(tmp_name);
        fs::OpenOptions::new()
            .write(true)
            .create(true)
            .truncate(true)
            .open(&tmp)
            .with_context(|| {
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
            committed: false,
        })
    }

    /// The temporary file to write to.
    pub fn path(&self) -> &Path {
        &self.tmp
    }

    /// The name the user gave.
    pub fn shown(&self) -> &Path {
        &self.shown
    }

    /// Writes `bytes` as the whole content (to the temporary file).
    pub fn write_all(&self, bytes: impl AsRef<[u8]>) -> Result<()> {
        fs::write(&self.tmp, bytes).with_context(|| format!("writing {}", self.shown.display()))
    }

    /// Makes the file complete: flushed to disk and renamed over the final name (keeping the
    /// permissions of a file it replaces).
    pub fn commit(mut self) -> Result<()> {
        if self.direct {
            self.committed = true;
            return Ok(());
        }
        let f = fs::File::open(&self.tmp)
            .with_context(|| format!("writing {}", self.shown.display()))?;
        f.sync_all()
            .with_context(|| format!("writing {}", self.shown.display()))?;
        drop(f);
        if let Ok(old) = fs::metadata(&self.dest) {
            let _ = fs::set_permissions(&self.tmp, old.permissions());
        }
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

fn folder_of(p: &Path) -> PathBuf {
    match p.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// The absolute, symlink-free form of a path that may not exist yet (its folder resolved).
fn resolved(p: &Path) -> Option<PathBuf> {
    if let Ok(c) = fs::canonicalize(p) {
        return Some(c);
    }
    let dir = fs::canonicalize(folder_of(p)).ok()?;
    Some(dir.join(p.file_name()?))
}

/// Whether `a` and `b` name the same file: the same resolved path, or (when both exist) the
/// same device and inode (a hard link).
pub fn same_file(a: &Path, b: &Path) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        if let (Ok(x), Ok(y)) = (fs::metadata(a), fs::metadata(b)) {
            if (x.dev(), x.ino()) == (y.dev(), y.ino()) {
                return true;
            }
        }
    }
    match (resolved(a), resolved(b)) {
        (Some(x), Some(y)) => x == y,
        _ => a == b,
    }
}

/// Refuses an output that is one of the inputs, or the same file as another output.
/// `outputs` and `inputs` are (flag, path) pairs, e.g. `("--out", out)`, `("--bag", bag)`.
pub fn refuse_same_file(outputs: &[(&str, &Path)], inputs: &[(&str, &Path)]) -> Result<()> {
    for (i, (oflag, out)) in outputs.iter().enumerate() {
        for (iflag, inp) in inputs {
            if same_file(out, inp) {
                bail!(
                    "{oflag} {} is the same file as the input {iflag} {}: writing it would destroy the input; choose another output file",
                    out.display(),
                    inp.display()
                );
            }
        }
        for (oflag2, out2) in &outputs[i + 1..] {
            if same_file(out, out2) {
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

/// stdout was closed by its reader (`scancorr … | head`): the command stops quietly.
#[derive(Debug)]
pub struct StdoutClosed;

impl std::fmt::Display for StdoutClosed {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("stdout closed")
    }
}

impl std::error::Error for StdoutClosed {}

/// Writes to stdout; a closed pipe becomes [`StdoutClosed`], another failure an error.
pub fn write_stdout(args: std::fmt::Arguments<'_>) -> Result<()> {
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
    () => { $crate::output::write_stdout(format_args!("\n")) };
    ($($t:tt)*) => { $crate::output::write_stdout(format_args!("{}\n", format_args!($($t)*))) };
}

/// `print!` that returns a `Result` (see [`outln!`]).
macro_rules! out {
    ($($t:tt)*) => { $crate::output::write_stdout(format_args!($($t)*)) };
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
            let o = AtomicOutput::new("--out", &f).unwrap();
            o.write_all("new").unwrap();
            assert_eq!(fs::read_to_string(&f).unwrap(), "old");
        }
        assert_eq!(fs::read_to_string(&f).unwrap(), "old");
        assert_eq!(fs::read_dir(&d).unwrap().count(), 1, "temporary removed");
        let o = AtomicOutput::new("--out", &f).unwrap();
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
        fs::remove_dir_all(&d).ok();
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
