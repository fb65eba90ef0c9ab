//! The file read record by record: framing, the length limits a record must keep, CRCs over
//! file ranges; the records of a chunk's data.

use super::*;

/// The file, read record by record.
pub(super) struct Source {
    pub(super) path: PathBuf,
    pub(super) file: BufReader<File>,
    pub(super) pos: u64,
    pub(super) len: u64,
    pub(super) buf: Vec<u8>,
}

pub(super) enum Next {
    /// A whole record is in `buf` (opcode, length, body); it ends at `end`.
    Record { op: u8, end: u64 },
    /// `pos` is the limit: no more records.
    End,
    /// The record at `pos` is incomplete: it extends beyond the limit.
    Cut(String),
    /// The record at `pos` claims more bytes than the reader accepts.
    TooLong(String),
}

impl Source {
    pub(super) fn io(&self, error: std::io::Error) -> BagError {
        BagError::Io {
            path: self.path.clone(),
            error,
        }
    }

    pub(super) fn read_at(&mut self, offset: u64, n: usize) -> Result<&[u8]> {
        if offset != self.pos {
            self.file
                .seek(SeekFrom::Start(offset))
                .map_err(|e| self.io(e))?;
        }
        self.buf.resize(n, 0);
        let r = self.file.read_exact(&mut self.buf);
        // After a failed read the position is unknown: force a seek next time.
        self.pos = if r.is_ok() {
            offset + n as u64
        } else {
            u64::MAX
        };
        r.map_err(|e| self.io(e))?;
        Ok(&self.buf)
    }

    /// Adds the bytes `start..end` of the file to `crc`.
    pub(super) fn hash_range(&mut self, start: u64, end: u64, crc: &mut Crc32) -> Result<()> {
        let mut at = start;
        while at < end {
            let n = (end - at).min(HASH_BLOCK);
            crc.update(self.read_at(at, n as usize)?);
            at += n;
        }
        Ok(())
    }

    /// Reads the record at `pos` whose bytes must end by `limit`.
    pub(super) fn next_record(&mut self, pos: u64, limit: u64) -> Result<Next> {
        if pos >= limit {
            return Ok(Next::End);
        }
        let avail = limit - pos;
        if avail < 9 {
            return Ok(Next::Cut(format!(
                "{avail} stray bytes at offset {pos}, not a whole record"
            )));
        }
        let head = self.read_at(pos, 9)?;
        let op = head[0];
        let len = u64::from_le_bytes(head[1..9].try_into().unwrap_or([0xff; 8]));
        if len > avail - 9 {
            return Ok(Next::Cut(format!(
                "record (opcode {op:#04x}) at offset {pos} needs {len} bytes, only {} remain",
                avail - 9
            )));
        }
        if len > RECORD_LIMIT {
            return Ok(Next::TooLong(format!(
                "record (opcode {op:#04x}) at offset {pos} is {len} bytes long, more than the \
                 {RECORD_LIMIT} the reader accepts"
            )));
        }
        let end = pos + 9 + len;
        self.buf.resize(9 + len as usize, 0);
        let r = self.file.read_exact(&mut self.buf[9..]);
        self.pos = if r.is_ok() { end } else { u64::MAX };
        r.map_err(|e| self.io(e))?;
        Ok(Next::Record { op, end })
    }

    pub(super) fn body(&self) -> &[u8] {
        &self.buf[9..]
    }
}

/// The records of well-formed record data (as [`decode_chunk`] returns): offset in `data`,
/// opcode and body.
pub(super) fn records(data: &[u8]) -> impl Iterator<Item = (usize, u8, &[u8])> {
    let mut rest = data;
    let mut at = 0;
    std::iter::from_fn(move || {
        let (&op, tail) = rest.split_first()?;
        let len = u64::from_le_bytes(tail.get(..8)?.try_into().ok()?);
        let body = tail.get(8..)?.get(..usize::try_from(len).ok()?)?;
        rest = &tail[8 + body.len()..];
        let start = at;
        at += 9 + body.len();
        Some((start, op, body))
    })
}
