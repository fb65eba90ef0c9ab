//! What a corrector reports: why a sample or point was dropped ([`DropReason`]), its counters
//! ([`Stats`]) and the points and alarms of one push ([`Output`]).

use super::*;

/// Why a sample or a point was dropped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum DropReason {
    /// A value was NaN or infinite.
    NonFinite,
    /// seq not above the last accepted seq of its stream.
    Duplicate,
    /// t_ns not above the last accepted t_ns of its stream (below, for temperatures).
    OutOfOrder,
    /// No command sample around the scale time (before the first / after the last).
    NoCommand,
    /// The command stream has a gap around the scale time.
    CommandGap,
    /// No probe sample around the scale time.
    NoProbe,
    /// The probe stream has a gap around the scale time.
    ProbeGap,
    /// A temperature the calibration needs was never measured.
    TemperatureMissing,
    /// A temperature the calibration needs is older than the maximum age.
    TemperatureStale,
    /// The active tip is not in the calibration's geometry.
    UnknownTip,
    /// A stream buffer was full (another stream stalled).
    BufferOverflow,
    /// A value outside the calibration's plausible ranges (`limits`).
    Implausible,
    /// A temperature of a sensor the calibration does not use, beyond the names kept.
    UnknownSensor,
    /// A sensor name outside the names grammar.
    BadName,
    /// A point that is not finite or lies outside the machine's volume (not published).
    ImplausibleOutput,
    /// A scale or probe sample off its stream's track by more than the machine can move,
    /// with the stream back on the track after it (the jump gate).
    ImplausibleJump,
}

impl DropReason {
    /// All reasons, in index order.
    pub const ALL: [DropReason; 16] = [
        DropReason::NonFinite,
        DropReason::Duplicate,
        DropReason::OutOfOrder,
        DropReason::NoCommand,
        DropReason::CommandGap,
        DropReason::NoProbe,
        DropReason::ProbeGap,
        DropReason::TemperatureMissing,
        DropReason::TemperatureStale,
        DropReason::UnknownTip,
        DropReason::BufferOverflow,
        DropReason::Implausible,
        DropReason::UnknownSensor,
        DropReason::BadName,
        DropReason::ImplausibleOutput,
        DropReason::ImplausibleJump,
    ];
    /// snake_case name used in JSON output and logs.
    pub fn name(self) -> &'static str {
        [
            "non_finite",
            "duplicate",
            "out_of_order",
            "no_command",
            "command_gap",
            "no_probe",
            "probe_gap",
            "temperature_missing",
            "temperature_stale",
            "unknown_tip",
            "buffer_overflow",
            "implausible",
            "unknown_sensor",
            "bad_name",
            "implausible_output",
            "implausible_jump",
        ][self as usize]
    }
}

/// Counters of one corrector.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Stats {
    /// Controller clock resets detected (each restarts the join in the new time base).
    pub clock_resets: u64,
    /// Samples received per stream (command, scale, probe, temperature).
    pub samples_in: [u64; 4],
    /// Points produced.
    pub points_out: u64,
    /// Points produced while the estimate was not valid.
    pub points_invalid: u64,
    /// Drops by reason ([`DropReason`] index).
    pub dropped: [u64; 16],
    /// Stream sequences restarted (a counter wrap or restart, confirmed).
    pub seq_resets: u64,
    /// Points to which each effect of the calibration in force contributed a non-zero
    /// correction, in effect order (reset when the calibration changes).
    pub effect_points: Vec<u64>,
    /// Seq jumps (missing samples) seen per stream.
    pub seq_gaps: [u64; 4],
    /// Samples missing in those jumps (lost before the corrector: a router down, a link
    /// dropped), per stream. A jump longer than the stream could have made in the time since
    /// its previous sample (four per sample period, plus 1024) is a bogus seq or a counter
    /// restarted higher: counted as a gap, not as missing samples (the return of a bogus seq
    /// is then a `seq_resets`).
    pub samples_missing: [u64; 4],
    /// Alarms raised.
    pub alarms_raised: u64,
    /// Jumps beyond the machine's speed and acceleration that the stream's next samples
    /// confirmed, per stream (command, scale, probe, temperature): taken, the points around
    /// them flagged (the jump gate).
    pub stream_jumps: [u64; 4],
}

impl Stats {
    /// Total samples in.
    pub fn samples(&self) -> u64 {
        self.samples_in.iter().sum()
    }
    /// Total drops.
    pub fn dropped_total(&self) -> u64 {
        self.dropped.iter().sum()
    }
    /// Non-zero drop counts by name.
    pub fn dropped_by_name(&self) -> Vec<(&'static str, u64)> {
        DropReason::ALL
            .iter()
            .filter(|r| self.dropped[**r as usize] > 0)
            .map(|r| (r.name(), self.dropped[*r as usize]))
            .collect()
    }
    /// Adds another corrector's counts.
    pub fn add(&mut self, o: &Stats) {
        for i in 0..4 {
            self.samples_in[i] += o.samples_in[i];
            self.seq_gaps[i] += o.seq_gaps[i];
            self.samples_missing[i] += o.samples_missing[i];
            self.stream_jumps[i] += o.stream_jumps[i];
        }
        for i in 0..self.dropped.len() {
            self.dropped[i] += o.dropped[i];
        }
        self.points_out += o.points_out;
        self.points_invalid += o.points_invalid;
        self.alarms_raised += o.alarms_raised;
        self.clock_resets += o.clock_resets;
        self.seq_resets += o.seq_resets;
        if self.effect_points.len() < o.effect_points.len() {
            self.effect_points.resize(o.effect_points.len(), 0);
        }
        for (a, b) in self.effect_points.iter_mut().zip(&o.effect_points) {
            *a += b;
        }
    }
}

/// What one call produced.
#[derive(Debug, Default, Clone)]
pub struct Output {
    /// Corrected points, in scale-time order.
    pub points: Vec<CorrectedPoint>,
    /// Alarms raised or cleared.
    pub alarms: Vec<Alarm>,
    /// The context of each point, when [`Corrector::record_context`] is on (the lab's input).
    pub contexts: Vec<PointContext>,
    /// The `corrections` lists of cleared points, reused by the next points (no allocation
    /// per point once the output has been cleared).
    pub(super) spare: Vec<Vec<Vec3>>,
}

impl Output {
    /// Empties all lists, keeping their capacity (and the points' lists of corrections, for
    /// the next points).
    #[inline]
    pub fn clear(&mut self) {
        if !self.points.is_empty() {
            self.recycle_points();
        }
        self.alarms.clear();
        self.contexts.clear();
    }

    /// Empties the points, their lists of corrections kept for the next points.
    pub(super) fn recycle_points(&mut self) {
        // The lists are taken out in place (not each point moved out whole, then dropped).
        self.spare.extend(
            self.points
                .iter_mut()
                .map(|p| std::mem::take(&mut p.corrections)),
        );
        self.points.clear();
    }

    /// An empty list for a point's corrections: a cleared point's, or a new one.
    pub(super) fn corrections_list(&mut self) -> Vec<Vec3> {
        let mut c = self.spare.pop().unwrap_or_default();
        c.clear();
        c
    }
}
