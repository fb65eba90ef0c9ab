//! Decoding raw batches into core samples: both layouts (a message per sample, v1.0–v1.2;
//! packed columns, v1.3), the plain packed form read straight from its bytes.

use super::*;

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
        force_n: s.force_n,
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
        StreamId::Probe => ("ProbeBatch", 10),
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
            // The force (v1.5): an empty column is no force signal.
            let forces = doubles(c[10])?;
            if forces != 0 {
                if let Err(e) = column_len(name, n, &[("force_n", forces)]) {
                    return Some(Err(e));
                }
            }
            let (mut seq, mut t, mut tip) = (Varints(c[2]), Varints(c[3]), Varints(c[7]));
            let [u, vv, w, a1, a2, fz] = [4, 5, 6, 8, 9, 10].map(|k| Doubles::new(c[k], n));
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
                        force_n: (forces != 0).then(|| fz.at(i)),
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
pub(super) fn varints(b: &[u8]) -> Option<usize> {
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
pub(super) struct Varints<'a>(pub(super) &'a [u8]);

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
    // The force (v1.5): an empty column is no force signal.
    if !c.force_n.is_empty() {
        column_len("ProbeBatch", n, &[("force_n", c.force_n.len())])?;
    }
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
                force_n: c.force_n.get(i).copied(),
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
