//! Checks a record body against the MCAP field layout of its record type before the `mcap`
//! crate parses it.
//!
//! `mcap` reads a string's `uint32` length prefix and reserves that many bytes before it checks
//! that the record holds them, so a few hostile bytes (a prefix of 2^32 − 1) make it allocate
//! gigabytes. [`parse`] first walks the body with the layout of its record type — every fixed
//! field, string, byte array, map and array must fit inside the body (and every map or array
//! entry inside its map or array) — and hands it to [`mcap::parse_record`] only when it does.
use mcap::records::{op, Record};
use mcap::McapError;

/// One field of a record body, as the MCAP spec lays it out.
#[derive(Clone, Copy)]
enum Field {
    /// A little-endian integer of this many bytes.
    Int(&'static str, usize),
    /// `uint32` length, then that many (UTF-8) bytes.
    Str(&'static str),
    /// `uint32` length, then that many bytes.
    Bytes32(&'static str),
    /// `uint64` length, then that many bytes.
    Bytes64(&'static str),
    /// `uint32` length in bytes, then (string, string) entries filling exactly that length.
    StrMap(&'static str),
    /// `uint32` length in bytes, then entries of this many bytes each filling exactly that
    /// length (integer maps and arrays of fixed-size entries).
    Entries(&'static str, usize),
}

use Field::*;

/// The name and field layout of the record type `opcode`; `None` for opcodes `mcap` does not
/// parse (unknown records are passed through as bytes).
fn layout(opcode: u8) -> Option<(&'static str, &'static [Field])> {
    Some(match opcode {
        op::HEADER => ("header", &[Str("profile"), Str("library")]),
        op::FOOTER => (
            "footer",
            &[
                Int("summary_start", 8),
                Int("summary_offset_start", 8),
                Int("summary_crc", 4),
            ],
        ),
        op::SCHEMA => (
            "schema",
            &[Int("id", 2), Str("name"), Str("encoding"), Bytes32("data")],
        ),
        op::CHANNEL => (
            "channel",
            &[
                Int("id", 2),
                Int("schema_id", 2),
                Str("topic"),
                Str("message_encoding"),
                StrMap("metadata"),
            ],
        ),
        op::MESSAGE => (
            "message",
            &[
                Int("channel_id", 2),
                Int("sequence", 4),
                Int("log_time", 8),
                Int("publish_time", 8),
            ],
        ),
        op::CHUNK => (
            "chunk",
            &[
                Int("message_start_time", 8),
                Int("message_end_time", 8),
                Int("uncompressed_size", 8),
                Int("uncompressed_crc", 4),
                Str("compression"),
                Bytes64("records"),
            ],
        ),
        op::MESSAGE_INDEX => (
            "message index",
            &[Int("channel_id", 2), Entries("records", 8 + 8)],
        ),
        op::CHUNK_INDEX => (
            "chunk index",
            &[
                Int("message_start_time", 8),
                Int("message_end_time", 8),
                Int("chunk_start_offset", 8),
                Int("chunk_length", 8),
                Entries("message_index_offsets", 2 + 8),
                Int("message_index_length", 8),
                Str("compression"),
                Int("compressed_size", 8),
                Int("uncompressed_size", 8),
            ],
        ),
        op::ATTACHMENT => (
            "attachment",
            &[
                Int("log_time", 8),
                Int("create_time", 8),
                Str("name"),
                Str("media_type"),
                Bytes64("data"),
                Int("crc", 4),
            ],
        ),
        op::ATTACHMENT_INDEX => (
            "attachment index",
            &[
                Int("offset", 8),
                Int("length", 8),
                Int("log_time", 8),
                Int("create_time", 8),
                Int("data_size", 8),
                Str("name"),
                Str("media_type"),
            ],
        ),
        op::STATISTICS => (
            "statistics",
            &[
                Int("message_count", 8),
                Int("schema_count", 2),
                Int("channel_count", 4),
                Int("attachment_count", 4),
                Int("metadata_count", 4),
                Int("chunk_count", 4),
                Int("message_start_time", 8),
                Int("message_end_time", 8),
                Entries("channel_message_counts", 2 + 8),
            ],
        ),
        op::METADATA => ("metadata", &[Str("name"), StrMap("metadata")]),
        op::METADATA_INDEX => (
            "metadata index",
            &[Int("offset", 8), Int("length", 8), Str("name")],
        ),
        op::SUMMARY_OFFSET => (
            "summary offset",
            &[
                Int("group_opcode", 1),
                Int("group_start", 8),
                Int("group_length", 8),
            ],
        ),
        op::DATA_END => ("data end", &[Int("data_section_crc", 4)]),
        _ => return None,
    })
}

/// A cursor over a record body, or over a map inside it, that says which field does not fit.
struct Walk<'a> {
    record: &'static str,
    /// `record body` or `map`.
    scope: &'static str,
    scope_len: usize,
    rest: &'a [u8],
}

impl<'a> Walk<'a> {
    fn new(record: &'static str, scope: &'static str, bytes: &'a [u8]) -> Self {
        Walk {
            record,
            scope,
            scope_len: bytes.len(),
            rest: bytes,
        }
    }

    fn take(&mut self, n: u64) -> Option<&'a [u8]> {
        let n = usize::try_from(n).ok().filter(|&n| n <= self.rest.len())?;
        let (head, tail) = self.rest.split_at(n);
        self.rest = tail;
        Some(head)
    }

    fn short(&self, what: std::fmt::Arguments<'_>) -> String {
        format!(
            "{} record: {what}, but only {} bytes of the {}-byte {} remain",
            self.record,
            self.rest.len(),
            self.scope_len,
            self.scope
        )
    }

    /// A little-endian integer of `n` bytes.
    fn int(&mut self, field: &dyn std::fmt::Display, n: usize) -> Result<u64, String> {
        match self.take(n as u64) {
            Some(b) => Ok(b.iter().rev().fold(0u64, |v, &x| v << 8 | u64::from(x))),
            None => Err(self.short(format_args!("field {field} needs {n} bytes"))),
        }
    }

    /// A length prefix of `n` bytes and the bytes it counts.
    fn prefixed(&mut self, field: &dyn std::fmt::Display, n: usize) -> Result<&'a [u8], String> {
        let len = match self.take(n as u64) {
            Some(b) => b.iter().rev().fold(0u64, |v, &x| v << 8 | u64::from(x)),
            None => {
                return Err(self.short(format_args!(
                    "the {n}-byte length prefix of field {field} does not fit"
                )))
            }
        };
        match self.take(len) {
            Some(b) => Ok(b),
            None => Err(self.short(format_args!("field {field} has length prefix {len}"))),
        }
    }
}

/// A field name for messages: `` `profile` ``, `` `metadata` entry 3 value ``.
struct Name<'a>(&'a str, Option<(usize, &'a str)>);

impl std::fmt::Display for Name<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "`{}`", self.0)?;
        if let Some((i, part)) = self.1 {
            write!(f, " entry {i} {part}")?;
        }
        Ok(())
    }
}

/// Checks that every field of the record body `body` of type `opcode` fits inside it. `Err`
/// names the record type and the field, e.g. ``header record: field `profile` has length
/// prefix 4294901768, but only 41 bytes of the 45-byte record body remain``.
pub(crate) fn check(opcode: u8, body: &[u8]) -> Result<(), String> {
    let Some((record, fields)) = layout(opcode) else {
        return Ok(());
    };
    let mut w = Walk::new(record, "record body", body);
    for &field in fields {
        match field {
            Int(name, n) => {
                w.int(&Name(name, None), n)?;
            }
            Str(name) | Bytes32(name) => {
                w.prefixed(&Name(name, None), 4)?;
            }
            Bytes64(name) => {
                w.prefixed(&Name(name, None), 8)?;
            }
            StrMap(name) => {
                let mut m = Walk::new(record, "map", w.prefixed(&Name(name, None), 4)?);
                let mut i = 0usize;
                while !m.rest.is_empty() {
                    m.prefixed(&Name(name, Some((i, "key"))), 4)?;
                    m.prefixed(&Name(name, Some((i, "value"))), 4)?;
                    i += 1;
                }
            }
            Entries(name, size) => {
                let entries = w.prefixed(&Name(name, None), 4)?;
                if entries.len() % size != 0 {
                    return Err(format!(
                        "{record} record: field `{name}` holds {} bytes, not a whole number of \
                         {size}-byte entries",
                        entries.len()
                    ));
                }
            }
        }
    }
    Ok(())
}

/// Why a record body was not parsed.
#[derive(Debug)]
pub(crate) enum RecordError {
    /// A field does not fit inside the body: the record was not handed to `mcap`.
    Layout(String),
    /// `mcap` rejected the record.
    Mcap(McapError),
}

impl std::fmt::Display for RecordError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            RecordError::Layout(reason) => f.write_str(reason),
            RecordError::Mcap(e) => e.fmt(f),
        }
    }
}

/// [`mcap::parse_record`], after [`check`] found every field inside the body. The only way the
/// reader parses record bodies.
pub(crate) fn parse(opcode: u8, body: &[u8]) -> Result<Record<'_>, RecordError> {
    check(opcode, body).map_err(RecordError::Layout)?;
    mcap::parse_record(opcode, body).map_err(RecordError::Mcap)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn string(s: &str) -> Vec<u8> {
        let mut v = (s.len() as u32).to_le_bytes().to_vec();
        v.extend_from_slice(s.as_bytes());
        v
    }

    #[test]
    fn well_formed_records_pass_and_parse() {
        let header = [string("scancorr"), string("lib")].concat();
        assert!(matches!(parse(op::HEADER, &header), Ok(Record::Header(_))));
        let map = [string("k"), string("v")].concat();
        let channel = [
            vec![1, 0, 1, 0],
            string("cmm/m1/raw/scale"),
            string("protobuf"),
            (map.len() as u32).to_le_bytes().to_vec(),
            map,
        ]
        .concat();
        assert!(matches!(
            parse(op::CHANNEL, &channel),
            Ok(Record::Channel(_))
        ));
        let stats = [vec![0; 8 + 2 + 4 * 4 + 16], vec![10, 0, 0, 0], vec![0; 10]].concat();
        assert!(matches!(
            parse(op::STATISTICS, &stats),
            Ok(Record::Statistics(_))
        ));
        // Unknown records and trailing bytes (fields of a future MCAP version) are fine.
        assert!(check(0x80, &[1, 2, 3]).is_ok());
        assert!(check(op::DATA_END, &[0; 8]).is_ok());
    }

    #[test]
    fn oversized_prefixes_are_rejected_before_mcap_sees_them() {
        let mut header = string("x");
        header[..4].copy_from_slice(&u32::MAX.to_le_bytes());
        let e = check(op::HEADER, &header).unwrap_err();
        assert!(e.contains("header record: field `profile`"), "{e}");
        assert!(e.contains("4294967295"), "{e}");
        assert!(matches!(
            parse(op::HEADER, &header),
            Err(RecordError::Layout(_))
        ));

        let map = [u32::MAX.to_le_bytes().to_vec(), b"k".to_vec()].concat();
        let md = [
            string("run"),
            (map.len() as u32).to_le_bytes().to_vec(),
            map,
        ]
        .concat();
        let e = check(op::METADATA, &md).unwrap_err();
        assert!(e.contains("field `metadata` entry 0 key"), "{e}");
        assert!(e.contains("5-byte map"), "{e}");

        let schema = [vec![1, 0], string("n"), string("protobuf"), vec![0xff; 4]].concat();
        let e = check(op::SCHEMA, &schema).unwrap_err();
        assert!(e.contains("field `data`"), "{e}");

        let stats = [vec![0; 42], vec![9, 0, 0, 0], vec![0; 9]].concat();
        let e = check(op::STATISTICS, &stats).unwrap_err();
        assert!(e.contains("whole number"), "{e}");

        let e = check(op::FOOTER, &[0; 19]).unwrap_err();
        assert!(e.contains("`summary_crc`"), "{e}");
        assert!(check(op::ATTACHMENT, &[0; 8 + 8 + 4 + 4 + 8 + 3]).is_err());
        assert!(check(op::ATTACHMENT, &[0; 8 + 8 + 4 + 4 + 8 + 4]).is_ok());
    }
}
