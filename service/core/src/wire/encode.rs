//! Encoding core output for the wire: points (one message each, or packed blocks written
//! straight to bytes, v1.4) and alarms.

use super::*;
use crate::corrector::Corrector;

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
pub(super) fn put_u64(tag: u8, v: u64, buf: &mut Vec<u8>) {
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
