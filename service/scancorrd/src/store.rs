//! The calibration store: every version of every machine's calibration, with its parent and
//! note, one current per machine. SQLite in WAL mode with synchronous writes: a crash loses
//! nothing that was acknowledged.

use rusqlite::{params, Connection, OptionalExtension};
use scancorr_core::Calibration;
use serde::Serialize;
use std::path::Path;

/// Store errors.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// Database error.
    #[error("calibration store: {0}")]
    Db(#[from] rusqlite::Error),
    /// A stored document no longer parses.
    #[error("calibration store: version {version} of `{machine}` is damaged: {msg}")]
    Damaged {
        /// Machine.
        machine: String,
        /// Version.
        version: u64,
        /// Parser message.
        msg: String,
    },
    /// The folder cannot be created.
    #[error("calibration store folder {0}: {1}")]
    Folder(String, std::io::Error),
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
}

/// The store.
pub struct Store {
    conn: Connection,
}

impl Store {
    /// Opens (creating) the store in `dir`.
    pub fn open(dir: &Path) -> Result<Store, StoreError> {
        std::fs::create_dir_all(dir)
            .map_err(|e| StoreError::Folder(dir.display().to_string(), e))?;
        let conn = Connection::open(dir.join("calibrations.sqlite"))?;
        conn.pragma_update(None, "journal_mode", "WAL")?;
        conn.pragma_update(None, "synchronous", "FULL")?;
        conn.execute_batch(
            "CREATE TABLE IF NOT EXISTS calibration (
                machine TEXT NOT NULL, version INTEGER NOT NULL, parent INTEGER, note TEXT NOT NULL,
                created TEXT NOT NULL, doc TEXT NOT NULL, PRIMARY KEY (machine, version));
             CREATE TABLE IF NOT EXISTS current (machine TEXT PRIMARY KEY, version INTEGER NOT NULL);",
        )?;
        Ok(Store { conn })
    }

    /// Stores a validated document as a new version and makes it current. A document whose
    /// version is not above the latest gets the next number (its parent defaults to the
    /// current version). Returns the stored document.
    pub fn put(&mut self, mut cal: Calibration) -> Result<Calibration, StoreError> {
        let tx = self.conn.transaction()?;
        let latest: Option<u64> = tx.query_row(
            "SELECT MAX(version) FROM calibration WHERE machine = ?1",
            params![cal.machine_id],
            |r| r.get(0),
        )?;
        let current: Option<u64> = tx
            .query_row(
                "SELECT version FROM current WHERE machine = ?1",
                params![cal.machine_id],
                |r| r.get(0),
            )
            .optional()?;
        if latest.is_some_and(|l| cal.version <= l) {
            cal.version = latest.unwrap_or(0) + 1;
        }
        if cal.parent_version.is_none() {
            cal.parent_version = current;
        }
        tx.execute(
            "INSERT INTO calibration (machine, version, parent, note, created, doc) VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
            params![cal.machine_id, cal.version, cal.parent_version, cal.note, cal.created, cal.to_json()],
        )?;
        tx.execute("INSERT INTO current (machine, version) VALUES (?1, ?2) ON CONFLICT(machine) DO UPDATE SET version = ?2", params![cal.machine_id, cal.version])?;
        tx.commit()?;
        Ok(cal)
    }

    /// The current document of a machine.
    pub fn current(&self, machine: &str) -> Result<Option<Calibration>, StoreError> {
        let v: Option<u64> = self
            .conn
            .query_row(
                "SELECT version FROM current WHERE machine = ?1",
                params![machine],
                |r| r.get(0),
            )
            .optional()?;
        match v {
            Some(v) => self.get(machine, v),
            None => Ok(None),
        }
    }

    /// A given version.
    pub fn get(&self, machine: &str, version: u64) -> Result<Option<Calibration>, StoreError> {
        let doc: Option<String> = self
            .conn
            .query_row(
                "SELECT doc FROM calibration WHERE machine = ?1 AND version = ?2",
                params![machine, version],
                |r| r.get(0),
            )
            .optional()?;
        doc.map(|d| {
            Calibration::from_json(&d).map_err(|e| StoreError::Damaged {
                machine: machine.into(),
                version,
                msg: e.to_string(),
            })
        })
        .transpose()
    }

    /// Every version, oldest first.
    pub fn history(&self, machine: &str) -> Result<Vec<VersionInfo>, StoreError> {
        let current: Option<u64> = self
            .conn
            .query_row(
                "SELECT version FROM current WHERE machine = ?1",
                params![machine],
                |r| r.get(0),
            )
            .optional()?;
        let mut st = self.conn.prepare("SELECT version, parent, note, created FROM calibration WHERE machine = ?1 ORDER BY version")?;
        let rows = st.query_map(params![machine], |r| {
            let version: u64 = r.get(0)?;
            Ok(VersionInfo {
                version,
                parent_version: r.get(1)?,
                note: r.get(2)?,
                created: r.get(3)?,
                current: Some(version) == current,
            })
        })?;
        Ok(rows.collect::<Result<Vec<_>, _>>()?)
    }

    /// Machines with a calibration.
    pub fn machines(&self) -> Result<Vec<String>, StoreError> {
        let mut st = self
            .conn
            .prepare("SELECT machine FROM current ORDER BY machine")?;
        let rows = st.query_map([], |r| r.get(0))?;
        Ok(rows.collect::<Result<Vec<_>, _>>()?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn versions_survive_reopening() {
        let dir = std::env::temp_dir().join(format!("scancorrd-store-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
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
        assert_eq!(s.get("m1", 1).unwrap().unwrap().version, 1);
        std::fs::remove_dir_all(&dir).ok();
    }
}
