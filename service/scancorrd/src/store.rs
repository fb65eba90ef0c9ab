//! The calibration store: every version of every machine's calibration, with its parent and
//! note, one current per machine. SQLite in WAL mode with synchronous writes: a crash loses
//! nothing that was acknowledged.
//!
//! # Versions
//!
//! The store assigns version numbers: every [`Store::put`] stores the document as version
//! `latest + 1` of its machine (1 for a new machine), whatever version the document names, and
//! returns the document with the assigned version. Its parent is the version the document
//! names as `parent_version` when that version of the machine exists in this store, else the
//! current version (a document made elsewhere may name versions this store does not have). Versions run from 1
//! to [`MAX_VERSION`]; the arithmetic is checked and a put that would go beyond is refused
//! ([`StoreError::VersionsExhausted`]).
//!
//! # Damage
//!
//! Damage is confined to the machine it touches. A machine whose current document is damaged
//! (not JSON, not a calibration, for another machine, another version than its row, stored as
//! something other than text, larger than [`MAX_DOC_BYTES`], a current version with no
//! document, a version entry that is not a version number, several current entries, versions
//! stored but none current, ...) is still listed by [`Store::machines`];
//! [`Store::current`] returns [`StoreError::Damaged`] naming it, and a new [`Store::put`] for
//! it works (its version is one above the largest intact version number) and heals it. Rows
//! whose machine is not a valid name (not text, not UTF-8, or against
//! [`scancorr_proto::names`]) or whose version is not a version number belong to no machine:
//! they are skipped everywhere and described by [`Store::damaged_rows`] for the log.
//! Damage of the database as a whole (a file that is not SQLite, tables of the wrong shape) is
//! an error of [`Store::open`] naming the file: the service refuses to start with it.
//!
//! # Size
//!
//! A document is at most [`MAX_DOC_BYTES`] in its stored (pretty JSON) form. The number of
//! versions kept per machine is not capped: the history is the lab's record and nothing is
//! ever deleted, so the database grows by at most [`MAX_DOC_BYTES`] per put.

use rusqlite::types::ValueRef;
use rusqlite::{params, Connection, ErrorCode, Row, TransactionBehavior};
use scancorr_core::Calibration;
use scancorr_proto::names;
use serde::Serialize;
use std::path::Path;

/// The database file inside the store's folder.
pub const FILE_NAME: &str = "calibrations.sqlite";

/// The largest calibration document the store keeps, bytes of its stored (pretty JSON) form.
///
/// The example calibration with every effect (`scancorr calib example --all-effects`) is
/// 7.4 KB; the simulator's (`scancorr sim --calib-out`, a 101-knot guide straightness and
/// pitch table) 16 KB; a lab-written model with every effect and full-precision guide tables
/// of 101 knots on all three axes 48 KB (`tests/tests/service_store.rs` builds it). 1 MiB
/// leaves 22 times that — a hand-made table of some 2500 knots per axis still fits — while a
/// flood of puts grows the database by at most 1 MiB each.
pub const MAX_DOC_BYTES: usize = 1 << 20;

/// The largest version number: 2^53 − 1, the largest integer every JSON reader (JavaScript,
/// a float) keeps exactly, far below SQLite's `i64::MAX`. A stored version above it is damage.
pub const MAX_VERSION: u64 = (1 << 53) - 1;

/// Most entries [`Store::damaged_rows`] lists one by one.
const MAX_DAMAGE_LINES: usize = 50;

/// Store errors.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// Database error.
    #[error("calibration store: {0}")]
    Db(#[from] rusqlite::Error),
    /// The database cannot be opened or is not a calibration store: not SQLite, tables of the
    /// wrong shape, no permission, ... The whole store is unusable.
    #[error("calibration store {path}: {msg}")]
    Open {
        /// The database file.
        path: String,
        /// What is wrong.
        msg: String,
    },
    /// The stored calibration of one machine is damaged; other machines are not affected, and
    /// a new put for this machine replaces it.
    #[error("calibration store: the calibration of machine `{machine}`{} is damaged: {msg}", at_version(.version))]
    Damaged {
        /// Machine.
        machine: String,
        /// The damaged version, 0 when the version number itself is what is damaged.
        version: u64,
        /// What is wrong.
        msg: String,
    },
    /// A document larger than [`MAX_DOC_BYTES`].
    #[error("calibration store: the calibration document for `{machine}` is {bytes} bytes, more than the limit of {max} bytes")]
    TooLarge {
        /// Machine.
        machine: String,
        /// The document's size (stored form), bytes.
        bytes: usize,
        /// [`MAX_DOC_BYTES`].
        max: usize,
    },
    /// The machine has used every version number.
    #[error(
        "calibration store: machine `{machine}` has reached the last version number {}",
        MAX_VERSION
    )]
    VersionsExhausted {
        /// Machine.
        machine: String,
    },
    /// A machine id that does not follow the name grammar.
    #[error("calibration store: {0}")]
    Name(#[from] names::NameError),
    /// Free text of the document (its note, its creation time) holding a control,
    /// bidirectional-override or zero-width character.
    #[error("calibration store: the calibration document for `{machine}`: {msg}")]
    Text {
        /// Machine.
        machine: String,
        /// The field, the character and where ([`scancorr_core::calib::check_text`]).
        msg: String,
    },
    /// The folder cannot be created.
    #[error("calibration store folder {0}: {1}")]
    Folder(String, std::io::Error),
}

fn at_version(v: &u64) -> String {
    if *v == 0 {
        String::new()
    } else {
        format!(" (version {v})")
    }
}

/// One version in the history.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct VersionInfo {
    /// Version.
    pub version: u64,
    /// Parent.
    pub parent_version: Option<u64>,
    /// Note.
    pub note: String,
    /// Creation time.
    pub created: String,
    /// Whether it is current.
    pub current: bool,
    /// What is damaged in this version (its document or its row), if anything; such a
    /// version cannot be fetched.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub damaged: Option<String>,
    /// When this store took it in (the service's clock), who asked and how — the audit
    /// trail; absent for versions stored before the trail existed.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub audit: Option<Audit>,
}

/// Who put a version, when, and how. Stored and listed with every control,
/// bidirectional-override and zero-width character written as `<U+XXXX>`
/// ([`scancorr_core::calib::escape_text`]): a claimed identity is shown as it came, and reads
/// as it is stored.
#[derive(Debug, Clone, Serialize, PartialEq, Default)]
pub struct Audit {
    /// When it was stored (RFC 3339, UTC, the service's clock).
    pub at: String,
    /// Who asked: the identity the requester gave (`user@host`), marked as claimed (`unnamed`
    /// when it gave no user, never a made-up one); the router's access control has already
    /// checked the requester's certificate role. zenoh's query API gives the service neither
    /// the requester's zenoh id nor its certificate (see `server::queries::audit_of`).
    pub by: String,
    /// `put`, or `rollback to vN`.
    pub action: String,
}

impl Audit {
    /// The record with its hidden characters shown (see [`Audit`]).
    pub fn shown(&self) -> Audit {
        use scancorr_core::calib::escape_text;
        Audit {
            at: escape_text(&self.at),
            by: escape_text(&self.by),
            action: escape_text(&self.action),
        }
    }
}

/// The store.
pub struct Store {
    conn: Connection,
    /// What [`Store::open`] found and repaired, for [`Store::damaged_rows`].
    notes: Vec<String>,
}

/// The columns each table needs.
const SHAPE: [(&str, &[&str]); 2] = [
    (
        "calibration",
        &["machine", "version", "parent", "note", "created", "doc"],
    ),
    ("current", &["machine", "version"]),
];

impl Store {
    /// Opens (creating) the store in `dir` (the database is `dir/`[`FILE_NAME`]).
    ///
    /// Damage of the whole database is an error naming the file ([`StoreError::Open`]): a file
    /// that is not SQLite, a `calibration` or `current` table without the store's columns. The
    /// service then refuses to start; move the file away to start with an empty store.
    /// A missing `current` table is rebuilt (each machine's latest version made current) and
    /// a missing `calibration` table created empty; both are reported by
    /// [`Store::damaged_rows`]. Damage confined to rows is no error here; see the module
    /// documentation.
    pub fn open(dir: &Path) -> Result<Store, StoreError> {
        std::fs::create_dir_all(dir)
            .map_err(|e| StoreError::Folder(dir.display().to_string(), e))?;
        let path = dir.join(FILE_NAME);
        let fail = |msg: String| StoreError::Open {
            path: path.display().to_string(),
            msg,
        };
        let db = |e: rusqlite::Error| {
            fail(match e.sqlite_error_code() {
                Some(ErrorCode::NotADatabase) => format!(
                    "{e}: the file is not an SQLite database (move it away to start with an empty store)"
                ),
                Some(ErrorCode::DatabaseCorrupt) => format!(
                    "{e}: the database file is corrupt (move it away to start with an empty store)"
                ),
                _ => e.to_string(),
            })
        };
        let conn = Connection::open(&path).map_err(db)?;
        let tables: Vec<(String, String)> = conn
            .prepare(
                "SELECT name, type FROM sqlite_master WHERE name IN ('calibration', 'current')",
            )
            .and_then(|mut st| {
                let rows = st
                    .query_map([], |r| Ok((r.get(0)?, r.get(1)?)))?
                    .collect::<Result<Vec<_>, _>>();
                rows
            })
            .map_err(db)?;
        for (name, kind) in &tables {
            if kind != "table" {
                return Err(fail(format!(
                    "`{name}` is a {kind}, not a table: this is not a scancorrd calibration store"
                )));
            }
        }
        let had = |t: &str| tables.iter().any(|(n, _)| n == t);
        let (had_calibration, had_current) = (had("calibration"), had("current"));
        conn.pragma_update(None, "journal_mode", "WAL")
            .map_err(db)?;
        conn.pragma_update(None, "synchronous", "FULL")
            .map_err(db)?;
        // A small page cache (SQLite's default is 2 MiB): the store is read when a machine
        // starts being served and on queries, never per sample, and each calibration read
        // would otherwise stay cached — memory that grew with the number of machines.
        conn.pragma_update(None, "cache_size", -256).map_err(db)?;
        conn.execute_batch(
            "CREATE TABLE IF NOT EXISTS calibration (
                machine TEXT NOT NULL, version INTEGER NOT NULL, parent INTEGER, note TEXT NOT NULL,
                created TEXT NOT NULL, doc TEXT NOT NULL, PRIMARY KEY (machine, version));
             CREATE TABLE IF NOT EXISTS current (machine TEXT PRIMARY KEY, version INTEGER NOT NULL);
             CREATE TABLE IF NOT EXISTS audit (machine TEXT NOT NULL, version INTEGER NOT NULL,
                at TEXT NOT NULL, by TEXT NOT NULL, action TEXT NOT NULL);",
        )
        .map_err(db)?;
        for (table, needed) in SHAPE {
            let cols: Vec<String> = conn
                .prepare("SELECT name FROM pragma_table_info(?1)")
                .and_then(|mut st| {
                    let rows = st
                        .query_map([table], |r| r.get(0))?
                        .collect::<Result<Vec<_>, _>>();
                    rows
                })
                .map_err(db)?;
            let missing: Vec<&str> = needed
                .iter()
                .copied()
                .filter(|c| !cols.iter().any(|h| h.eq_ignore_ascii_case(c)))
                .collect();
            if !missing.is_empty() {
                return Err(fail(format!(
                    "table `{table}` has no column {} (it has {}): this is not a scancorrd calibration store",
                    missing.join(", "),
                    if cols.is_empty() { "none".into() } else { cols.join(", ") }
                )));
            }
        }
        let mut notes = vec![];
        if had_current && !had_calibration {
            notes.push(
                "table `calibration` was missing: created empty (every machine named in `current` has lost its documents)"
                    .to_string(),
            );
        }
        if had_calibration && !had_current {
            let n = conn
                .execute(
                    "INSERT INTO current (machine, version)
                     SELECT machine, MAX(version) FROM calibration
                     WHERE typeof(machine) = 'text' AND typeof(version) = 'integer' AND version BETWEEN 1 AND ?1
                     GROUP BY machine",
                    [MAX_VERSION as i64],
                )
                .map_err(db)?;
            notes.push(format!(
                "table `current` was missing: rebuilt, the latest version of each of {n} machines made current"
            ));
        }
        Ok(Store { conn, notes })
    }

    /// Stores a document as a new version of its machine and makes it current: version
    /// `latest + 1` (1 for a new machine) whatever the document says; parent the document's
    /// `parent_version` if the machine has that version in this store, else the current
    /// version. Returns the stored document. Works for a
    /// machine whose stored calibration is damaged: the new version is one above the largest
    /// intact version number, and replaces the damaged current. Refuses a document larger than
    /// [`MAX_DOC_BYTES`] ([`StoreError::TooLarge`]) and a machine id against the name grammar.
    /// Does not validate the document's values ([`Calibration::build`] is the caller's).
    pub fn put(&mut self, cal: Calibration) -> Result<Calibration, StoreError> {
        self.put_audited(cal, None)
    }

    /// [`Store::put`] with its audit record written in the same transaction (the version and
    /// its record are stored together or not at all).
    pub fn put_audited(
        &mut self,
        mut cal: Calibration,
        audit: Option<&Audit>,
    ) -> Result<Calibration, StoreError> {
        names::check_machine(&cal.machine_id)?;
        let machine = cal.machine_id.clone();
        for (field, text, lines) in [("note", &cal.note, true), ("created", &cal.created, false)] {
            scancorr_core::calib::check_text(field, text, lines).map_err(|msg| {
                StoreError::Text {
                    machine: machine.clone(),
                    msg,
                }
            })?;
        }
        let audit = audit.map(Audit::shown);
        let tx = self
            .conn
            .transaction_with_behavior(TransactionBehavior::Immediate)?;
        let latest = latest_valid(&tx, &machine)?;
        let next = latest
            .unwrap_or(0)
            .checked_add(1)
            .filter(|n| *n <= MAX_VERSION)
            .ok_or_else(|| StoreError::VersionsExhausted {
                machine: machine.clone(),
            })?;
        // The parent the document names, if this store has that version of the machine (a
        // document made elsewhere — the lab's files, another store — names versions this
        // store may not have); else the current version.
        let parent = match cal.parent_version {
            Some(p) if count_rows(&tx, &machine, p)? > 0 => Some(p),
            _ => match current_entries(&tx, &machine)?.as_slice() {
                [v] => version_of(v.into())
                    .ok()
                    .filter(|v| count_rows(&tx, &machine, *v).is_ok_and(|n| n > 0)),
                _ => None,
            },
        };
        cal.version = next;
        cal.parent_version = parent;
        let doc = cal.to_json();
        if doc.len() > MAX_DOC_BYTES {
            return Err(StoreError::TooLarge {
                machine,
                bytes: doc.len(),
                max: MAX_DOC_BYTES,
            });
        }
        tx.execute(
            "INSERT INTO calibration (machine, version, parent, note, created, doc) VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
            params![machine, next as i64, parent.map(|p| p as i64), cal.note, cal.created, doc],
        )?;
        // Delete and insert rather than upsert: heals duplicated entries, and works on a
        // `current` table that has lost its primary key.
        tx.execute("DELETE FROM current WHERE machine = ?1", params![machine])?;
        tx.execute(
            "INSERT INTO current (machine, version) VALUES (?1, ?2)",
            params![machine, next as i64],
        )?;
        if let Some(a) = &audit {
            tx.execute(
                "INSERT INTO audit (machine, version, at, by, action) VALUES (?1, ?2, ?3, ?4, ?5)",
                params![machine, next as i64, a.at, a.by, a.action],
            )?;
        }
        tx.commit()?;
        Ok(cal)
    }

    /// The current document of a machine; `Ok(None)` if the machine has none. Any damage of
    /// that machine's current calibration is [`StoreError::Damaged`] naming the machine (so
    /// is a corrupt database page met while reading it).
    pub fn current(&self, machine: &str) -> Result<Option<Calibration>, StoreError> {
        names::check_machine(machine)?;
        self.current_inner(machine)
            .map_err(|e| corrupt_is_damage(machine, 0, e))
    }

    fn current_inner(&self, machine: &str) -> Result<Option<Calibration>, StoreError> {
        let damaged = |version: u64, msg: String| StoreError::Damaged {
            machine: machine.into(),
            version,
            msg,
        };
        let entries = current_entries(&self.conn, machine)?;
        match entries.as_slice() {
            [] => {
                let stored: i64 = self.conn.query_row(
                    "SELECT COUNT(*) FROM calibration WHERE machine = ?1",
                    params![machine],
                    |r| r.get(0),
                )?;
                if stored == 0 {
                    Ok(None)
                } else {
                    Err(damaged(
                        0,
                        format!(
                            "{stored} versions are stored but none is marked current{}; a new put makes one current",
                            match latest_valid(&self.conn, machine)? {
                                Some(l) => format!(" (the latest is {l})"),
                                None => String::new(),
                            }
                        ),
                    ))
                }
            }
            [v] => {
                let v = version_of(v.into())
                    .map_err(|why| damaged(0, format!("its current version is {why}")))?;
                match self.get_inner(machine, v)? {
                    Some(c) => Ok(Some(c)),
                    None => Err(damaged(
                        v,
                        "the current version has no stored document".into(),
                    )),
                }
            }
            many => Err(damaged(
                0,
                format!(
                    "{} current-version entries ({}) where there must be one",
                    many.len(),
                    many.iter()
                        .map(|v| describe(v.into()))
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            )),
        }
    }

    /// A given version; `Ok(None)` if the machine has no such version, [`StoreError::Damaged`]
    /// if its document is damaged.
    pub fn get(&self, machine: &str, version: u64) -> Result<Option<Calibration>, StoreError> {
        names::check_machine(machine)?;
        self.get_inner(machine, version)
            .map_err(|e| corrupt_is_damage(machine, version, e))
    }

    fn get_inner(&self, machine: &str, version: u64) -> Result<Option<Calibration>, StoreError> {
        if version == 0 || version > MAX_VERSION {
            return Ok(None);
        }
        let mut st = self.conn.prepare_cached(
            "SELECT typeof(doc), length(CAST(doc AS BLOB)),
                    CASE WHEN length(CAST(doc AS BLOB)) <= ?3 THEN doc END
             FROM calibration WHERE machine = ?1 AND version = ?2",
        )?;
        let rows: Vec<(String, Option<i64>, Cell)> = st
            .query_map(
                params![machine, version as i64, MAX_DOC_BYTES as i64],
                |r| Ok((r.get(0)?, r.get(1)?, Cell::read(r, 2)?)),
            )?
            .collect::<Result<_, _>>()?;
        let damaged = |msg: String| StoreError::Damaged {
            machine: machine.into(),
            version,
            msg,
        };
        let (kind, len, doc) = match rows.as_slice() {
            [] => return Ok(None),
            [row] => row,
            many => {
                return Err(damaged(format!(
                    "{} stored documents for this version where there must be one",
                    many.len()
                )))
            }
        };
        if kind != "text" {
            return Err(damaged(format!(
                "the document is stored as {}, not as text",
                kind.to_uppercase()
            )));
        }
        let len = len.unwrap_or(0).max(0) as usize;
        if len > MAX_DOC_BYTES {
            return Err(damaged(format!(
                "the document is {len} bytes, more than the limit of {MAX_DOC_BYTES}"
            )));
        }
        let Cell::Text(bytes) = doc else {
            return Err(damaged("the document cannot be read as text".into()));
        };
        let text = std::str::from_utf8(bytes).map_err(|e| {
            damaged(format!(
                "the document is not UTF-8 text (byte {} is not)",
                e.valid_up_to()
            ))
        })?;
        let cal = Calibration::from_json(text)
            .map_err(|e| damaged(format!("the document is not a calibration: {e}")))?;
        if cal.machine_id != machine {
            return Err(damaged(format!(
                "the document is for machine {}",
                names::shown(&cal.machine_id)
            )));
        }
        if cal.version != version {
            return Err(damaged(format!(
                "the document says version {}",
                cal.version
            )));
        }
        Ok(Some(cal))
    }

    /// Every version of a machine, oldest first. A version whose document or row is damaged
    /// is listed with `damaged` saying what; a row whose version number is damaged is left out
    /// (see [`Store::damaged_rows`]).
    pub fn history(&self, machine: &str) -> Result<Vec<VersionInfo>, StoreError> {
        names::check_machine(machine)?;
        let current = match current_entries(&self.conn, machine)?.as_slice() {
            [v] => version_of(v.into()).ok(),
            _ => None,
        };
        let mut st = self
            .conn
            .prepare("SELECT version, parent, note, created FROM calibration WHERE machine = ?1")?;
        let rows: Vec<[Cell; 4]> = st
            .query_map(params![machine], |r| {
                Ok([
                    Cell::read(r, 0)?,
                    Cell::read(r, 1)?,
                    Cell::read(r, 2)?,
                    Cell::read(r, 3)?,
                ])
            })?
            .collect::<Result<_, _>>()?;
        // The audit trail (a damaged record is left out: the version is still listed).
        let mut trail: std::collections::BTreeMap<u64, Audit> = Default::default();
        if let Ok(mut st) = self
            .conn
            .prepare("SELECT version, at, by, action FROM audit WHERE machine = ?1")
        {
            if let Ok(rows) = st.query_map(params![machine], |r| {
                Ok((
                    r.get::<_, i64>(0)?,
                    r.get::<_, String>(1)?,
                    r.get::<_, String>(2)?,
                    r.get::<_, String>(3)?,
                ))
            }) {
                for (v, at, by, action) in rows.flatten() {
                    // (Shown again: a record stored before they were.)
                    trail.insert(v as u64, Audit { at, by, action }.shown());
                }
            }
        }
        let mut out = vec![];
        for [version, parent, note, created] in rows {
            let Ok(version) = version_of((&version).into()) else {
                continue;
            };
            let mut damage = vec![];
            let parent_version = match ValueRef::from(&parent) {
                ValueRef::Null => None,
                p => match version_of(p) {
                    Ok(p) => Some(p),
                    Err(why) => {
                        damage.push(format!("its parent is {why}"));
                        None
                    }
                },
            };
            let mut text = |what: &str, v: Cell| match v {
                Cell::Text(s) if std::str::from_utf8(&s).is_ok() => {
                    String::from_utf8(s).unwrap_or_default()
                }
                v => {
                    damage.push(format!("its {what} is {}, not text", describe((&v).into())));
                    String::new()
                }
            };
            let (note, created) = (text("note", note), text("created", created));
            // Stored before free text was checked: shown, not hidden.
            let (note, created) = (
                scancorr_core::calib::escape_text(&note)
                    .replace("<U+000A>", "\n")
                    .replace("<U+0009>", "\t"),
                scancorr_core::calib::escape_text(&created),
            );
            if let Err(e) = self.get_inner(machine, version) {
                let e = corrupt_is_damage(machine, version, e);
                damage.insert(
                    0,
                    match e {
                        StoreError::Damaged { msg, .. } => msg,
                        e => e.to_string(),
                    },
                );
            }
            out.push(VersionInfo {
                version,
                parent_version,
                note,
                created,
                current: Some(version) == current,
                damaged: (!damage.is_empty()).then(|| damage.join("; ")),
                audit: trail.remove(&version),
            });
        }
        out.sort_by_key(|v| v.version);
        Ok(out)
    }

    /// Machines with a calibration: every valid machine name with a current-version entry or
    /// a stored version, sorted. Includes machines whose calibration is damaged
    /// ([`Store::current`] says how); rows whose machine is not a valid name are skipped
    /// (listed by [`Store::damaged_rows`]), never an error for the whole list.
    pub fn machines(&self) -> Result<Vec<String>, StoreError> {
        let mut st = self.conn.prepare(
            "SELECT machine FROM current WHERE typeof(machine) = 'text'
             UNION SELECT machine FROM calibration WHERE typeof(machine) = 'text'",
        )?;
        let mut out: Vec<String> = st
            .query_map([], |r| match r.get_ref(0)? {
                ValueRef::Text(b) => Ok(std::str::from_utf8(b).ok().map(str::to_string)),
                _ => Ok(None),
            })?
            .filter_map(|r| r.transpose())
            .collect::<Result<Vec<_>, _>>()?;
        out.retain(|m| names::is_valid(m));
        out.sort();
        out.dedup();
        Ok(out)
    }

    /// Rows that belong to no machine and are skipped (a machine that is not a valid name, a
    /// version that is not a version number) and what [`Store::open`] repaired, one line each,
    /// for the log. Damage of a valid machine's calibration is reported by [`Store::current`]
    /// instead. Never fails: a table that cannot be scanned is itself a line.
    pub fn damaged_rows(&self) -> Vec<String> {
        let mut out = self.notes.clone();
        let mut more = 0usize;
        for table in ["current", "calibration"] {
            let scan = || -> Result<Vec<(Cell, Cell)>, rusqlite::Error> {
                let mut st = self
                    .conn
                    .prepare(&format!("SELECT machine, version FROM {table}"))?;
                let rows = st
                    .query_map([], |r| Ok((Cell::read(r, 0)?, Cell::read(r, 1)?)))?
                    .collect::<Result<Vec<_>, _>>()?;
                Ok(rows)
            };
            match scan() {
                Ok(rows) => {
                    for (m, v) in rows {
                        let why = match &m {
                            Cell::Text(t) => match std::str::from_utf8(t)
                                .map_err(|_| "the machine is text that is not UTF-8".to_string())
                                .and_then(|t| {
                                    names::check_machine(t)
                                        .map_err(|e| format!("the machine id {}", e.reason))
                                }) {
                                Err(e) => e,
                                Ok(()) => match version_of((&v).into()) {
                                    Err(why) => format!("the version is {why}"),
                                    Ok(_) => continue,
                                },
                            },
                            _ => "the machine is not text".to_string(),
                        };
                        if out.len() < MAX_DAMAGE_LINES {
                            out.push(format!(
                                "table `{table}`: row (machine {}, version {}) skipped: {why}",
                                describe((&m).into()),
                                describe((&v).into())
                            ));
                        } else {
                            more += 1;
                        }
                    }
                }
                Err(e) => out.push(format!("table `{table}` cannot be scanned: {e}")),
            }
        }
        if more > 0 {
            out.push(format!("... and {more} more damaged rows"));
        }
        out
    }

    /// Runs raw SQL on the database. For tests that damage a store on purpose; never used by
    /// the service.
    #[doc(hidden)]
    pub fn raw_sql_for_tests(&self, sql: &str) -> Result<(), StoreError> {
        Ok(self.conn.execute_batch(sql)?)
    }
}

/// The largest intact version number of a machine.
fn latest_valid(conn: &Connection, machine: &str) -> Result<Option<u64>, rusqlite::Error> {
    let l: Option<i64> = conn.query_row(
        "SELECT MAX(version) FROM calibration
         WHERE machine = ?1 AND typeof(version) = 'integer' AND version BETWEEN 1 AND ?2",
        params![machine, MAX_VERSION as i64],
        |r| r.get(0),
    )?;
    Ok(l.map(|l| l as u64))
}

/// How many stored rows a machine has for a version.
fn count_rows(conn: &Connection, machine: &str, version: u64) -> Result<i64, rusqlite::Error> {
    if version == 0 || version > MAX_VERSION {
        return Ok(0);
    }
    conn.query_row(
        "SELECT COUNT(*) FROM calibration WHERE machine = ?1 AND version = ?2",
        params![machine, version as i64],
        |r| r.get(0),
    )
}

/// The machine's entries in `current` (one, unless damaged), as stored.
fn current_entries(conn: &Connection, machine: &str) -> Result<Vec<Cell>, rusqlite::Error> {
    let mut st = conn.prepare_cached("SELECT version FROM current WHERE machine = ?1")?;
    let rows = st
        .query_map(params![machine], |r| Cell::read(r, 0))?
        .collect::<Result<Vec<Cell>, _>>()?;
    Ok(rows)
}

/// A stored value, owned. Text is kept as bytes: SQLite text need not be UTF-8 (and
/// `rusqlite::types::Value` panics on such text).
#[derive(Debug, Clone, PartialEq)]
enum Cell {
    Null,
    Integer(i64),
    Real(f64),
    Text(Vec<u8>),
    Blob(Vec<u8>),
}

impl Cell {
    fn read(r: &Row<'_>, i: usize) -> Result<Cell, rusqlite::Error> {
        Ok(match r.get_ref(i)? {
            ValueRef::Null => Cell::Null,
            ValueRef::Integer(v) => Cell::Integer(v),
            ValueRef::Real(v) => Cell::Real(v),
            ValueRef::Text(b) => Cell::Text(b.to_vec()),
            ValueRef::Blob(b) => Cell::Blob(b.to_vec()),
        })
    }
}

impl<'a> From<&'a Cell> for ValueRef<'a> {
    fn from(c: &'a Cell) -> ValueRef<'a> {
        match c {
            Cell::Null => ValueRef::Null,
            Cell::Integer(v) => ValueRef::Integer(*v),
            Cell::Real(v) => ValueRef::Real(*v),
            Cell::Text(b) => ValueRef::Text(b),
            Cell::Blob(b) => ValueRef::Blob(b),
        }
    }
}

/// A stored version number, or why it is none.
fn version_of(v: ValueRef<'_>) -> Result<u64, String> {
    match v {
        ValueRef::Integer(i) if i >= 1 && i as u64 <= MAX_VERSION => Ok(i as u64),
        v => Err(format!(
            "{}, not a version number (1 … {MAX_VERSION})",
            describe(v)
        )),
    }
}

/// A stored value, shown safely for a message.
fn describe(v: ValueRef<'_>) -> String {
    match v {
        ValueRef::Null => "NULL".into(),
        ValueRef::Integer(i) => i.to_string(),
        ValueRef::Real(f) => format!("the real number {f}"),
        ValueRef::Text(b) => match std::str::from_utf8(b) {
            Ok(s) => format!("the text {}", names::shown(s)),
            Err(_) => format!(
                "text that is not UTF-8 ({})",
                names::shown(&String::from_utf8_lossy(b))
            ),
        },
        ValueRef::Blob(b) => {
            let hex: String = b.iter().take(16).map(|x| format!("{x:02x}")).collect();
            format!(
                "a BLOB of {} bytes (x'{hex}{}')",
                b.len(),
                if b.len() > 16 { "…" } else { "" }
            )
        }
    }
}

/// A corrupt database page met while reading one machine's calibration is that machine's
/// damage.
fn corrupt_is_damage(machine: &str, version: u64, e: StoreError) -> StoreError {
    match e {
        StoreError::Db(e)
            if matches!(
                e.sqlite_error_code(),
                Some(ErrorCode::DatabaseCorrupt | ErrorCode::NotADatabase)
            ) =>
        {
            StoreError::Damaged {
                machine: machine.into(),
                version,
                msg: e.to_string(),
            }
        }
        e => e,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fresh(name: &str) -> std::path::PathBuf {
        let dir =
            std::env::temp_dir().join(format!("scancorrd-store-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    #[test]
    fn versions_survive_reopening() {
        let dir = fresh("reopen");
        {
            let mut s = Store::open(&dir).unwrap();
            assert!(s.current("m1").unwrap().is_none());
            let v1 = s.put(Calibration::example("m1")).unwrap();
            assert_eq!(v1.version, 1);
            let v2 = s.put(Calibration::example("m1")).unwrap();
            assert_eq!((v2.version, v2.parent_version), (2, Some(1)));
        }
        let s = Store::open(&dir).unwrap();
        assert_eq!(s.current("m1").unwrap().unwrap().version, 2);
        let h = s.history("m1").unwrap();
        assert_eq!(h.iter().map(|v| v.version).collect::<Vec<_>>(), vec![1, 2]);
        assert!(h[1].current && !h[0].current);
        assert!(h.iter().all(|v| v.damaged.is_none()));
        assert_eq!(s.get("m1", 1).unwrap().unwrap().version, 1);
        assert!(s.damaged_rows().is_empty(), "{:?}", s.damaged_rows());
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn the_store_assigns_versions_whatever_the_document_says() {
        let dir = fresh("versions");
        let mut s = Store::open(&dir).unwrap();
        let mut c = Calibration::example("m1");
        c.version = i64::MAX as u64;
        assert_eq!(s.put(c.clone()).unwrap().version, 1);
        c.version = u64::MAX;
        let v2 = s.put(c.clone()).unwrap();
        assert_eq!((v2.version, v2.parent_version), (2, Some(1)));
        c.version = 0;
        let v3 = s.put(c).unwrap();
        assert_eq!((v3.version, v3.parent_version), (3, Some(2)));
        // The stored document carries the assigned version.
        assert_eq!(s.current("m1").unwrap().unwrap().version, 3);
        assert_eq!(s.get("m1", 2).unwrap().unwrap().version, 2);
        assert!(s.get("m1", i64::MAX as u64).unwrap().is_none());
        assert!(s.get("m1", u64::MAX).unwrap().is_none());
        // Another machine counts from 1.
        assert_eq!(s.put(Calibration::example("m2")).unwrap().version, 1);
        drop(s);
        // A version at the very end of the range is exhausted, not an overflow.
        let s = Store::open(&dir).unwrap();
        s.raw_sql_for_tests(&format!(
            "UPDATE calibration SET version = {MAX_VERSION}, doc = replace(doc, '\"version\": 3', '\"version\": {MAX_VERSION}') WHERE machine = 'm1' AND version = 3;
             UPDATE current SET version = {MAX_VERSION} WHERE machine = 'm1';"
        ))
        .unwrap();
        assert_eq!(s.current("m1").unwrap().unwrap().version, MAX_VERSION);
        let mut s = s;
        let e = s.put(Calibration::example("m1")).unwrap_err();
        assert!(matches!(e, StoreError::VersionsExhausted { .. }), "{e}");
        std::fs::remove_dir_all(&dir).ok();
    }

    /// Issue 44: the audit's author is free text the requester claims: bidirectional
    /// overrides and zero-width characters passed into the history. They are written as
    /// `<U+XXXX>` (stored and listed); a document's note or creation time holding one is
    /// refused naming the field.
    #[test]
    fn hidden_characters_are_shown_in_the_audit_and_refused_in_a_note() {
        let dir = fresh("hidden");
        let mut s = Store::open(&dir).unwrap();
        let who = Audit {
            at: "2026-01-01T00:00:00Z".into(),
            by: "eve\u{202E}nimda\u{200B}@host (claimed)".into(),
            action: "put".into(),
        };
        s.put_audited(Calibration::example("m1"), Some(&who))
            .unwrap();
        let h = s.history("m1").unwrap();
        let by = &h[0].audit.as_ref().unwrap().by;
        assert_eq!(by, "eve<U+202E>nimda<U+200B>@host (claimed)");
        for (field, bad) in [("note", "ok \u{2067}x"), ("created", "\u{FEFF}2026")] {
            let mut c = Calibration::example("m1");
            if field == "note" {
                c.note = bad.into();
            } else {
                c.created = bad.into();
            }
            let e = s.put_audited(c, Some(&who)).unwrap_err();
            assert!(matches!(e, StoreError::Text { .. }), "{e}");
            assert!(e.to_string().contains(field), "{e}");
        }
        assert_eq!(s.history("m1").unwrap().len(), 1);
        // Rows stored before the check are listed with their hidden characters shown.
        s.raw_sql_for_tests(
            "UPDATE calibration SET note = 'a' || char(8238) || 'b' || char(10) || 'c' WHERE machine = 'm1';
             UPDATE audit SET by = 'x' || char(8203) || 'y' WHERE machine = 'm1';",
        )
        .unwrap();
        let h = s.history("m1").unwrap();
        assert_eq!(h[0].note, "a<U+202E>b\nc");
        assert_eq!(h[0].audit.as_ref().unwrap().by, "x<U+200B>y");
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn a_too_large_document_is_refused() {
        let dir = fresh("large");
        let mut s = Store::open(&dir).unwrap();
        s.put(Calibration::example("m1")).unwrap();
        let mut c = Calibration::example("m1");
        c.note = "x".repeat(MAX_DOC_BYTES);
        let e = s.put(c).unwrap_err();
        assert!(matches!(e, StoreError::TooLarge { .. }), "{e}");
        assert!(e.to_string().contains("limit"), "{e}");
        // Nothing was stored; the next put is version 2.
        assert_eq!(s.history("m1").unwrap().len(), 1);
        let mut c = Calibration::example("m1");
        c.note = "y".repeat(MAX_DOC_BYTES / 2);
        assert_eq!(s.put(c).unwrap().version, 2);
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn parents_are_existing_versions_else_the_current_one() {
        let dir = fresh("parents");
        let mut s = Store::open(&dir).unwrap();
        let mut c = Calibration::example("m1");
        // A parent this store does not have (a document from elsewhere): none yet.
        c.parent_version = Some(7);
        assert_eq!(s.put(c.clone()).unwrap().parent_version, None);
        c.parent_version = None;
        assert_eq!(s.put(c.clone()).unwrap().parent_version, Some(1));
        assert_eq!(s.put(c.clone()).unwrap().parent_version, Some(2));
        // A named existing parent is kept: the lab derived version 4 from version 1.
        c.parent_version = Some(1);
        let v4 = s.put(c.clone()).unwrap();
        assert_eq!((v4.version, v4.parent_version), (4, Some(1)));
        let h = s.history("m1").unwrap();
        assert_eq!(h[3].parent_version, Some(1));
        for bad in [0, 9, i64::MAX as u64, u64::MAX] {
            c.parent_version = Some(bad);
            let v = s.put(c.clone()).unwrap();
            assert_eq!(v.parent_version, Some(v.version - 1), "parent {bad}");
        }
        // A parent of another machine is not this machine's.
        let mut other = Calibration::example("m2");
        other.parent_version = Some(1);
        assert_eq!(s.put(other).unwrap().parent_version, None);
        assert_eq!(s.current("m1").unwrap().unwrap().version, 8);
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn machine_ids_follow_the_name_grammar() {
        let dir = fresh("names");
        let mut s = Store::open(&dir).unwrap();
        for bad in ["", "m*", "a/b", "-x"] {
            let mut c = Calibration::example("m1");
            c.machine_id = bad.into();
            assert!(matches!(s.put(c).unwrap_err(), StoreError::Name(_)));
            assert!(matches!(s.current(bad).unwrap_err(), StoreError::Name(_)));
        }
        assert!(s.machines().unwrap().is_empty());
        std::fs::remove_dir_all(&dir).ok();
    }
}
