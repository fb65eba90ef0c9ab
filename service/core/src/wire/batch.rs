//! Batching raw samples of one machine for the wire ([`Batcher`]): packed columns (v1.3) or
//! one message per sample.

use super::*;

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
    /// Per pending probe sample, whether it carries a force (v1.5).
    probe_forced: Vec<bool>,
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
            probe_forced: vec![],
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
                // The force column (v1.5) holds the forces of the samples that carry one.
                if let Some(f) = s.force_n {
                    c.force_n.push(f);
                }
                self.probe_forced.push(s.force_n.is_some());
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
            ($c:expr, $layout:expr, $batch:ident, |$cs:ident| $samples:expr, [$($column:ident),*]) => {{
                let c = &mut $c;
                if c.seq.is_empty() {
                    return None;
                }
                let bytes = encode_batch($layout, tag, &*c, |$cs| v1::$batch {
                    stream: tag,
                    samples: $samples,
                    columns: None,
                });
                let (first, last) = ends(&c.t_ns);
                $(c.$column.clear();)*
                (bytes, first, last)
            }};
        }
        // The force column holds a force for every probe sample or none (v1.5): a batch whose
        // samples differ in this is written one message per sample.
        let p = &self.probe;
        let probe_layout = if !p.force_n.is_empty() && p.force_n.len() != p.seq.len() {
            Layout::PerSample
        } else {
            layout
        };
        let taken = match stream {
            StreamId::Command => take!(
                self.command,
                layout,
                CommandBatch,
                |c| command_samples(c),
                [seq, t_ns, x, y, z, arc_cx, arc_cy, arc_cz, arc_radius, segment_id]
            ),
            StreamId::Scale => take!(
                self.scale,
                layout,
                ScaleBatch,
                |c| scale_samples(c),
                [seq, t_ns, x, y, z]
            ),
            StreamId::Probe => {
                let forced = &self.probe_forced;
                take!(
                    self.probe,
                    probe_layout,
                    ProbeBatch,
                    |c| probe_samples(c, forced),
                    [
                        seq,
                        t_ns,
                        u,
                        v,
                        w,
                        tip_id,
                        head_a1_deg,
                        head_a2_deg,
                        force_n
                    ]
                )
            }
            StreamId::Temperature => take!(
                self.temperature,
                layout,
                TemperatureBatch,
                |c| temperature_samples(c),
                [seq, t_ns, sensor, celsius]
            ),
        };
        if stream == StreamId::Probe {
            self.probe_forced.clear();
        }
        Some(taken)
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

/// `forced[i]`: whether sample i has a force (the force column holds those samples' forces).
fn probe_samples(c: &v1::ProbeColumns, forced: &[bool]) -> Vec<v1::ProbeSample> {
    let mut forces = c.force_n.iter();
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
            force_n: if forced.get(i) == Some(&true) {
                forces.next().copied()
            } else {
                None
            },
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
