//! Conversion between the wire contract (`scancorr.v1`) and the core's types.
//!
//! Pure functions: bytes or prost messages in, core samples out, and back. The live service,
//! the bag tools and the simulator all convert here, so a point means the same everywhere.

use crate::corrector::Corrector;
use crate::sample::*;
use scancorr_proto::v1;
use scancorr_proto::Message;

/// Why a payload could not be turned into samples.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum WireError {
    /// The bytes are not the expected protobuf message.
    #[error("malformed {message}: {reason}")]
    Malformed {
        /// Expected message.
        message: &'static str,
        /// Decoder's complaint.
        reason: String,
    },
    /// A batch with no samples.
    #[error("empty {0}")]
    Empty(&'static str),
    /// A batch that names another stream than the key it came on (v1.1 stream tag).
    #[error("a {found} batch on the {expected} stream")]
    WrongStream {
        /// The stream of the key.
        expected: &'static str,
        /// The stream the batch names.
        found: String,
    },
    /// A batch without the v1.1 stream tag where one is required.
    #[error(
        "{0} without its stream tag (a producer older than scancorr.v1.1, or another message type)"
    )]
    Untagged(&'static str),
}

/// Whether a raw batch must carry its v1.1 stream tag.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Tags {
    /// A batch without the tag is refused ([`WireError::Untagged`]): the live service, where
    /// nothing but the key says what a payload is.
    Require,
    /// A batch without the tag is taken as the key's stream: bags, whose channel names the
    /// message type, and producers older than v1.1.
    AllowUntagged,
}

/// The v1.1 tag value of a stream.
pub fn stream_kind(stream: StreamId) -> v1::StreamKind {
    match stream {
        StreamId::Command => v1::StreamKind::Command,
        StreamId::Scale => v1::StreamKind::Scale,
        StreamId::Probe => v1::StreamKind::Probe,
        StreamId::Temperature => v1::StreamKind::Temperature,
    }
}

fn check_tag(stream: StreamId, tag: i32, tags: Tags, name: &'static str) -> Result<(), WireError> {
    if tag == stream_kind(stream) as i32 {
        return Ok(());
    }
    if tag == v1::StreamKind::Unspecified as i32 {
        return match tags {
            Tags::AllowUntagged => Ok(()),
            Tags::Require => Err(WireError::Untagged(name)),
        };
    }
    Err(WireError::WrongStream {
        expected: stream.name(),
        found: tag_name(tag),
    })
}

/// A stream tag as a stream name: `distance`, `unknown (9)`.
fn tag_name(tag: i32) -> String {
    v1::StreamKind::try_from(tag)
        .map(|k| {
            k.as_str_name()
                .trim_start_matches("STREAM_KIND_")
                .to_ascii_lowercase()
        })
        .unwrap_or_else(|_| format!("unknown ({tag})"))
}

/// The error of a raw batch of `stream` that prost could not decode: [`WireError::WrongStream`]
/// when the bytes are a well-formed batch of another raw stream that carries that stream's tag
/// (one whose samples lay out their fields differently, e.g. a v1.2 `DistanceBatch` on a scale
/// key), else [`WireError::Malformed`]. Only on this error path are the other types tried.
fn undecodable(
    stream: StreamId,
    bytes: &[u8],
    message: &'static str,
    e: scancorr_proto::prost::DecodeError,
) -> WireError {
    fn tagged_as<M: Message + Default>(
        bytes: &[u8],
        kind: v1::StreamKind,
        tag: fn(&M) -> i32,
    ) -> bool {
        M::decode(bytes).is_ok_and(|m| tag(&m) == kind as i32)
    }
    use v1::StreamKind as K;
    let other = [
        K::Command,
        K::Scale,
        K::Probe,
        K::Temperature,
        K::Distance,
        K::Stage,
    ]
    .into_iter()
    .filter(|&k| k != stream_kind(stream))
    .find(|&k| match k {
        K::Command => tagged_as::<v1::CommandBatch>(bytes, k, |m| m.stream),
        K::Scale => tagged_as::<v1::ScaleBatch>(bytes, k, |m| m.stream),
        K::Probe => tagged_as::<v1::ProbeBatch>(bytes, k, |m| m.stream),
        K::Temperature => tagged_as::<v1::TemperatureBatch>(bytes, k, |m| m.stream),
        K::Distance => tagged_as::<v1::DistanceBatch>(bytes, k, |m| m.stream),
        K::Stage => tagged_as::<v1::StageBatch>(bytes, k, |m| m.stream),
        K::Unspecified => false,
    });
    match other {
        Some(k) => WireError::WrongStream {
            expected: stream.name(),
            found: tag_name(k as i32),
        },
        None => WireError::Malformed {
            message,
            reason: e.to_string(),
        },
    }
}

/// The bytes of a raw batch with its v1.1 stream tag: appended when missing (protobuf merges
/// a field written after the others), refused when it names another stream. For replaying
/// bags recorded before v1.1 into a service that requires the tag.
pub fn tagged(stream: StreamId, bytes: &[u8]) -> Result<std::borrow::Cow<'_, [u8]>, WireError> {
    let tag = match stream {
        StreamId::Command => v1::CommandBatch::decode(bytes).map(|b| b.stream),
        StreamId::Scale => v1::ScaleBatch::decode(bytes).map(|b| b.stream),
        StreamId::Probe => v1::ProbeBatch::decode(bytes).map(|b| b.stream),
        StreamId::Temperature => v1::TemperatureBatch::decode(bytes).map(|b| b.stream),
    }
    .map_err(|e| undecodable(stream, bytes, "raw batch", e))?;
    check_tag(stream, tag, Tags::AllowUntagged, "raw batch")?;
    if tag != 0 {
        return Ok(std::borrow::Cow::Borrowed(bytes));
    }
    let mut v = Vec::with_capacity(bytes.len() + 2);
    v.extend_from_slice(bytes);
    put_u64(2, stream_kind(stream) as u64, &mut v);
    Ok(std::borrow::Cow::Owned(v))
}

/// Decoded samples of one raw message with the machine id each named.
#[derive(Debug, Default, Clone)]
pub struct Decoded {
    /// (machine id, sample) in batch order.
    pub samples: Vec<(String, Sample)>,
}

fn v(x: f64, y: f64, z: f64) -> Vec3 {
    Vec3::new(x, y, z)
}

/// Core sample of a wire command.
pub fn command(s: &v1::CommandSample) -> Sample {
    Sample::Command(CommandSample {
        seq: s.seq,
        t_ns: s.t_ns,
        pos: v(s.x, s.y, s.z),
        arc_center: v(s.arc_cx, s.arc_cy, s.arc_cz),
        arc_radius: s.arc_radius,
        segment_id: s.segment_id,
    })
}

/// Core sample of a wire scale reading.
pub fn scale(s: &v1::ScaleSample) -> Sample {
    Sample::Scale(ScaleSample {
        seq: s.seq,
        t_ns: s.t_ns,
        pos: v(s.x, s.y, s.z),
    })
}

/// Core sample of a wire probe reading.
pub fn probe(s: &v1::ProbeSample) -> Sample {
    Sample::Probe(ProbeSample {
        seq: s.seq,
        t_ns: s.t_ns,
        deflection: v(s.u, s.v, s.w),
        tip_id: s.tip_id,
        head_a1_deg: s.head_a1_deg,
        head_a2_deg: s.head_a2_deg,
    })
}

/// Core sample of a wire temperature.
pub fn temperature(s: &v1::TemperatureSample) -> Sample {
    Sample::Temperature(TemperatureSample {
        seq: s.seq,
        t_ns: s.t_ns,
        sensor: s.sensor.clone(),
        celsius: s.celsius,
    })
}

/// Decodes a raw payload of `stream` into samples.
pub fn decode(stream: StreamId, bytes: &[u8]) -> Result<Decoded, WireError> {
    let mut out = Decoded::default();
    decode_with(stream, bytes, |m, s| out.samples.push((m.to_string(), s)))?;
    Ok(out)
}

/// Decodes a raw payload of one machine: samples naming `machine` are appended to `out`, the
/// number of samples naming another machine is returned. Untagged batches are taken (bags).
pub fn decode_machine(
    stream: StreamId,
    bytes: &[u8],
    machine: &str,
    out: &mut Vec<Sample>,
) -> Result<u64, WireError> {
    decode_machine_tagged(stream, bytes, machine, Tags::AllowUntagged, out)
}

/// [`decode_machine`] with a choice about batches without the v1.1 stream tag.
pub fn decode_machine_tagged(
    stream: StreamId,
    bytes: &[u8],
    machine: &str,
    tags: Tags,
    out: &mut Vec<Sample>,
) -> Result<u64, WireError> {
    decode_machine_each(stream, bytes, machine, tags, |s| out.push(s))
}

/// [`decode_machine_tagged`] handing each sample of `machine` to `f` as it is decoded (a
/// service pushes them straight into its corrector). Nothing is handed to `f` unless the
/// whole batch decodes. Returns how many samples named another machine.
pub fn decode_machine_each(
    stream: StreamId,
    bytes: &[u8],
    machine: &str,
    tags: Tags,
    mut f: impl FnMut(Sample),
) -> Result<u64, WireError> {
    let mut foreign = 0;
    // A batch of packed columns names its machine once, and hands that one name with each
    // sample: compared once.
    let mut last: Option<(*const u8, usize, bool)> = None;
    decode_with_tags(stream, bytes, tags, |m, s| {
        let mine = match last {
            Some((p, n, mine)) if p == m.as_ptr() && n == m.len() => mine,
            _ => {
                let mine = m == machine;
                last = Some((m.as_ptr(), m.len(), mine));
                mine
            }
        };
        if mine {
            f(s)
        } else {
            foreign += 1
        }
    })?;
    Ok(foreign)
}

/// Decodes a raw payload and hands each (machine id, sample) to `f`, in batch order. Untagged
/// batches are taken; a batch tagged with another stream is refused.
pub fn decode_with(
    stream: StreamId,
    bytes: &[u8],
    f: impl FnMut(&str, Sample),
) -> Result<usize, WireError> {
    decode_with_tags(stream, bytes, Tags::AllowUntagged, f)
}

/// [`decode_with`] with a choice about batches without the v1.1 stream tag. Nothing is handed
/// to `f` unless the whole batch decodes and its tag fits. Reads both forms of a batch: one
/// message per sample (v1.0–v1.2) and packed columns (v1.3), which name the machine once.
pub fn decode_with_tags(
    stream: StreamId,
    bytes: &[u8],
    tags: Tags,
    mut f: impl FnMut(&str, Sample),
) -> Result<usize, WireError> {
    if let Some(n) = plain_packed(stream, bytes, tags, &mut f) {
        return n;
    }
    let malformed =
        |message, e: scancorr_proto::prost::DecodeError| undecodable(stream, bytes, message, e);
    let (n, name) = match stream {
        StreamId::Command => {
            const NAME: &str = "CommandBatch";
            let b = v1::CommandBatch::decode(bytes).map_err(|e| malformed(NAME, e))?;
            check_tag(stream, b.stream, tags, NAME)?;
            let n = match packed(NAME, b.samples.len(), &b.columns)? {
                Some(c) => command_columns(c, &mut f)?,
                None => {
                    b.samples.iter().for_each(|s| f(&s.machine_id, command(s)));
                    b.samples.len()
                }
            };
            (n, NAME)
        }
        StreamId::Scale => {
            const NAME: &str = "ScaleBatch";
            let b = v1::ScaleBatch::decode(bytes).map_err(|e| malformed(NAME, e))?;
            check_tag(stream, b.stream, tags, NAME)?;
            let n = match packed(NAME, b.samples.len(), &b.columns)? {
                Some(c) => scale_columns(c, &mut f)?,
                None => {
                    b.samples.iter().for_each(|s| f(&s.machine_id, scale(s)));
                    b.samples.len()
                }
            };
            (n, NAME)
        }
        StreamId::Probe => {
            const NAME: &str = "ProbeBatch";
            let b = v1::ProbeBatch::decode(bytes).map_err(|e| malformed(NAME, e))?;
            check_tag(stream, b.stream, tags, NAME)?;
            let n = match packed(NAME, b.samples.len(), &b.columns)? {
                Some(c) => probe_columns(c, &mut f)?,
                None => {
                    b.samples.iter().for_each(|s| f(&s.machine_id, probe(s)));
                    b.samples.len()
                }
            };
            (n, NAME)
        }
        StreamId::Temperature => {
            const NAME: &str = "TemperatureBatch";
            let b = v1::TemperatureBatch::decode(bytes).map_err(|e| malformed(NAME, e))?;
            check_tag(stream, b.stream, tags, NAME)?;
            let n = match packed(NAME, b.samples.len(), &b.columns)? {
                Some(c) => temperature_columns(c, &mut f)?,
                None => {
                    b.samples
                        .iter()
                        .for_each(|s| f(&s.machine_id, temperature(s)));
                    b.samples.len()
                }
            };
            (n, NAME)
        }
    };
    if n == 0 {
        return Err(WireError::Empty(name));
    }
    Ok(n)
}

/// A plain packed batch (v1.3) of the command, scale or probe stream read straight from its
/// bytes, without prost's column vectors (allocated and grown per message): its samples
/// handed to `f`, or its error. `None` for anything else — per-sample messages, a field
/// repeated, unpacked or unknown, bytes that are not protobuf — which [`decode_with_tags`]
/// leaves to prost, so what this accepts decodes exactly as prost decodes it.
fn plain_packed(
    stream: StreamId,
    bytes: &[u8],
    tags: Tags,
    f: &mut impl FnMut(&str, Sample),
) -> Option<Result<usize, WireError>> {
    let (name, columns) = match stream {
        StreamId::Command => ("CommandBatch", 11),
        StreamId::Scale => ("ScaleBatch", 6),
        StreamId::Probe => ("ProbeBatch", 9),
        StreamId::Temperature => return None,
    };
    let (tag, machine, c) = packed_fields(bytes, columns)?;
    if let Err(e) = check_tag(stream, tag, tags, name) {
        return Some(Err(e));
    }
    let n = varints(c[2])?;
    // Below, every column holds `n` values (checked first), so no `next()` comes up short
    // and `f` sees the whole batch or nothing.
    let n = match stream {
        StreamId::Command => {
            let counts = [
                ("t_ns", varints(c[3])?),
                ("x", doubles(c[4])?),
                ("y", doubles(c[5])?),
                ("z", doubles(c[6])?),
                ("arc_cx", doubles(c[7])?),
                ("arc_cy", doubles(c[8])?),
                ("arc_cz", doubles(c[9])?),
                ("arc_radius", doubles(c[10])?),
                ("segment_id", varints(c[11])?),
            ];
            if let Err(e) = column_len(name, n, &counts) {
                return Some(Err(e));
            }
            let (mut seq, mut t, mut seg) = (Varints(c[2]), Varints(c[3]), Varints(c[11]));
            let [x, y, z, cx, cy, cz, r] = [4, 5, 6, 7, 8, 9, 10].map(|k| Doubles::new(c[k], n));
            for i in 0..n {
                f(
                    machine,
                    Sample::Command(CommandSample {
                        seq: seq.next()?,
                        t_ns: t.next()? as i64,
                        pos: v(x.at(i), y.at(i), z.at(i)),
                        arc_center: v(cx.at(i), cy.at(i), cz.at(i)),
                        arc_radius: r.at(i),
                        segment_id: seg.next()? as u32,
                    }),
                );
            }
            n
        }
        StreamId::Scale => {
            let counts = [
                ("t_ns", varints(c[3])?),
                ("x", doubles(c[4])?),
                ("y", doubles(c[5])?),
                ("z", doubles(c[6])?),
            ];
            if let Err(e) = column_len(name, n, &counts) {
                return Some(Err(e));
            }
            let (mut seq, mut t) = (Varints(c[2]), Varints(c[3]));
            let [x, y, z] = [4, 5, 6].map(|k| Doubles::new(c[k], n));
            for i in 0..n {
                f(
                    machine,
                    Sample::Scale(ScaleSample {
                        seq: seq.next()?,
                        t_ns: t.next()? as i64,
                        pos: v(x.at(i), y.at(i), z.at(i)),
                    }),
                );
            }
            n
        }
        _ => {
            let counts = [
                ("t_ns", varints(c[3])?),
                ("u", doubles(c[4])?),
                ("v", doubles(c[5])?),
                ("w", doubles(c[6])?),
                ("tip_id", varints(c[7])?),
                ("head_a1_deg", doubles(c[8])?),
                ("head_a2_deg", doubles(c[9])?),
            ];
            if let Err(e) = column_len(name, n, &counts) {
                return Some(Err(e));
            }
            let (mut seq, mut t, mut tip) = (Varints(c[2]), Varints(c[3]), Varints(c[7]));
            let [u, vv, w, a1, a2] = [4, 5, 6, 8, 9].map(|k| Doubles::new(c[k], n));
            for i in 0..n {
                f(
                    machine,
                    Sample::Probe(ProbeSample {
                        seq: seq.next()?,
                        t_ns: t.next()? as i64,
                        deflection: v(u.at(i), vv.at(i), w.at(i)),
                        tip_id: tip.next()? as u32,
                        head_a1_deg: a1.at(i),
                        head_a2_deg: a2.at(i),
                    }),
                );
            }
            n
        }
    };
    Some(if n == 0 {
        Err(WireError::Empty(name))
    } else {
        Ok(n)
    })
}

/// The stream tag, machine id and column bytes (indexed by field number, up to `columns`) of
/// a batch that holds its columns once and nothing but its stream tag besides, every column
/// packed and written once; `None` for any other batch.
fn packed_fields(bytes: &[u8], columns: usize) -> Option<(i32, &str, [&[u8]; 12])> {
    use scancorr_proto::prost::encoding::decode_varint;
    /// The next field: its number and wire type, its bytes (length-delimited) or value.
    fn field<'a>(b: &mut &'a [u8]) -> Option<(u64, Result<&'a [u8], u64>)> {
        let key = decode_varint(b).ok()?;
        match key & 7 {
            0 => Some((key >> 3, Err(decode_varint(b).ok()?))),
            2 => {
                let len = usize::try_from(decode_varint(b).ok()?).ok()?;
                let body = b.get(..len)?;
                *b = &b[len..];
                Some((key >> 3, Ok(body)))
            }
            _ => None,
        }
    }
    let (mut b, mut tag, mut cols) = (bytes, 0, None);
    while !b.is_empty() {
        match field(&mut b)? {
            // The last stream tag counts, as in prost.
            (2, Err(t)) => tag = t as i32,
            (3, Ok(c)) if cols.is_none() => cols = Some(c),
            _ => return None,
        }
    }
    let mut b = cols?;
    let (mut machine, mut c) = (None, [&[][..]; 12]);
    let mut seen = 0u16;
    while !b.is_empty() {
        let (k, Ok(body)) = field(&mut b)? else {
            return None;
        };
        let k = usize::try_from(k)
            .ok()
            .filter(|k| (1..=columns).contains(k))?;
        if seen & 1 << k != 0 {
            return None;
        }
        seen |= 1 << k;
        match k {
            1 => machine = Some(std::str::from_utf8(body).ok()?),
            k => c[k] = body,
        }
    }
    Some((tag, machine.unwrap_or(""), c))
}

/// Bit 7 of every byte of a word: where a varint's byte says that more follow.
const CONTINUES: u64 = 0x8080_8080_8080_8080;

/// How many varints a packed column holds; `None` when one is not a varint. The same
/// refusals as prost's `decode_varint`: a value ends at a byte below 0x80 within ten bytes, and
/// the tenth byte of a ten-byte value is 0 or 1 (no overflow of 64 bits). One pass over the
/// bytes, no value computed: a column is counted before any of it is handed out. Eight bytes
/// are read at a time: the values ending in them are counted at once, and only the first
/// can be too long (the others begin inside the word, so they are at most seven bytes).
fn varints(b: &[u8]) -> Option<usize> {
    // `run`: continuation bytes since the last value ended.
    let (mut n, mut run) = (0, 0);
    let (words, rest) = b.as_chunks::<8>();
    for w in words {
        let w = u64::from_le_bytes(*w);
        // Bit 7 of byte k set when byte k ends a value.
        let ends = !w & CONTINUES;
        if ends == 0 {
            run += 8;
            if run >= 10 {
                return None;
            }
            continue;
        }
        let first = ends.trailing_zeros() as usize / 8;
        let before = run + first;
        if before >= 10 || (before == 9 && (w >> (8 * first)) as u8 > 1) {
            return None;
        }
        n += ends.count_ones() as usize;
        run = 7 - (63 - ends.leading_zeros() as usize) / 8;
    }
    for &x in rest {
        if x < 0x80 {
            if run == 9 && x > 1 {
                return None;
            }
            n += 1;
            run = 0;
        } else {
            run += 1;
            if run == 10 {
                return None;
            }
        }
    }
    (run == 0).then_some(n)
}

/// The next varint of `b` (prost's value and refusals, see [`varints`]), inline: the values of
/// a column are read one per sample. A value of up to eight bytes (below 2⁵⁶: every seq, and a
/// controller time in ns under 2.2 years) is read from one word with no loop; a longer one,
/// or one in the column's last seven bytes, byte by byte.
#[inline(always)]
fn next_varint(b: &mut &[u8]) -> Option<u64> {
    if let Some((w, _)) = b.split_first_chunk::<8>() {
        let w = u64::from_le_bytes(*w);
        let ends = !w & CONTINUES;
        if ends != 0 {
            // The value's bytes (up to its first end), their continuation bits cleared, then
            // the 7-bit groups packed: pairs into 14 bits, fours into 28, eight into 56.
            let x = w & (ends ^ (ends - 1)) & !CONTINUES;
            let x = (x & 0x007f_007f_007f_007f) | ((x >> 1) & 0x3f80_3f80_3f80_3f80);
            let x = (x & 0x0000_3fff_0000_3fff) | ((x >> 2) & 0x0fff_c000_0fff_c000);
            let x = (x & 0x0000_0000_0fff_ffff) | ((x >> 4) & 0x00ff_ffff_f000_0000);
            *b = &b[ends.trailing_zeros() as usize / 8 + 1..];
            return Some(x);
        }
    }
    let mut v = 0u64;
    for (i, &x) in b.iter().enumerate().take(10) {
        v |= u64::from(x & 0x7f) << (7 * i);
        if x < 0x80 {
            if i == 9 && x > 1 {
                return None;
            }
            *b = &b[i + 1..];
            return Some(v);
        }
    }
    None
}

/// How many doubles a packed column holds; `None` when its length is not a multiple of 8.
fn doubles(b: &[u8]) -> Option<usize> {
    let values = b.chunks_exact(8);
    values.remainder().is_empty().then_some(values.len())
}

/// The values of a packed varint column (checked by [`varints`]).
struct Varints<'a>(&'a [u8]);

impl Iterator for Varints<'_> {
    type Item = u64;
    #[inline]
    fn next(&mut self) -> Option<u64> {
        next_varint(&mut self.0)
    }
}

/// The values of a packed double column (checked by [`doubles`]), read by index: a zip of
/// seven column iterators was not inlined, and handing its tuple back through memory stalled
/// each sample's loads (a profile of the service put it at a quarter of decoding).
struct Doubles<'a>(&'a [[u8; 8]]);

impl<'a> Doubles<'a> {
    /// The first `n` values of `b` (as many as its checked length holds, at most).
    fn new(b: &'a [u8], n: usize) -> Self {
        let (values, _) = b.as_chunks::<8>();
        Self(&values[..n.min(values.len())])
    }

    /// Value `i`; a column's length was checked against the batch's count, so `i` is in it.
    #[inline(always)]
    fn at(&self, i: usize) -> f64 {
        f64::from_le_bytes(self.0[i])
    }
}

/// The columns of a packed batch (v1.3), `None` for a batch of one message per sample; a batch
/// with both is malformed.
fn packed<'a, C>(
    message: &'static str,
    samples: usize,
    columns: &'a Option<C>,
) -> Result<Option<&'a C>, WireError> {
    match columns {
        Some(_) if samples > 0 => Err(WireError::Malformed {
            message,
            reason: "both per-sample messages (`samples`) and packed columns (`columns`)".into(),
        }),
        c => Ok(c.as_ref()),
    }
}

/// The number of samples of a packed batch, `seq`'s length, after checking that every other
/// column holds as many values.
fn column_len(
    message: &'static str,
    seq: usize,
    columns: &[(&str, usize)],
) -> Result<usize, WireError> {
    match columns.iter().find(|(_, len)| *len != seq) {
        Some((name, len)) => Err(WireError::Malformed {
            message,
            reason: format!("column `{name}` holds {len} values for {seq} samples (`seq`)"),
        }),
        None => Ok(seq),
    }
}

fn command_columns(
    c: &v1::CommandColumns,
    f: &mut impl FnMut(&str, Sample),
) -> Result<usize, WireError> {
    let n = column_len(
        "CommandBatch",
        c.seq.len(),
        &[
            ("t_ns", c.t_ns.len()),
            ("x", c.x.len()),
            ("y", c.y.len()),
            ("z", c.z.len()),
            ("arc_cx", c.arc_cx.len()),
            ("arc_cy", c.arc_cy.len()),
            ("arc_cz", c.arc_cz.len()),
            ("arc_radius", c.arc_radius.len()),
            ("segment_id", c.segment_id.len()),
        ],
    )?;
    for i in 0..n {
        f(
            &c.machine_id,
            Sample::Command(CommandSample {
                seq: c.seq[i],
                t_ns: c.t_ns[i],
                pos: v(c.x[i], c.y[i], c.z[i]),
                arc_center: v(c.arc_cx[i], c.arc_cy[i], c.arc_cz[i]),
                arc_radius: c.arc_radius[i],
                segment_id: c.segment_id[i],
            }),
        );
    }
    Ok(n)
}

fn scale_columns(
    c: &v1::ScaleColumns,
    f: &mut impl FnMut(&str, Sample),
) -> Result<usize, WireError> {
    let n = column_len(
        "ScaleBatch",
        c.seq.len(),
        &[
            ("t_ns", c.t_ns.len()),
            ("x", c.x.len()),
            ("y", c.y.len()),
            ("z", c.z.len()),
        ],
    )?;
    for i in 0..n {
        f(
            &c.machine_id,
            Sample::Scale(ScaleSample {
                seq: c.seq[i],
                t_ns: c.t_ns[i],
                pos: v(c.x[i], c.y[i], c.z[i]),
            }),
        );
    }
    Ok(n)
}

fn probe_columns(
    c: &v1::ProbeColumns,
    f: &mut impl FnMut(&str, Sample),
) -> Result<usize, WireError> {
    let n = column_len(
        "ProbeBatch",
        c.seq.len(),
        &[
            ("t_ns", c.t_ns.len()),
            ("u", c.u.len()),
            ("v", c.v.len()),
            ("w", c.w.len()),
            ("tip_id", c.tip_id.len()),
            ("head_a1_deg", c.head_a1_deg.len()),
            ("head_a2_deg", c.head_a2_deg.len()),
        ],
    )?;
    for i in 0..n {
        f(
            &c.machine_id,
            Sample::Probe(ProbeSample {
                seq: c.seq[i],
                t_ns: c.t_ns[i],
                deflection: v(c.u[i], c.v[i], c.w[i]),
                tip_id: c.tip_id[i],
                head_a1_deg: c.head_a1_deg[i],
                head_a2_deg: c.head_a2_deg[i],
            }),
        );
    }
    Ok(n)
}

fn temperature_columns(
    c: &v1::TemperatureColumns,
    f: &mut impl FnMut(&str, Sample),
) -> Result<usize, WireError> {
    let n = column_len(
        "TemperatureBatch",
        c.seq.len(),
        &[
            ("t_ns", c.t_ns.len()),
            ("sensor", c.sensor.len()),
            ("celsius", c.celsius.len()),
        ],
    )?;
    for i in 0..n {
        f(
            &c.machine_id,
            Sample::Temperature(TemperatureSample {
                seq: c.seq[i],
                t_ns: c.t_ns[i],
                sensor: c.sensor[i].clone(),
                celsius: c.celsius[i],
            }),
        );
    }
    Ok(n)
}

/// The core stream of a raw wire stream.
pub fn stream_id(s: scancorr_proto::Stream) -> Option<StreamId> {
    use scancorr_proto::Stream as S;
    match s {
        S::Command => Some(StreamId::Command),
        S::Scale => Some(StreamId::Scale),
        S::Probe => Some(StreamId::Probe),
        S::Temperature => Some(StreamId::Temperature),
        _ => None,
    }
}

fn v3(p: &Vec3) -> Option<v1::Vec3> {
    Some(v1::Vec3 {
        x: p.x,
        y: p.y,
        z: p.z,
    })
}

/// Wire form of a corrected point; `effect_ids` from [`Corrector::effect_ids`].
pub fn point(p: &CorrectedPoint, machine: &str, effect_ids: &[String]) -> v1::CorrectedPoint {
    v1::CorrectedPoint {
        machine_id: machine.to_string(),
        seq: p.seq,
        t_ns: p.t_ns,
        sample_seq: p.sample_seq,
        surface: v3(&p.surface),
        tip_center: v3(&p.tip_center),
        normal: v3(&p.normal),
        corrections: p
            .corrections
            .iter()
            .zip(effect_ids)
            .map(|(c, id)| v1::Correction {
                effect: id.clone(),
                dx: c.x,
                dy: c.y,
                dz: c.z,
            })
            .collect(),
        calibration_version: p.calibration_version,
        estimator_valid: p.estimator_valid,
        segment_id: p.segment_id,
        tip_id: p.tip_id,
    }
}

/// Encodes a batch of points and appends it to `buf` as one packed block (v1.4), written
/// without building the message (no allocation — the live service's hot path). The machine
/// and the effect ids are written once, each field of the points as one packed column. Every
/// length is known before its field is written, so the block's room is made once and written
/// front to back. When every point has one correction per effect (as a corrector's points
/// do) these are the bytes of `CorrectedPointBatch { columns: [pack(ps)] }.encode_to_vec()`
/// (see [`scancorr_proto::points::pack`]; a test checks them against prost's); a point with
/// fewer is padded with zero corrections. Appending to a buffer that already holds a packed
/// batch gives the batch of both.
pub fn encode_points(
    ps: &[CorrectedPoint],
    machine: &str,
    effect_ids: &[String],
    buf: &mut Vec<u8>,
) {
    if ps.is_empty() {
        return;
    }
    let n = ps.len();
    let e = effect_ids.len();
    // The varint columns' lengths: seq, t_ns, sample_seq, calibration_version,
    // estimator_valid (one byte a point), segment_id, tip_id.
    let mut varints = [0, 0, 0, 0, n, 0, 0];
    for p in ps {
        varints[0] += encoded_len_varint(p.seq);
        varints[1] += encoded_len_varint(p.t_ns as u64);
        varints[2] += encoded_len_varint(p.sample_seq);
        varints[3] += encoded_len_varint(p.calibration_version);
        varints[5] += encoded_len_varint(p.segment_id.into());
        varints[6] += encoded_len_varint(p.tip_id.into());
    }
    const VARINT_TAGS: [u8; 7] = [2, 3, 4, 9, 10, 11, 12];
    let body = str_len(machine)
        + varints.iter().map(|&l| ld_len(l)).sum::<usize>()
        + 9 * ld_len(8 * n) + 6 // the keys of tags 16–21 take two bytes
        + effect_ids.iter().map(|id| 1 + ld_len(id.len())).sum::<usize>()
        + if e == 0 { 0 } else { 3 * (1 + ld_len(8 * n * e)) };
    let at = buf.len();
    buf.resize(at + ld_len(body), 0);
    let mut w = Out {
        b: &mut buf[at..],
        n: 0,
    };
    w.key(2, 2);
    w.varint(body as u64);
    w.str(1, machine);
    // Every column's header is written and its room skipped; one pass over the points then
    // fills all the columns at once (a cursor each).
    let mut v = [0usize; 7];
    for (k, (tag, len)) in VARINT_TAGS.into_iter().zip(varints).enumerate() {
        w.key(tag, 2);
        w.varint(len as u64);
        v[k] = w.skip(len);
    }
    let mut d = [0usize; 9];
    for (k, at) in d.iter_mut().enumerate() {
        w.long_key(13 + k as u16, 2);
        w.varint(8 * n as u64);
        *at = w.skip(8 * n);
    }
    for id in effect_ids {
        w.long_key(22, 2);
        w.varint(id.len() as u64);
        w.bytes(id.as_bytes());
    }
    let mut c = [0usize; 3];
    if e > 0 {
        for (k, at) in c.iter_mut().enumerate() {
            w.long_key(23 + k as u16, 2);
            w.varint(8 * (n * e) as u64);
            *at = w.skip(8 * n * e);
        }
    }
    debug_assert_eq!(w.n, w.b.len(), "a block's size was computed wrong");
    let b = &mut *w.b;
    for p in ps {
        put_varint(b, &mut v[0], p.seq);
        put_varint(b, &mut v[1], p.t_ns as u64);
        put_varint(b, &mut v[2], p.sample_seq);
        put_varint(b, &mut v[3], p.calibration_version);
        put_varint(b, &mut v[4], p.estimator_valid.into());
        put_varint(b, &mut v[5], p.segment_id.into());
        put_varint(b, &mut v[6], p.tip_id.into());
        for (k, x) in [p.surface, p.tip_center, p.normal].iter().enumerate() {
            put_f64(b, &mut d[3 * k], x.x);
            put_f64(b, &mut d[3 * k + 1], x.y);
            put_f64(b, &mut d[3 * k + 2], x.z);
        }
        // The corrections, point-major; a point with fewer than `e` (never, from a corrector:
        // one per effect) is padded with zeros so the columns keep their lengths.
        for j in 0..e {
            let x = p.corrections.get(j).copied().unwrap_or_default();
            put_f64(b, &mut c[0], x.x);
            put_f64(b, &mut c[1], x.y);
            put_f64(b, &mut c[2], x.z);
        }
    }
}

/// Writes a varint at `b[*at..]` and moves `at` past it.
#[inline]
fn put_varint(b: &mut [u8], at: &mut usize, mut v: u64) {
    while v >= 0x80 {
        b[*at] = v as u8 | 0x80;
        *at += 1;
        v >>= 7;
    }
    b[*at] = v as u8;
    *at += 1;
}

/// Writes a double (little-endian) at `b[*at..]` and moves `at` past it.
#[inline]
fn put_f64(b: &mut [u8], at: &mut usize, v: f64) {
    b[*at..*at + 8].copy_from_slice(&v.to_le_bytes());
    *at += 8;
}

// Protobuf field writers and sizes for `encode_points`. A singular string skips its default
// (empty) value as proto3 does; a packed column is written whenever it holds a value.
use scancorr_proto::prost::encoding::{encode_varint, encoded_len_varint};

/// A block's room in the output, written front to back.
struct Out<'a> {
    b: &'a mut [u8],
    n: usize,
}

impl Out<'_> {
    fn bytes(&mut self, v: &[u8]) {
        self.b[self.n..self.n + v.len()].copy_from_slice(v);
        self.n += v.len();
    }
    fn key(&mut self, tag: u8, wire_type: u8) {
        self.b[self.n] = tag << 3 | wire_type;
        self.n += 1;
    }
    fn varint(&mut self, v: u64) {
        put_varint(self.b, &mut self.n, v);
    }
    fn str(&mut self, tag: u8, s: &str) {
        if !s.is_empty() {
            self.key(tag, 2);
            self.varint(s.len() as u64);
            self.bytes(s.as_bytes());
        }
    }
    /// The key of any field number (a varint: two bytes from field 16 on).
    fn long_key(&mut self, tag: u16, wire_type: u8) {
        self.varint(u64::from(tag) << 3 | u64::from(wire_type));
    }
    /// Skips `len` bytes (a column's room, filled later); returns where they start.
    fn skip(&mut self, len: usize) -> usize {
        self.n += len;
        self.n - len
    }
}

/// The size of a length-delimited field (key, length, body) of a `body`-byte body.
fn ld_len(body: usize) -> usize {
    1 + encoded_len_varint(body as u64) + body
}
fn str_len(s: &str) -> usize {
    if s.is_empty() {
        0
    } else {
        ld_len(s.len())
    }
}
fn put_u64(tag: u8, v: u64, buf: &mut Vec<u8>) {
    if v != 0 {
        buf.push(tag << 3);
        encode_varint(v, buf);
    }
}

/// Wire form of an alarm.
pub fn alarm(a: &Alarm, machine: &str) -> v1::EstimatorAlarm {
    v1::EstimatorAlarm {
        machine_id: machine.to_string(),
        seq: a.seq,
        t_ns: a.t_ns,
        raised: a.raised,
        axis: match a.axis {
            Axis::X => v1::Axis::X,
            Axis::Y => v1::Axis::Y,
            Axis::Z => v1::Axis::Z,
        } as i32,
        estimated_accel: a.estimated_accel,
        measured_accel: a.measured_accel,
        difference: a.difference,
        threshold: a.threshold,
        action: match a.action {
            AlarmAction::Flag => v1::AlarmAction::Flag,
            AlarmAction::Suspend => v1::AlarmAction::Suspend,
        } as i32,
        calibration_version: a.calibration_version,
    }
}

/// The points of one corrector as a reader gets them from a batch
/// ([`v1::CorrectedPointBatch::into_points`]), one message each.
pub fn points(ps: &[CorrectedPoint], machine: &str, corr: &Corrector) -> Vec<v1::CorrectedPoint> {
    let ids = corr.effect_ids();
    ps.iter().map(|p| point(p, machine, &ids)).collect()
}

/// How a [`Batcher`] lays out the samples of a batch.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Layout {
    /// Packed columns (v1.3): the machine id once per batch, each sample field a column.
    #[default]
    Packed,
    /// One message per sample, each naming the machine (v1.0–v1.2): what producers older
    /// than v1.3 write; for tests that old input is still read.
    PerSample,
}

/// Accumulates core samples of one machine into wire batches of up to `size` samples, as
/// packed columns (v1.3) unless told otherwise ([`Batcher::with_layout`]).
#[derive(Debug)]
pub struct Batcher {
    size: usize,
    layout: Layout,
    command: v1::CommandColumns,
    scale: v1::ScaleColumns,
    probe: v1::ProbeColumns,
    temperature: v1::TemperatureColumns,
}

impl Batcher {
    /// A batcher for `machine` writing packed batches.
    pub fn new(machine: &str, size: usize) -> Batcher {
        let machine_id = machine.to_string();
        Batcher {
            size: size.max(1),
            layout: Layout::Packed,
            command: v1::CommandColumns {
                machine_id: machine_id.clone(),
                ..Default::default()
            },
            scale: v1::ScaleColumns {
                machine_id: machine_id.clone(),
                ..Default::default()
            },
            probe: v1::ProbeColumns {
                machine_id: machine_id.clone(),
                ..Default::default()
            },
            temperature: v1::TemperatureColumns {
                machine_id,
                ..Default::default()
            },
        }
    }

    /// The same batcher writing batches laid out as `layout`.
    pub fn with_layout(self, layout: Layout) -> Batcher {
        Batcher { layout, ..self }
    }

    /// Adds a sample; returns the stream whose batch just became full.
    pub fn push(&mut self, s: &Sample) -> Option<StreamId> {
        let (stream, len) = match s {
            Sample::Command(s) => {
                let c = &mut self.command;
                c.seq.push(s.seq);
                c.t_ns.push(s.t_ns);
                c.x.push(s.pos.x);
                c.y.push(s.pos.y);
                c.z.push(s.pos.z);
                c.arc_cx.push(s.arc_center.x);
                c.arc_cy.push(s.arc_center.y);
                c.arc_cz.push(s.arc_center.z);
                c.arc_radius.push(s.arc_radius);
                c.segment_id.push(s.segment_id);
                (StreamId::Command, c.seq.len())
            }
            Sample::Scale(s) => {
                let c = &mut self.scale;
                c.seq.push(s.seq);
                c.t_ns.push(s.t_ns);
                c.x.push(s.pos.x);
                c.y.push(s.pos.y);
                c.z.push(s.pos.z);
                (StreamId::Scale, c.seq.len())
            }
            Sample::Probe(s) => {
                let c = &mut self.probe;
                c.seq.push(s.seq);
                c.t_ns.push(s.t_ns);
                c.u.push(s.deflection.x);
                c.v.push(s.deflection.y);
                c.w.push(s.deflection.z);
                c.tip_id.push(s.tip_id);
                c.head_a1_deg.push(s.head_a1_deg);
                c.head_a2_deg.push(s.head_a2_deg);
                (StreamId::Probe, c.seq.len())
            }
            Sample::Temperature(s) => {
                let c = &mut self.temperature;
                c.seq.push(s.seq);
                c.t_ns.push(s.t_ns);
                c.sensor.push(s.sensor.clone());
                c.celsius.push(s.celsius);
                (StreamId::Temperature, c.seq.len())
            }
        };
        (len >= self.size).then_some(stream)
    }

    /// Takes the pending batch of `stream` encoded, with the times of its first and last
    /// sample (None when empty).
    pub fn take(&mut self, stream: StreamId) -> Option<(Vec<u8>, i64, i64)> {
        let tag = stream_kind(stream) as i32;
        let layout = self.layout;
        // Each arm encodes the pending columns, then empties them keeping their capacity.
        macro_rules! take {
            ($c:expr, $batch:ident, $per_sample:ident, [$($column:ident),*]) => {{
                let c = &mut $c;
                if c.seq.is_empty() {
                    return None;
                }
                let bytes = encode_batch(layout, tag, c, |c| v1::$batch {
                    stream: tag,
                    samples: $per_sample(c),
                    columns: None,
                });
                let (first, last) = ends(&c.t_ns);
                $(c.$column.clear();)*
                (bytes, first, last)
            }};
        }
        Some(match stream {
            StreamId::Command => take!(
                self.command,
                CommandBatch,
                command_samples,
                [seq, t_ns, x, y, z, arc_cx, arc_cy, arc_cz, arc_radius, segment_id]
            ),
            StreamId::Scale => take!(self.scale, ScaleBatch, scale_samples, [seq, t_ns, x, y, z]),
            StreamId::Probe => take!(
                self.probe,
                ProbeBatch,
                probe_samples,
                [seq, t_ns, u, v, w, tip_id, head_a1_deg, head_a2_deg]
            ),
            StreamId::Temperature => take!(
                self.temperature,
                TemperatureBatch,
                temperature_samples,
                [seq, t_ns, sensor, celsius]
            ),
        })
    }
}

/// A batch of `columns` laid out as `layout`, encoded. Packed: the bytes prost writes for
/// `XxxBatch { stream, columns }` (the tag, field 2, then the columns, field 3; a test checks
/// them), without moving the columns into a message; per sample: `per_sample(columns)`'s.
fn encode_batch<C: Message, B: Message>(
    layout: Layout,
    stream_tag: i32,
    columns: &C,
    per_sample: impl FnOnce(&C) -> B,
) -> Vec<u8> {
    match layout {
        Layout::Packed => {
            let mut buf = Vec::with_capacity(columns.encoded_len() + 16);
            put_u64(2, stream_tag as u64, &mut buf);
            buf.push(3 << 3 | 2);
            // Encoding into a Vec cannot fail (it grows as needed).
            let _ = columns.encode_length_delimited(&mut buf);
            buf
        }
        Layout::PerSample => per_sample(columns).encode_to_vec(),
    }
}

/// The first and last of a batch's times (0, 0 when empty).
fn ends(t_ns: &[i64]) -> (i64, i64) {
    match (t_ns.first(), t_ns.last()) {
        (Some(&first), Some(&last)) => (first, last),
        _ => (0, 0),
    }
}

// Columns (v1.3) as one message per sample (v1.0–v1.2), for `Layout::PerSample`. The columns
// come from a `Batcher`, so they have equal lengths.

fn command_samples(c: &v1::CommandColumns) -> Vec<v1::CommandSample> {
    (0..c.seq.len())
        .map(|i| v1::CommandSample {
            machine_id: c.machine_id.clone(),
            seq: c.seq[i],
            t_ns: c.t_ns[i],
            x: c.x[i],
            y: c.y[i],
            z: c.z[i],
            arc_cx: c.arc_cx[i],
            arc_cy: c.arc_cy[i],
            arc_cz: c.arc_cz[i],
            arc_radius: c.arc_radius[i],
            segment_id: c.segment_id[i],
        })
        .collect()
}

fn scale_samples(c: &v1::ScaleColumns) -> Vec<v1::ScaleSample> {
    (0..c.seq.len())
        .map(|i| v1::ScaleSample {
            machine_id: c.machine_id.clone(),
            seq: c.seq[i],
            t_ns: c.t_ns[i],
            x: c.x[i],
            y: c.y[i],
            z: c.z[i],
        })
        .collect()
}

fn probe_samples(c: &v1::ProbeColumns) -> Vec<v1::ProbeSample> {
    (0..c.seq.len())
        .map(|i| v1::ProbeSample {
            machine_id: c.machine_id.clone(),
            seq: c.seq[i],
            t_ns: c.t_ns[i],
            u: c.u[i],
            v: c.v[i],
            w: c.w[i],
            tip_id: c.tip_id[i],
            head_a1_deg: c.head_a1_deg[i],
            head_a2_deg: c.head_a2_deg[i],
        })
        .collect()
}

fn temperature_samples(c: &v1::TemperatureColumns) -> Vec<v1::TemperatureSample> {
    (0..c.seq.len())
        .map(|i| v1::TemperatureSample {
            machine_id: c.machine_id.clone(),
            seq: c.seq[i],
            t_ns: c.t_ns[i],
            sensor: c.sensor[i].clone(),
            celsius: c.celsius[i],
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_round_trip_through_the_wire() {
        let samples = vec![
            Sample::Command(CommandSample {
                seq: 1,
                t_ns: 5,
                pos: Vec3::new(1.0, 2.0, 3.0),
                arc_center: Vec3::new(0.5, 0.0, 3.0),
                arc_radius: 2.0,
                segment_id: 7,
            }),
            Sample::Scale(ScaleSample {
                seq: 1,
                t_ns: 5,
                pos: Vec3::new(1.0, 2.0, 3.5),
            }),
            Sample::Probe(ProbeSample {
                seq: 1,
                t_ns: 5,
                deflection: Vec3::new(0.1, -0.2, 0.0),
                tip_id: 2,
                head_a1_deg: 90.0,
                head_a2_deg: 15.0,
            }),
            Sample::Temperature(TemperatureSample {
                seq: 1,
                t_ns: 5,
                sensor: "air".into(),
                celsius: 20.25,
            }),
        ];
        let mut b = Batcher::new("m1", 1);
        for s in &samples {
            let stream = b.push(s).unwrap();
            let (bytes, t0, t1) = b.take(stream).unwrap();
            assert_eq!((t0, t1), (5, 5));
            let d = decode(stream, &bytes).unwrap();
            assert_eq!(d.samples, vec![("m1".to_string(), s.clone())]);
        }
        assert!(matches!(
            decode(StreamId::Scale, &[0xff, 0xff, 0xff]),
            Err(WireError::Malformed { .. })
        ));
        assert!(matches!(
            decode(StreamId::Scale, &[]),
            Err(WireError::Empty(_))
        ));
    }

    #[test]
    fn a_batch_on_another_streams_key_is_refused() {
        let cmd = Sample::Command(CommandSample {
            seq: 1,
            t_ns: 5,
            pos: Vec3::new(100.0, 2.0, 3.0),
            arc_center: Vec3::zeros(),
            arc_radius: 0.0,
            segment_id: 0,
        });
        let mut b = Batcher::new("m1", 10).with_layout(Layout::PerSample);
        b.push(&cmd);
        let (bytes, _, _) = b.take(StreamId::Command).unwrap();
        // Without its tag a command batch decodes as a valid scale batch (fields 1–6 agree).
        let untagged = v1::CommandBatch {
            samples: v1::CommandBatch::decode(&bytes[..]).unwrap().samples,
            stream: 0,
            columns: None,
        }
        .encode_to_vec();
        assert_eq!(decode(StreamId::Scale, &untagged).unwrap().samples.len(), 1);
        // With it, the mismatch is detected whatever the policy.
        for tags in [Tags::Require, Tags::AllowUntagged] {
            let e = decode_with_tags(StreamId::Scale, &bytes, tags, |_, _| panic!("decoded"))
                .unwrap_err();
            assert_eq!(
                e,
                WireError::WrongStream {
                    expected: "scale",
                    found: "command".into()
                }
            );
        }
        assert_eq!(
            decode_with_tags(StreamId::Command, &untagged, Tags::Require, |_, _| {}),
            Err(WireError::Untagged("CommandBatch"))
        );
        // Tagging an old batch gives the bytes a v1.1 producer writes.
        assert_eq!(&*tagged(StreamId::Command, &untagged).unwrap(), &bytes[..]);
        assert_eq!(&*tagged(StreamId::Command, &bytes).unwrap(), &bytes[..]);
        assert!(tagged(StreamId::Scale, &bytes).is_err());
        let mut n = 0;
        decode_with_tags(StreamId::Command, &bytes, Tags::Require, |m, s| {
            assert_eq!((m, &s), ("m1", &cmd));
            n += 1;
        })
        .unwrap();
        assert_eq!(n, 1);
        // Packed (v1.3), the same: the columns of fields 1–6 agree too, the tag tells.
        let mut b = Batcher::new("m1", 10);
        b.push(&cmd);
        let (packed, _, _) = b.take(StreamId::Command).unwrap();
        for tags in [Tags::Require, Tags::AllowUntagged] {
            assert_eq!(
                decode_with_tags(StreamId::Scale, &packed, tags, |_, _| panic!("decoded")),
                Err(WireError::WrongStream {
                    expected: "scale",
                    found: "command".into()
                })
            );
        }
        assert_eq!(
            decode(StreamId::Command, &packed).unwrap().samples,
            vec![("m1".to_string(), cmd)]
        );
    }

    #[test]
    fn a_measurement_batch_on_a_corrected_streams_key_is_the_wrong_stream() {
        // v1.2 samples lay out their fields after `t_ns` differently: prost refuses them as
        // a scale batch, and the error names what they are instead of "malformed".
        let distance = v1::DistanceBatch {
            samples: vec![v1::DistanceSample {
                machine_id: "m1".into(),
                seq: 1,
                t_ns: 5,
                probe_id: 2,
                distance_mm: 0.01,
                spacing_mm: 80.0,
            }],
            stream: v1::StreamKind::Distance as i32,
        }
        .encode_to_vec();
        assert!(v1::ScaleBatch::decode(&distance[..]).is_err());
        for tags in [Tags::Require, Tags::AllowUntagged] {
            assert_eq!(
                decode_with_tags(StreamId::Scale, &distance, tags, |_, _| panic!("decoded")),
                Err(WireError::WrongStream {
                    expected: "scale",
                    found: "distance".into()
                })
            );
        }
        assert_eq!(
            tagged(StreamId::Probe, &distance).unwrap_err(),
            WireError::WrongStream {
                expected: "probe",
                found: "distance".into()
            }
        );
        let stage = v1::StageBatch {
            samples: vec![v1::StageSample {
                machine_id: "m1".into(),
                t_ns: 5,
                commanded_mm: 0.1,
                sensor_mm: 0.1,
                probe_id: 2,
                ..Default::default()
            }],
            stream: v1::StreamKind::Stage as i32,
        }
        .encode_to_vec();
        assert_eq!(
            decode(StreamId::Temperature, &stage).unwrap_err(),
            WireError::WrongStream {
                expected: "temperature",
                found: "stage".into()
            }
        );
        // Untagged, or not protobuf: malformed, as before.
        let mut untagged = v1::DistanceBatch::decode(&distance[..]).unwrap();
        untagged.stream = 0;
        assert!(matches!(
            decode(StreamId::Scale, &untagged.encode_to_vec()),
            Err(WireError::Malformed { .. })
        ));
        assert!(matches!(
            decode(StreamId::Scale, &[0xff, 0xff, 0xff]),
            Err(WireError::Malformed { .. })
        ));
    }

    /// Samples of every stream with every field set, some to values varints and zigzag care
    /// about (0, negative, large).
    fn every_stream(n: u64) -> Vec<Sample> {
        let mut v = vec![];
        for k in 0..n {
            let f = k as f64;
            let t_ns = if k % 7 == 3 {
                -(k as i64)
            } else {
                k as i64 * 1_000_003
            };
            v.push(Sample::Command(CommandSample {
                seq: k,
                t_ns,
                pos: Vec3::new(f, -f * 0.5, 1e300),
                arc_center: Vec3::new(0.0, f * 1e-9, -0.0),
                arc_radius: if k % 2 == 0 { 0.0 } else { 12.5 },
                segment_id: (k * 1000) as u32,
            }));
            v.push(Sample::Scale(ScaleSample {
                seq: u64::MAX - k,
                t_ns: i64::MIN + k as i64,
                pos: Vec3::new(f, 2.0, -3.5),
            }));
            v.push(Sample::Probe(ProbeSample {
                seq: k << 40,
                t_ns,
                deflection: Vec3::new(0.1 * f, 0.0, -0.2),
                tip_id: k as u32 % 3,
                head_a1_deg: 90.0,
                head_a2_deg: -f,
            }));
            v.push(Sample::Temperature(TemperatureSample {
                seq: k,
                t_ns: i64::MAX - k as i64,
                sensor: ["air", "", "scale_x"][k as usize % 3].into(),
                celsius: 20.0 + f,
            }));
        }
        v
    }

    /// The encoded batches of `samples`, one per stream, in `layout`.
    fn batches(samples: &[Sample], machine: &str, layout: Layout) -> Vec<(StreamId, Vec<u8>)> {
        let mut b = Batcher::new(machine, usize::MAX).with_layout(layout);
        samples.iter().for_each(|s| {
            b.push(s);
        });
        StreamId::ALL
            .into_iter()
            .filter_map(|s| Some((s, b.take(s)?.0)))
            .collect()
    }

    /// The bytes prost writes for the batch message `bytes` decode to.
    fn prosts_bytes(stream: StreamId, bytes: &[u8]) -> Vec<u8> {
        match stream {
            StreamId::Command => v1::CommandBatch::decode(bytes).unwrap().encode_to_vec(),
            StreamId::Scale => v1::ScaleBatch::decode(bytes).unwrap().encode_to_vec(),
            StreamId::Probe => v1::ProbeBatch::decode(bytes).unwrap().encode_to_vec(),
            StreamId::Temperature => v1::TemperatureBatch::decode(bytes).unwrap().encode_to_vec(),
        }
    }

    /// A packed batch whose columns field is written twice, the machine id in the first and
    /// the columns in the second (one message for prost, which merges them).
    fn split_columns(batch: &[u8]) -> Vec<u8> {
        use scancorr_proto::prost::encoding::decode_varint;
        let mut b = batch;
        let mut out = vec![];
        while !b.is_empty() {
            let start = b;
            let key = decode_varint(&mut b).unwrap();
            if key == (3 << 3 | 2) {
                let len = decode_varint(&mut b).unwrap() as usize;
                let (mut cols, rest) = b.split_at(len);
                b = rest;
                let mut machine = vec![];
                let mut others = vec![];
                while !cols.is_empty() {
                    let field = cols;
                    let k = decode_varint(&mut cols).unwrap();
                    let n = decode_varint(&mut cols).unwrap() as usize;
                    cols = &cols[n..];
                    let whole = &field[..field.len() - cols.len()];
                    if k >> 3 == 1 {
                        &mut machine
                    } else {
                        &mut others
                    }
                    .extend_from_slice(whole);
                }
                for part in [machine, others] {
                    out.push(3 << 3 | 2);
                    encode_varint(part.len() as u64, &mut out);
                    out.extend(part);
                }
            } else {
                let _ = decode_varint(&mut b).unwrap();
                out.extend_from_slice(&start[..start.len() - b.len()]);
            }
        }
        out
    }

    #[test]
    fn old_and_packed_batches_decode_to_the_same_samples() {
        let samples = every_stream(50);
        for machine in ["m1", "", "a-much-longer-machine-name"] {
            let old = batches(&samples, machine, Layout::PerSample);
            let packed = batches(&samples, machine, Layout::Packed);
            assert_eq!(old.len(), 4);
            for ((stream, old), (_, packed)) in old.iter().zip(&packed) {
                let want: Vec<(String, Sample)> = samples
                    .iter()
                    .filter(|s| s.stream() == *stream)
                    .map(|s| (machine.to_string(), s.clone()))
                    .collect();
                assert_eq!(
                    decode(*stream, old).unwrap().samples,
                    want,
                    "{stream:?} old"
                );
                assert_eq!(decode(*stream, packed).unwrap().samples, want, "{stream:?}");
                // Read by prost rather than straight from the bytes (an unknown field; the
                // columns split in two, which prost merges): the same samples.
                let mut unknown = packed.clone();
                unknown.extend([15 << 3, 1]);
                assert_eq!(
                    decode(*stream, &unknown).unwrap().samples,
                    want,
                    "{stream:?}"
                );
                let split = split_columns(packed);
                assert_ne!(&split, packed);
                assert_eq!(decode(*stream, &split).unwrap().samples, want, "{stream:?}");
                let mut out = vec![];
                let foreign =
                    decode_machine_tagged(*stream, packed, "m1", Tags::Require, &mut out).unwrap();
                let ours = if machine == "m1" { want.len() } else { 0 };
                assert_eq!((out.len(), foreign as usize), (ours, want.len() - ours));
                assert_eq!(&prosts_bytes(*stream, packed), packed, "{stream:?}");
                // The v1.1 tag is set: nothing to add for a service that requires it.
                assert_eq!(&*tagged(*stream, packed).unwrap(), &packed[..]);
            }
        }
        let mut b = Batcher::new("m1", 3);
        let full: Vec<_> = samples.iter().take(12).map(|s| b.push(s)).collect();
        assert_eq!(full[..8].iter().flatten().count(), 0);
        assert_eq!(full[8], Some(StreamId::Command));
        let (_, t0, t1) = b.take(StreamId::Command).unwrap();
        assert_eq!((t0, t1), (0, 2_000_006));
        assert!(b.take(StreamId::Command).is_none(), "taken");
        // Batch after batch (the columns emptied and refilled), every sample once, in order.
        let mut b = Batcher::new("m1", 3);
        let mut decoded = vec![];
        for s in &samples[12..] {
            if let Some(stream) = b.push(s) {
                let (bytes, _, _) = b.take(stream).unwrap();
                decode_machine(stream, &bytes, "m1", &mut decoded).unwrap();
            }
        }
        for stream in StreamId::ALL {
            if let Some((bytes, _, _)) = b.take(stream) {
                decode_machine(stream, &bytes, "m1", &mut decoded).unwrap();
            }
        }
        for stream in StreamId::ALL {
            let got: Vec<_> = decoded.iter().filter(|s| s.stream() == stream).collect();
            let want: Vec<_> = samples[12..]
                .iter()
                .filter(|s| s.stream() == stream)
                .collect();
            assert_eq!(got, want, "{stream:?}");
        }
    }

    #[test]
    fn packed_columns_must_agree_in_length() {
        let scale = |columns: v1::ScaleColumns| {
            v1::ScaleBatch {
                stream: v1::StreamKind::Scale as i32,
                columns: Some(columns),
                ..Default::default()
            }
            .encode_to_vec()
        };
        let good = v1::ScaleColumns {
            machine_id: "m1".into(),
            seq: vec![1, 2],
            t_ns: vec![10, 20],
            x: vec![1.0, 2.0],
            y: vec![0.0, 0.0],
            z: vec![3.0, 4.0],
        };
        assert_eq!(
            decode(StreamId::Scale, &scale(good.clone()))
                .unwrap()
                .samples
                .len(),
            2
        );
        let short_y = v1::ScaleColumns {
            y: vec![0.0],
            ..good.clone()
        };
        let e = decode_with(StreamId::Scale, &scale(short_y), |_, _| panic!("decoded"));
        assert_eq!(
            e.unwrap_err().to_string(),
            "malformed ScaleBatch: column `y` holds 1 values for 2 samples (`seq`)"
        );
        let no_seq = v1::ScaleColumns {
            seq: vec![],
            ..good.clone()
        };
        assert!(matches!(
            decode(StreamId::Scale, &scale(no_seq)),
            Err(WireError::Malformed { .. })
        ));
        let temps = v1::TemperatureBatch {
            stream: v1::StreamKind::Temperature as i32,
            columns: Some(v1::TemperatureColumns {
                machine_id: "m1".into(),
                seq: vec![1, 2],
                t_ns: vec![1, 2],
                sensor: vec!["air".into()],
                celsius: vec![20.0, 20.0],
            }),
            ..Default::default()
        };
        assert!(matches!(
            decode(StreamId::Temperature, &temps.encode_to_vec()),
            Err(WireError::Malformed { reason, .. }) if reason.contains("`sensor`")
        ));
        // Columns without samples: an empty batch, as one without messages.
        assert_eq!(
            decode(StreamId::Scale, &scale(v1::ScaleColumns::default())).unwrap_err(),
            WireError::Empty("ScaleBatch")
        );
        // Both forms in one batch.
        let both = v1::ScaleBatch {
            samples: vec![v1::ScaleSample::default()],
            stream: v1::StreamKind::Scale as i32,
            columns: Some(good),
        };
        assert!(matches!(
            decode(StreamId::Scale, &both.encode_to_vec()),
            Err(WireError::Malformed { reason, .. }) if reason.contains("both")
        ));
    }

    mod garbled {
        use super::*;
        use proptest::prelude::*;

        /// A packed varint column's values as this module reads them (`None` when refused)
        /// and as prost's `decode_varint` reads them.
        fn column_as_read(bytes: &[u8]) -> (Option<Vec<u64>>, Option<Vec<u64>>) {
            let ours = varints(bytes).map(|n| {
                let v: Vec<u64> = Varints(bytes).collect();
                assert_eq!(v.len(), n, "{bytes:02x?}: counted {n}, read {}", v.len());
                v
            });
            let mut b = bytes;
            let mut prost = Some(vec![]);
            while !b.is_empty() {
                match scancorr_proto::prost::encoding::decode_varint(&mut b) {
                    Ok(v) => prost.as_mut().expect("not refused yet").push(v),
                    Err(_) => {
                        prost = None;
                        break;
                    }
                }
            }
            (ours, prost)
        }

        /// The edges of a varint, which random bytes seldom reach: ten bytes whose last is 0 or
        /// 1 (read) or more (refused), ten continuation bytes, a value cut short, no bytes;
        /// eight and nine bytes (the longest read from one word, and one more).
        #[test]
        fn varint_edges_read_as_prost_reads_them() {
            let ten = |last: u8| [[0xff; 9].as_slice(), &[last]].concat();
            let cases: Vec<(Vec<u8>, Option<Vec<u64>>)> = vec![
                (ten(1), Some(vec![u64::MAX])),
                ([[0x80; 9].as_slice(), &[1]].concat(), Some(vec![1 << 63])),
                ([[0x80; 9].as_slice(), &[0]].concat(), Some(vec![0])),
                (ten(2), None),
                (ten(0x7f), None),
                (vec![0xff; 10], None),
                (
                    [ten(1).as_slice(), &[0x05]].concat(),
                    Some(vec![u64::MAX, 5]),
                ),
                (vec![5, 0xff, 0xff], None),
                (vec![0x96, 0x01], Some(vec![150])),
                (
                    [[0xff; 7].as_slice(), &[0x7f]].concat(),
                    Some(vec![(1 << 56) - 1]),
                ),
                ([[0x80; 8].as_slice(), &[1]].concat(), Some(vec![1 << 56])),
                (
                    [[0x81; 7].as_slice(), &[0x40]].concat(),
                    Some(vec![
                        (0..7).map(|k| 1u64 << (7 * k)).sum::<u64>() | 0x40 << 49,
                    ]),
                ),
                (vec![], Some(vec![])),
            ];
            // Each case alone and after 1–15 one-byte values: its edge then falls anywhere in
            // the words the column is read by (eight bytes), and across two of them.
            for (bytes, want) in cases {
                for before in 0..16 {
                    let bytes = [vec![0x05; before], bytes.clone()].concat();
                    let want = want.clone().map(|w| [vec![5; before], w].concat());
                    let (ours, prost) = column_as_read(&bytes);
                    assert_eq!(prost, want, "prost on {bytes:02x?}");
                    assert_eq!(ours, want, "{bytes:02x?}");
                }
            }
        }

        proptest! {
            #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

            /// A packed varint column is counted and read as prost reads it: the same count
            /// and values, and refused exactly when prost refuses one of its values.
            #[test]
            fn varint_columns_read_as_prost_reads_them(
                bytes in prop::collection::vec(
                    prop_oneof![0u8..2, 2u8..0x80, 0x80u8..=0xff, Just(0xffu8)], 0..80),
            ) {
                let (ours, prost) = column_as_read(&bytes);
                prop_assert_eq!(ours, prost, "{:02x?}", bytes);
            }

            /// Every strict prefix of a packed batch is refused, and no byte changed anywhere
            /// makes the decoder panic or hand out samples of a batch it then refuses.
            #[test]
            fn cut_or_changed_packed_batches_are_errors(
                n in 1u64..12,
                which in 0usize..4,
                at in any::<prop::sample::Index>(),
                byte in any::<u8>(),
            ) {
                let (stream, bytes) = batches(&every_stream(n), "m1", Layout::Packed)
                    .swap_remove(which);
                for cut in 0..bytes.len() {
                    let r = decode_with_tags(stream, &bytes[..cut], Tags::Require, |_, _| {});
                    prop_assert!(r.is_err(), "prefix of {cut} of {} bytes decoded", bytes.len());
                }
                let mut changed = bytes.clone();
                changed[at.index(bytes.len())] = byte;
                let mut handed = 0;
                match decode_with_tags(stream, &changed, Tags::AllowUntagged, |_, _| handed += 1) {
                    Ok(k) => prop_assert_eq!(k, handed),
                    Err(_) => prop_assert_eq!(handed, 0),
                }
            }

            /// Columns of any lengths: decoded when they agree, else malformed (or empty).
            #[test]
            fn columns_of_any_lengths(lens in prop::collection::vec(0usize..4, 10)) {
                let col = |k: usize| vec![1.5; lens[k]];
                let c = v1::CommandColumns {
                    machine_id: "m1".into(),
                    seq: vec![7; lens[0]],
                    t_ns: vec![-1; lens[1]],
                    x: col(2),
                    y: col(3),
                    z: col(4),
                    arc_cx: col(5),
                    arc_cy: col(6),
                    arc_cz: col(7),
                    arc_radius: col(8),
                    segment_id: vec![3; lens[9]],
                };
                let bytes = v1::CommandBatch {
                    stream: v1::StreamKind::Command as i32,
                    columns: Some(c),
                    ..Default::default()
                }
                .encode_to_vec();
                let r = decode(StreamId::Command, &bytes);
                let agree = lens.iter().all(|&l| l == lens[0]);
                match r {
                    Ok(d) => prop_assert!(agree && d.samples.len() == lens[0]),
                    Err(WireError::Empty(_)) => prop_assert!(agree && lens[0] == 0),
                    Err(WireError::Malformed { .. }) => prop_assert!(!agree),
                    Err(e) => prop_assert!(false, "{e}"),
                }
            }
        }
    }

    #[test]
    fn encode_points_writes_prosts_bytes() {
        let ids: Vec<String> = ["accel_deflection", "", "x_cyclic"]
            .map(String::from)
            .to_vec();
        let mut ps = vec![];
        for k in 0..40u64 {
            let f = k as f64;
            let z = |v: f64| if k % 3 == 0 { 0.0 } else { v };
            ps.push(CorrectedPoint {
                seq: k * 1_000_003,
                t_ns: if k % 5 == 0 {
                    -(k as i64) * 7_777_777
                } else {
                    k as i64 * 1_000_000_000
                },
                sample_seq: k % 4,
                surface: Vec3::new(z(f * 1.5), -f, if k % 2 == 0 { -0.0 } else { 3.25 }),
                tip_center: Vec3::new(f, z(2.0), 1e-300),
                normal: Vec3::zeros(),
                corrections: (0..3)
                    .map(|i| Vec3::new(z(i as f64 * 1e-4), 0.0, -1e-6 * (k % 4) as f64))
                    .collect(),
                calibration_version: k % 3,
                estimator_valid: k % 2 == 0,
                segment_id: (k % 7) as u32,
                tip_id: (k * 300) as u32,
            });
        }
        // Lengths of one, two and three bytes (an effect id longer than 127 bytes, one longer
        // than 16 KiB), and a calibration with no effect.
        let long_ids = ["x".repeat(200), "y".repeat(17_000), String::new()].to_vec();
        for ids in [&ids, &long_ids, &vec![]] {
            for machine in [
                "m1",
                "",
                "a-machine-with-a-long-name-to-make-lengths-two-bytes",
            ] {
                let per_point: Vec<_> = ps.iter().map(|p| point(p, machine, ids)).collect();
                let want = scancorr_proto::points::pack(&per_point).encode_to_vec();
                let mut got = vec![0xAA];
                encode_points(&ps, machine, ids, &mut got);
                assert_eq!(&got[1..], &want[..], "machine `{machine}`");
                // Read back: the points, each naming the machine and all effects.
                let back = v1::CorrectedPointBatch::decode(&got[1..])
                    .unwrap()
                    .into_points()
                    .unwrap();
                assert_eq!(back, per_point);
            }
        }
    }
}
