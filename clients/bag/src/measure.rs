//! The measurement streams the corrector does not use (`scancorr.v1.2`): distance probes
//! (`raw/distance`) and the micro-stage that carries one of them (`raw/stage`), as a
//! straightness error-separation measurement records them. [`read_separation`] reads them for
//! one machine as plain readings in time order, for a calibration procedure to fit.
//!
//! Nothing is dropped silently: a batch whose stream tag names another stream than its channel
//! (a `DistanceBatch` published on the stage key), a batch that does not decode, a sample that
//! names another machine or holds a value that is not a finite number is skipped and counted
//! per stream and reason ([`Skipped`]); [`SeparationData::warnings`] says so in words. Damage
//! to the file is the reader's business: an error, or with
//! [`crate::ReadOptions::skip_damaged`] chunks the caller finds in
//! [`BagReader::damaged_chunks`].
use crate::{BagError, BagReader, RawBatch, Stream};
use std::path::PathBuf;

/// The command that records a straightness measurement, named in
/// [`MeasureError::NoDistanceStream`].
pub const RECORD_HINT: &str = "scancorr sim --program straightness-three-probe";

/// One reading of a distance probe (a single-axis displacement sensor on a mount).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DistanceReading {
    /// Controller time, ns.
    pub t_ns: i64,
    /// Sequence number in the machine's distance stream.
    pub seq: u64,
    /// Which probe of the mount.
    pub probe_id: u32,
    /// The reading, mm.
    pub distance_mm: f64,
    /// The probe's position along the travel relative to the mount's reference, mm, as
    /// mounted.
    pub spacing_mm: f64,
}

/// One position of the micro-stage that carries a distance probe.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StageReading {
    /// Controller time, ns.
    pub t_ns: i64,
    /// Sequence number in the machine's stage stream.
    pub seq: u64,
    /// The distance probe the stage carries.
    pub probe_id: u32,
    /// Where the stage was told to go, mm.
    pub commanded_mm: f64,
    /// What the stage's own displacement sensor reads, mm: the true shear.
    pub sensor_mm: f64,
}

/// What was left out of one stream, by reason.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Skipped {
    /// Messages whose stream tag names another stream than their channel's, e.g. a distance
    /// batch published on the stage key.
    pub wrong_stream: u64,
    /// Messages that do not decode as their channel's batch.
    pub malformed: u64,
    /// Samples inside the machine's messages that name another machine.
    pub other_machine: u64,
    /// Samples with a reading, position or spacing that is not a finite number.
    pub not_finite: u64,
    /// The first skipped message's error, to show what the others are like.
    pub first_error: Option<String>,
}

impl Skipped {
    /// Messages and samples skipped, all reasons.
    pub fn total(&self) -> u64 {
        self.wrong_stream + self.malformed + self.other_machine + self.not_finite
    }

    fn describe(&self) -> String {
        let mut parts = Vec::new();
        for (n, what) in [
            (self.wrong_stream, "message(s) tagged as another stream"),
            (self.malformed, "message(s) that do not decode"),
            (self.other_machine, "sample(s) naming another machine"),
            (
                self.not_finite,
                "sample(s) with values that are not finite numbers",
            ),
        ] {
            if n > 0 {
                parts.push(format!("{n} {what}"));
            }
        }
        let mut s = parts.join(", ");
        if let Some(e) = &self.first_error {
            s.push_str(&format!(" (first: {e})"));
        }
        s
    }

    fn message(&mut self, e: &BagError) {
        if self.first_error.is_none() {
            self.first_error = Some(e.to_string());
        }
    }
}

/// The distance-probe and micro-stage readings of one machine in a bag, each in time order
/// (by `t_ns`; readings of equal time in the order they were recorded).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SeparationData {
    /// The machine.
    pub machine: String,
    /// The distance stream's key expression (`cmm/m1/raw/distance`).
    pub distance_topic: String,
    /// The stage stream's key expression, `None` when the bag has no stage stream for the
    /// machine (a measurement without a micro-stage).
    pub stage_topic: Option<String>,
    /// Every probe's readings, in time order; never empty.
    pub distance: Vec<DistanceReading>,
    /// The micro-stage's positions, in time order; empty without a stage stream.
    pub stage: Vec<StageReading>,
    /// What was left out of the distance stream.
    pub distance_skipped: Skipped,
    /// What was left out of the stage stream.
    pub stage_skipped: Skipped,
}

impl SeparationData {
    /// The probes with readings, sorted.
    pub fn probe_ids(&self) -> Vec<u32> {
        let mut ids: Vec<u32> = self.distance.iter().map(|r| r.probe_id).collect();
        ids.sort_unstable();
        ids.dedup();
        ids
    }

    /// One probe's readings, in time order.
    pub fn readings_of(&self, probe_id: u32) -> impl Iterator<Item = &DistanceReading> {
        self.distance.iter().filter(move |r| r.probe_id == probe_id)
    }

    /// One line per stream that lost something, for the caller to warn with; empty when
    /// nothing was skipped.
    pub fn warnings(&self) -> Vec<String> {
        let mut w = Vec::new();
        if self.distance_skipped.total() > 0 {
            w.push(format!(
                "{}: skipped {}",
                self.distance_topic,
                self.distance_skipped.describe()
            ));
        }
        if self.stage_skipped.total() > 0 {
            w.push(format!(
                "{}: skipped {}",
                self.stage_topic.as_deref().unwrap_or("raw/stage"),
                self.stage_skipped.describe()
            ));
        }
        w
    }
}

/// Why a bag's separation measurement cannot be read.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum MeasureError {
    /// The machine id does not follow the name grammar ([`scancorr_proto::names`]).
    #[error(transparent)]
    InvalidMachine(#[from] scancorr_proto::names::NameError),
    /// The bag holds no stream of the machine at all.
    #[error("{}: no streams of machine `{machine}` in this bag (it holds: {holds})", path.display())]
    NoMachine {
        /// The bag file.
        path: PathBuf,
        /// The machine asked for.
        machine: String,
        /// The machines it holds, comma-separated (`none`).
        holds: String,
    },
    /// The bag has streams of the machine but no distance-probe stream.
    #[error(
        "{}: the bag has no distance-probe stream ({topic}): record the straightness measurement, e.g. {RECORD_HINT}",
        path.display()
    )]
    NoDistanceStream {
        /// The bag file.
        path: PathBuf,
        /// The key expression the stream would have (`cmm/m1/raw/distance`).
        topic: String,
    },
    /// The distance-probe stream is there but yields no reading.
    #[error("{}: the distance-probe stream {topic} holds no readings{}", path.display(), match skipped.total() {
        0 => String::new(),
        _ => format!(": skipped {}", skipped.describe()),
    })]
    NoReadings {
        /// The bag file.
        path: PathBuf,
        /// The distance stream's key expression.
        topic: String,
        /// What was skipped.
        skipped: Skipped,
    },
    /// Reading the bag failed (I/O, damage).
    #[error(transparent)]
    Bag(#[from] BagError),
}

/// Reads the distance-probe readings (required) and micro-stage positions (when recorded) of
/// `machine` from `bag`, each in time order, skipping and counting what cannot be used (see the
/// module documentation). Every message of the bag is read once.
pub fn read_separation(bag: &BagReader, machine: &str) -> Result<SeparationData, MeasureError> {
    scancorr_proto::names::check_machine(machine)?;
    let path = || bag.path().to_path_buf();
    let Some(distance) = bag.channel(machine, Stream::Distance) else {
        let machines = bag.machines();
        if !machines.contains(&machine) {
            return Err(MeasureError::NoMachine {
                path: path(),
                machine: machine.to_owned(),
                holds: if machines.is_empty() {
                    "none".to_owned()
                } else {
                    machines.join(", ")
                },
            });
        }
        return Err(MeasureError::NoDistanceStream {
            path: path(),
            topic: Stream::Distance.key(bag.prefix(), machine),
        });
    };
    let mut data = SeparationData {
        machine: machine.to_owned(),
        distance_topic: distance.topic.clone(),
        stage_topic: bag.channel(machine, Stream::Stage).map(|c| c.topic.clone()),
        ..SeparationData::default()
    };
    for msg in bag.messages()? {
        let msg = msg?;
        if &*msg.machine != machine || !Stream::MEASUREMENT.contains(&msg.stream) {
            continue;
        }
        let skipped = match msg.stream {
            Stream::Distance => &mut data.distance_skipped,
            _ => &mut data.stage_skipped,
        };
        let batch = match msg.decode_checked() {
            Ok(b) => b,
            Err(e @ BagError::WrongStream { .. }) => {
                skipped.wrong_stream += 1;
                skipped.message(&e);
                continue;
            }
            Err(e @ BagError::Decode { .. }) => {
                skipped.malformed += 1;
                skipped.message(&e);
                continue;
            }
            Err(e) => return Err(e.into()),
        };
        match batch {
            RawBatch::Distance(b) => {
                for s in b.samples {
                    if s.machine_id != machine {
                        skipped.other_machine += 1;
                    } else if !(s.distance_mm.is_finite() && s.spacing_mm.is_finite()) {
                        skipped.not_finite += 1;
                    } else {
                        data.distance.push(DistanceReading {
                            t_ns: s.t_ns,
                            seq: s.seq,
                            probe_id: s.probe_id,
                            distance_mm: s.distance_mm,
                            spacing_mm: s.spacing_mm,
                        });
                    }
                }
            }
            RawBatch::Stage(b) => {
                for s in b.samples {
                    if s.machine_id != machine {
                        skipped.other_machine += 1;
                    } else if !(s.commanded_mm.is_finite() && s.sensor_mm.is_finite()) {
                        skipped.not_finite += 1;
                    } else {
                        data.stage.push(StageReading {
                            t_ns: s.t_ns,
                            seq: s.seq,
                            probe_id: s.probe_id,
                            commanded_mm: s.commanded_mm,
                            sensor_mm: s.sensor_mm,
                        });
                    }
                }
            }
            // decode_checked decodes a message of a measurement channel as its batch.
            _ => {}
        }
    }
    if data.distance.is_empty() {
        return Err(MeasureError::NoReadings {
            path: path(),
            topic: data.distance_topic,
            skipped: data.distance_skipped,
        });
    }
    // Stable: readings of equal time stay in recording order.
    data.distance.sort_by_key(|r| r.t_ns);
    data.stage.sort_by_key(|r| r.t_ns);
    Ok(data)
}
