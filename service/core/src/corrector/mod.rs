//! The corrector: one machine's stream join, estimator, effects, synthesis and judgement.
//!
//! Stream join. Each stream must arrive in its own order (seq and t_ns increasing);
//! duplicates, samples going back in time and non-finite values are dropped and counted.
//! One point is produced per scale sample at time t once every stream it needs has a
//! watermark (latest t seen) at or past t: the command and probe streams are interpolated to
//! t between their two neighbouring samples (never across a gap of more than
//! `join.max_gap_periods` periods: such points are dropped), temperatures — a slow stream —
//! are taken as the last reading at or before t − `join.temperature_delay_s` and must be
//! younger than `join.temperature_max_age_s`. Because the decision and the values depend only
//! on the samples' times, the output does not depend on how the streams were interleaved on
//! arrival (as long as no buffer reaches `join.max_pending`).
//!
//! Sequence numbers are evidence, not law: a sample whose seq is not above its stream's last
//! while its time runs on (a 32-bit counter that wrapped, a controller that restarted its
//! counter, or the aftermath of one bogus jump) is held; `join.seq_reset_samples` of them in a
//! row restart the stream's sequence and are taken (counted as `seq_resets`). A sample that
//! repeats both seq and time is a duplicate.
//!
//! Plausibility (`limits` of the calibration): commands, arc centres and scales outside the
//! travel, deflections beyond the probe range, head angles beyond a turn, temperatures outside
//! the range are dropped as `implausible`; of the sensors the calibration does not use only the
//! latest reading is kept, for at most [`MAX_KEPT_SENSORS`] names (so a new calibration that
//! needs them has them at once), readings of further names are dropped as `unknown_sensor`; names outside the
//! [`scancorr_proto::names`] grammar are dropped as `bad_name`. A point that is not finite or
//! lies outside the machine's volume is dropped as `implausible_output`: never published.
//!
//! Jump gate. Limits judge each value alone; a scale or probe sample is also judged against
//! its stream's recent past, by what no machine can do at its fastest (`limits`: speed v̄,
//! acceleration ā, head rate ω̄, reading noise m). With s₁, s₀ the last two samples taken
//! (t₁ > t₀), h = t − t₁ and h₀ = t₁ − t₀, a sample s at t is on its stream's track when
//! * scales, per axis: |s − s₁| ≤ v̄·h + 2m, and (when s₀ is no gap before s₁)
//!   |s − s₁ − (s₁ − s₀)·h/h₀| ≤ ā·h·(h + h₀)/2 + 2m·(1 + h/h₀) — the extrapolation of the
//!   last two readings misses the true position by at most ā·h²/2 (Taylor, the acceleration
//!   bounded) plus the slope's own error ā·h·h₀/2 (the chord's slope is the velocity
//!   somewhere within [t₀, t₁]);
//! * probe: the deflection d within v̄·h + 2m of the segment from 0 to d₁ (the stylus may
//!   spring back towards rest at any speed, but a surface pushes it at most as fast as the
//!   machine moves), each head angle within ω̄·h + 0.01° of its last (the difference taken
//!   within ±180°, a head turning through 0° included), and the same tip.
//!
//! A sample off its track is held, with the samples that follow it, until one of them is
//! back on the old track (extrapolated over the longer h): the held samples left the track
//! and came back, which no machine can do — they are dropped as `implausible_jump`. When
//! `limits.jump_confirm_samples` in a row stay off it, the stream really moved (a collision,
//! a head indexing, a tip changed): they are taken and the track restarts from them
//! (counted in [`Stats::stream_jumps`]). Either way the points between the last sample
//! taken before the jump and the sample that settled it (the point at each time the join
//! would interpolate across the jump) are flagged (`estimator_valid = false`). The decision
//! depends only on the stream's own samples, so the output still does not depend on the
//! interleaving; the probe stream counts as arrived for the join only up to the last sample
//! taken. What is held at the end of input is dropped. Source idea: a rate-of-change
//! (slew-rate) and extrapolation plausibility check of a sampled physical quantity, as in
//! sensor validation for control (a reading the plant's dynamics cannot produce is
//! rejected; a step that persists is believed).
//!
//! Synthesis: tip centre = scales + Σ corrections + R·deflection + R·tip offset;
//! surface point = tip centre − tip radius · n, n = deflection direction (out of the material).

use crate::calib::{CalibError, Calibration, Limits, Model, Settings};
use crate::effects::thermal_drift::Lag;
use crate::effects::{BuiltEffect, Effect};
use crate::estimator::{rotation, Estimate, Estimator};
use crate::judge::Judge;
use crate::sample::*;
use crate::stylus::TipPose;
use std::collections::VecDeque;
use std::sync::Arc;

mod gate;
mod limits;
mod report;
mod synthesis;

use gate::*;
use limits::*;
pub use report::*;
pub use synthesis::*;

#[derive(Debug, Clone, Copy, Default)]
struct Intake {
    last_seq: Option<u64>,
    last_t: Option<i64>,
}

#[derive(Debug, Clone)]
struct PendingTemp {
    t_ns: i64,
    sensor: String,
    /// Whether the calibration reads this sensor (directly or through a lag).
    used: bool,
    celsius: f64,
}

/// Most names of temperature sensors the calibration does not use whose last reading is kept.
pub const MAX_KEPT_SENSORS: usize = 64;

/// One machine's correction pipeline.
#[derive(Debug)]
pub struct Corrector {
    model: Arc<Model>,
    intake: [Intake; 4],
    cmd_q: VecDeque<CommandSample>,
    scale_q: VecDeque<ScaleSample>,
    probe_q: VecDeque<ProbeSample>,
    temp_q: VecDeque<PendingTemp>,
    held: [(f64, i64); MAX_SENSORS],
    held_valid: u16,
    /// Last reading of every sensor seen (also those the calibration does not use, so a new
    /// calibration that needs them has them at once).
    held_all: std::collections::HashMap<String, (f64, i64)>,
    estimator: Option<Estimator>,
    probe_type: String,
    /// The tip last found to be of `probe_type` (so its probe name is not compared again on
    /// every point); `None` whenever `probe_type` or the model changes.
    probe_tip: Option<u32>,
    /// The pose of the last point's tip and head angles (they rarely change).
    pose: Option<TipPose>,
    /// The estimates at the last two commands (the bracket of the next scale time), written
    /// in turn: `estimates[newest]` is the later one (e1), the other the earlier (e0).
    estimates: [Option<Estimate>; 2],
    newest: usize,
    judge: Judge,
    last_judged_t: Option<i64>,
    point_seq: u64,
    alarm_seq: u64,
    record_context: bool,
    stats: Stats,
    /// The host's bound on samples waiting per stream (a service serving many machines caps
    /// their memory below the calibration's `join.max_pending`).
    pending_limit: Option<usize>,
    /// Samples far behind their stream's latest, held until they prove a clock reset (or a
    /// sample in the old time base proves them late); count per stream.
    probation: Vec<Sample>,
    probation_n: [usize; 4],
    /// Samples whose seq went back while their time runs on, per stream, held until they
    /// prove a sequence restart (or a sample of the old sequence proves them duplicates).
    seq_hold: [Vec<Sample>; 4],
    /// The jump gates of the scale and probe streams.
    gates: [Gate; 2],
}

impl Corrector {
    /// A corrector for a calibration (validated here).
    pub fn new(cal: &Calibration) -> Result<Corrector, CalibError> {
        Ok(Corrector::with_model(Arc::new(cal.build()?)))
    }

    /// A corrector for an already built model.
    pub fn with_model(model: Arc<Model>) -> Corrector {
        let judge = Judge::new(
            model.filter.clone(),
            model.settings.judgement.threshold_mm_s2,
            model.settings.judgement.clear_fraction,
            model.raise_samples,
            model.clear_samples,
        );
        Corrector {
            model,
            intake: [Intake::default(); 4],
            cmd_q: VecDeque::new(),
            scale_q: VecDeque::new(),
            probe_q: VecDeque::new(),
            temp_q: VecDeque::new(),
            held: [(0.0, 0); MAX_SENSORS],
            held_valid: 0,
            held_all: Default::default(),
            estimator: None,
            probe_type: String::new(),
            probe_tip: None,
            pose: None,
            estimates: [None, None],
            newest: 0,
            judge,
            last_judged_t: None,
            point_seq: 0,
            alarm_seq: 0,
            record_context: false,
            stats: Stats::default(),
            pending_limit: None,
            probation: Vec::new(),
            probation_n: [0; 4],
            seq_hold: Default::default(),
            gates: Default::default(),
        }
        .with_effect_counters()
    }

    fn with_effect_counters(mut self) -> Corrector {
        self.stats.effect_points = vec![0; self.model.effects.len()];
        self
    }

    /// Effects of the calibration that have parameters but contributed nothing to any of the
    /// points so far: inactive for lack of a signal (no arcs and no curvature for the servo
    /// effects, no deflection for probe effects, positions outside a table, ...). Empty until
    /// a point has been produced.
    pub fn inactive_effects(&self) -> Vec<String> {
        if self.stats.points_out == 0 {
            return vec![];
        }
        self.model
            .effects
            .iter()
            .zip(&self.stats.effect_points)
            .filter(|(e, n)| **n == 0 && e.has_params)
            .map(|(e, _)| e.id.clone())
            .collect()
    }

    /// Also output each point's [`PointContext`] (for the model lab).
    pub fn record_context(&mut self, on: bool) {
        self.record_context = on;
    }

    /// The settings of the calibration in force (its version among them).
    pub fn settings(&self) -> &Settings {
        &self.model.settings
    }

    /// Effect ids in the order of [`CorrectedPoint::corrections`].
    pub fn effect_ids(&self) -> Vec<String> {
        self.model.effects.iter().map(|e| e.id.clone()).collect()
    }

    /// Temperature sensor names by [`PointContext::temps`] slot.
    pub fn sensor_names(&self) -> &[String] {
        self.model.sensors.names()
    }

    /// Counters.
    pub fn stats(&self) -> &Stats {
        &self.stats
    }

    /// Latest accepted t_ns per stream (command, scale, probe, temperature).
    pub fn watermarks(&self) -> [Option<i64>; 4] {
        [
            self.intake[0].last_t,
            self.intake[1].last_t,
            self.intake[2].last_t,
            self.intake[3].last_t,
        ]
    }

    /// Samples waiting per stream.
    pub fn pending(&self) -> [usize; 4] {
        [
            self.cmd_q.len(),
            self.scale_q.len() + self.gates[GATE_SCALE].held.len(),
            self.probe_q.len() + self.gates[GATE_PROBE].held.len(),
            self.temp_q.len(),
        ]
    }

    /// Switches to a new calibration at this sample boundary. Nothing buffered is lost; the
    /// estimator keeps running when the nominal model is unchanged and restarts (points
    /// flagged invalid while it settles) when it changed.
    pub fn set_model(&mut self, model: Arc<Model>) {
        // The discretised models (their sample period among their fields) decide what the
        // estimator does: equal bit for bit, its state carries over.
        if model.nominal != self.model.nominal {
            self.estimator = None;
            self.probe_type.clear();
        }
        self.probe_tip = None;
        let j = &model.settings.judgement;
        self.judge.reconfigure(
            model.filter.clone(),
            j.threshold_mm_s2,
            j.clear_fraction,
            model.raise_samples,
            model.clear_samples,
        );
        // Temperature slots may differ: re-resolve the held values by name. A lag the old
        // model ran too (same sensor and τ) keeps its state; a new one starts at the sensor's
        // last reading (the structure taken as in equilibrium with it).
        let (old, old_valid) = (self.held, self.held_valid);
        self.held_valid = 0;
        for (i, name) in model.sensors.names().iter().enumerate() {
            let tau = model.sensors.tau(i);
            let kept = (0..self.model.sensors.names().len()).find(|&o| {
                old_valid & (1 << o) != 0
                    && tau > 0.0
                    && self.model.sensors.names()[o] == *name
                    && self.model.sensors.tau(o) == tau
            });
            if let Some(o) = kept {
                self.held[i] = old[o];
                self.held_valid |= 1 << i;
            } else if let Some((v, t)) = self.held_all.get(name) {
                self.held[i] = (*v, *t);
                self.held_valid |= 1 << i;
            }
        }
        for p in self.temp_q.iter_mut() {
            p.used = model.sensors.uses(&p.sensor);
        }
        self.stats.effect_points = vec![0; model.effects.len()];
        // The tips' geometry may differ.
        self.pose = None;
        self.model = model;
    }

    /// Caps the samples waiting per stream at `limit` (at least 1), below the calibration's
    /// `join.max_pending` when smaller; `None` leaves the calibration's bound alone. Samples
    /// pushed out of a full buffer are counted as `buffer_overflow`.
    pub fn limit_pending(&mut self, limit: Option<usize>) {
        self.pending_limit = limit.map(|l| l.max(1));
    }

    /// The bound on samples waiting per stream in force.
    pub fn max_pending(&self) -> usize {
        let m = self.model.settings.join.max_pending.max(1);
        self.pending_limit.map_or(m, |l| l.min(m))
    }

    /// Gives back the room of join buffers that hold far less than they have room for (a
    /// batch of one stream waits in its buffer for the others, and the room it took would
    /// otherwise stay with the machine until the next batch). A service serving many
    /// machines calls this between messages, so only the machines whose samples are waiting
    /// hold room. Changes capacities only, never what is corrected.
    pub fn trim(&mut self) {
        fn trim<T>(q: &mut VecDeque<T>) {
            // Room for a few samples stays: a batch grows from there in a few doublings.
            const KEEP: usize = 8;
            if q.capacity() > KEEP && q.capacity() >= 4 * q.len() {
                q.shrink_to(KEEP.max(q.len()));
            }
        }
        trim(&mut self.cmd_q);
        trim(&mut self.scale_q);
        trim(&mut self.probe_q);
        trim(&mut self.temp_q);
    }

    /// Bytes held by this corrector's own state: the struct and the capacity of its buffers
    /// (not the calibration model, which is shared and counted once by its owner).
    pub fn state_bytes(&self) -> usize {
        use std::mem::size_of;
        size_of::<Corrector>()
            + self.cmd_q.capacity() * size_of::<CommandSample>()
            + self.scale_q.capacity() * size_of::<ScaleSample>()
            + self.probe_q.capacity() * size_of::<ProbeSample>()
            + self.temp_q.capacity() * size_of::<PendingTemp>()
            + self
                .temp_q
                .iter()
                .map(|p| p.sensor.capacity())
                .sum::<usize>()
            + self.held_all.capacity() * size_of::<(String, (f64, i64))>()
            + self.held_all.keys().map(|k| k.capacity()).sum::<usize>()
            + self
                .seq_hold
                .iter()
                .map(|h| h.capacity() * size_of::<Sample>())
                .sum::<usize>()
            + self
                .gates
                .iter()
                .map(|g| {
                    g.held.capacity() * size_of::<Sample>()
                        + g.flagged.capacity() * size_of::<(i64, i64)>()
                })
                .sum::<usize>()
            + self.probe_type.capacity()
            + self.judge.heap_bytes()
    }

    /// Takes one sample and appends whatever it completes to `out`.
    pub fn push(&mut self, sample: Sample, out: &mut Output) {
        let k = sample.stream() as usize;
        self.stats.samples_in[k] += 1;
        let t = sample.t_ns();
        let behind = self.intake[k]
            .last_t
            .is_some_and(|l| t < l && t < l.saturating_sub(self.model.clock_reset_ns));
        if behind && sample.is_finite() {
            self.probation.push(sample);
            self.probation_n[k] += 1;
            if self.probation_n[k] >= self.model.settings.join.clock_reset_samples {
                self.reset_clock(out);
            }
            return;
        }
        if self.probation_n[k] > 0 {
            // A sample in the old time base: what was held was late, not a new time base.
            self.probation.retain(|s| s.stream() as usize != k);
            self.stats.dropped[DropReason::OutOfOrder as usize] += self.probation_n[k] as u64;
            self.probation_n[k] = 0;
        }
        let st = self.intake[k];
        let seq_back = st.last_seq.is_some_and(|l| sample.seq() <= l);
        let time_on = st.last_t.is_some_and(|l| t > l);
        if seq_back && time_on && sample.is_finite() {
            // The sequence went back while time runs on: a wrap or restart of the counter,
            // or the samples after a bogus jump; held until enough in a row confirm it.
            self.seq_hold[k].push(sample);
            if self.seq_hold[k].len() >= self.model.settings.join.seq_reset_samples {
                self.stats.seq_resets += 1;
                self.intake[k].last_seq = None;
                for s in std::mem::take(&mut self.seq_hold[k]) {
                    self.take(s, out);
                }
            }
            return;
        }
        if !self.seq_hold[k].is_empty() {
            // The old sequence goes on: what was held repeated its numbers.
            self.stats.dropped[DropReason::Duplicate as usize] += self.seq_hold[k].len() as u64;
            self.seq_hold[k].clear();
        }
        self.take(sample, out);
    }

    /// The controller's clock was reset: what the old time base can still give is given, the
    /// join, estimator and judgement restart (point and alarm `seq` run on), and the samples
    /// that proved the reset are taken in the new time base.
    fn reset_clock(&mut self, out: &mut Output) {
        self.drop_held();
        self.emit(true, out);
        self.cmd_q.clear();
        self.probe_q.clear();
        self.temp_q.clear();
        self.intake = [Intake::default(); 4];
        self.held_valid = 0;
        self.held_all.clear();
        self.estimator = None;
        self.probe_type.clear();
        self.probe_tip = None;
        self.estimates = [None, None];
        self.judge.restart();
        self.last_judged_t = None;
        for g in self.gates.iter_mut() {
            g.reset();
        }
        self.stats.clock_resets += 1;
        self.probation_n = [0; 4];
        for h in self.seq_hold.iter_mut() {
            // Held in the old time base; with the new one they are late.
            self.stats.dropped[DropReason::OutOfOrder as usize] += h.len() as u64;
            h.clear();
        }
        for s in std::mem::take(&mut self.probation) {
            self.take(s, out);
        }
    }

    /// Taken into [`Self::push`] (its one caller per sample): the sample is not copied
    /// once more to be handed over.
    #[inline(always)]
    fn take(&mut self, sample: Sample, out: &mut Output) {
        if self.accept(&sample) {
            match sample {
                Sample::Scale(_) | Sample::Probe(_) => self.screen(sample),
                _ => self.enqueue(sample),
            }
        }
        self.emit(false, out);
    }

    /// The jump gate (the module's "Jump gate"): a scale or probe sample on its stream's
    /// track is queued; off it, held; the samples held are dropped when the stream is back
    /// on its track, and taken when it stays off it.
    #[inline]
    fn screen(&mut self, sample: Sample) {
        let g = match sample {
            Sample::Scale(_) => GATE_SCALE,
            _ => GATE_PROBE,
        };
        let (v, tip) = gate_values(&sample);
        let t = sample.t_ns();
        let (limits, gap) = (&self.model.settings.limits, self.model.max_gap_ns);
        let gate = &mut self.gates[g];
        if gate.fits(g == GATE_PROBE, t, &v, tip, limits, gap) {
            if !gate.held.is_empty() {
                // Off the track and back: no machine moves so.
                let n = gate.held.len() as u64;
                gate.held.clear();
                let after = gate.taken_t.unwrap_or(i64::MIN);
                gate.flag(after, t);
                self.stats.dropped[DropReason::ImplausibleJump as usize] += n;
            }
            gate.record(t, v, tip);
            return self.enqueue(sample);
        }
        gate.held.push(sample);
        if gate.held.len() < limits.jump_confirm_samples {
            return;
        }
        // The stream stays where it jumped: it moved. Its samples are taken, the track
        // restarts from them, and the points across the jump are flagged.
        let mut held = std::mem::take(&mut gate.held);
        let after = gate.taken_t.unwrap_or(i64::MIN);
        gate.flag(after, held.last().map_or(t, |s| s.t_ns()));
        gate.hist = [None, None];
        self.stats.stream_jumps[if g == GATE_SCALE { 1 } else { 2 }] += 1;
        for s in held.drain(..) {
            let (v, tip) = gate_values(&s);
            self.gates[g].record(s.t_ns(), v, tip);
            self.enqueue(s);
        }
        // The list's room is kept for the next jump.
        self.gates[g].held = held;
    }

    /// Drops the samples the jump gates hold (end of input, or a new time base): nothing
    /// confirmed them.
    fn drop_held(&mut self) {
        for g in self.gates.iter_mut() {
            self.stats.dropped[DropReason::ImplausibleJump as usize] += g.held.len() as u64;
            g.held.clear();
        }
    }

    /// Puts an accepted sample into its join buffer (a temperature the calibration does not
    /// use only into the held readings).
    #[inline(always)]
    fn enqueue(&mut self, sample: Sample) {
        {
            // Make room first, so a buffer never holds (or allocates for) more than `max`.
            let max = self.max_pending();
            match sample {
                Sample::Command(c) => {
                    if self.cmd_q.len() >= max {
                        self.cmd_q.pop_front();
                        self.drop(DropReason::BufferOverflow);
                    }
                    self.cmd_q.push_back(c);
                }
                Sample::Scale(s) => {
                    if self.scale_q.len() >= max {
                        self.scale_q.pop_front();
                        self.drop(DropReason::BufferOverflow);
                    }
                    self.scale_q.push_back(s);
                }
                Sample::Probe(p) => {
                    if self.probe_q.len() >= max {
                        self.probe_q.pop_front();
                        self.drop(DropReason::BufferOverflow);
                    }
                    self.probe_q.push_back(p);
                }
                Sample::Temperature(t) => {
                    let used = self.model.sensors.uses(&t.sensor);
                    if !used {
                        // Not used by this calibration: only its last reading is kept (for a
                        // calibration that needs it), for a bounded number of names.
                        self.hold(&PendingTemp {
                            t_ns: t.t_ns,
                            sensor: t.sensor,
                            used: false,
                            celsius: t.celsius,
                        });
                        return;
                    }
                    if self.temp_q.len() >= max {
                        let p = self.temp_q.pop_front().expect("non-empty");
                        self.hold(&p);
                    }
                    self.temp_q.push_back(PendingTemp {
                        t_ns: t.t_ns,
                        used,
                        celsius: t.celsius,
                        sensor: t.sensor,
                    });
                }
            }
        }
    }

    /// Takes many samples.
    pub fn push_all(&mut self, samples: impl IntoIterator<Item = Sample>, out: &mut Output) {
        for s in samples {
            self.push(s, out);
        }
    }

    /// End of input: produces every point that can still be produced and drops the rest.
    pub fn flush(&mut self, out: &mut Output) {
        self.stats.dropped[DropReason::OutOfOrder as usize] += self.probation.len() as u64;
        self.probation.clear();
        for h in self.seq_hold.iter_mut() {
            // Never confirmed as a new sequence: they repeated the old one's numbers.
            self.stats.dropped[DropReason::Duplicate as usize] += h.len() as u64;
            h.clear();
        }
        self.probation_n = [0; 4];
        self.drop_held();
        self.emit(true, out);
    }

    fn drop(&mut self, r: DropReason) {
        self.stats.dropped[r as usize] += 1;
    }

    #[inline(always)]
    fn accept(&mut self, s: &Sample) -> bool {
        let k = s.stream() as usize;
        let (seq, t, finite) = (s.seq(), s.t_ns(), s.is_finite());
        let st = &mut self.intake[k];
        if !finite {
            self.stats.dropped[DropReason::NonFinite as usize] += 1;
            return false;
        }
        if let Err(r) = plausible(s, &self.model) {
            self.stats.dropped[r as usize] += 1;
            return false;
        }
        if st.last_seq.is_some_and(|l| seq <= l) {
            self.stats.dropped[DropReason::Duplicate as usize] += 1;
            return false;
        }
        // Temperatures of several sensors may share a time stamp; other streams may not.
        let back = if k == StreamId::Temperature as usize {
            st.last_t.is_some_and(|l| t < l)
        } else {
            st.last_t.is_some_and(|l| t <= l)
        };
        if back {
            self.stats.dropped[DropReason::OutOfOrder as usize] += 1;
            return false;
        }
        if let Some(l) = st.last_seq.filter(|l| seq > l.saturating_add(1)) {
            self.stats.seq_gaps[k] += 1;
            // A jump the stream cannot have made in the time since its last sample (a bogus
            // seq, a counter restarted higher) loses no sample: its return is a seq reset.
            let dt = st.last_t.map_or(0, |l| t.saturating_sub(l));
            if seq - l - 1 <= plausible_missing(dt, &self.model) {
                self.stats.samples_missing[k] =
                    self.stats.samples_missing[k].saturating_add(seq - l - 1);
            }
        }
        st.last_seq = Some(seq);
        st.last_t = Some(t);
        true
    }

    fn hold(&mut self, p: &PendingTemp) {
        let room = self.held_all.len() < MAX_KEPT_SENSORS || p.used;
        match self.held_all.get_mut(&p.sensor) {
            Some(h) => *h = (p.celsius, p.t_ns),
            None if room => {
                self.held_all.insert(p.sensor.clone(), (p.celsius, p.t_ns));
            }
            None => self.drop(DropReason::UnknownSensor),
        }
        if p.used {
            // Every slot of this sensor: its reading, or the reading through a lag
            // (thermal_drift), advanced by the time since the slot's previous reading.
            let sensors = &self.model.sensors;
            for slot in 0..sensors.names().len() {
                if sensors.names()[slot] != p.sensor {
                    continue;
                }
                let (z, t0) = self.held[slot];
                let v = if self.held_valid & (1 << slot) == 0 || p.t_ns <= t0 {
                    if self.held_valid & (1 << slot) != 0 && sensors.tau(slot) > 0.0 {
                        // A second reading at the same instant: the lag has had no time.
                        z
                    } else {
                        p.celsius
                    }
                } else {
                    Lag {
                        tau_s: sensors.tau(slot),
                    }
                    .step(z, p.celsius, (p.t_ns - t0) as f64 * 1e-9)
                };
                self.held[slot] = (v, p.t_ns);
                self.held_valid |= 1 << slot;
            }
        }
    }

    /// Whether the oldest scale sample can be corrected now: the command, probe and (when
    /// the calibration reads temperatures) temperature streams have reached its time.
    #[inline]
    fn front_ready(&self) -> bool {
        let Some(s) = self.scale_q.front() else {
            return false;
        };
        let wm = self.watermarks();
        // The probe stream has arrived up to the last sample its jump gate took.
        let probe = &self.gates[GATE_PROBE];
        let wp = if probe.held.is_empty() {
            wm[2]
        } else {
            probe.taken_t
        };
        wm[0].is_some_and(|w| w >= s.t_ns)
            && wp.is_some_and(|w| w >= s.t_ns)
            && (self.model.sensors.names().is_empty()
                || wm[3].is_some_and(|w| w >= s.t_ns - self.model.temperature_delay_ns))
    }

    /// Corrects the scale samples that can be corrected (all of them on `flush`). Checked
    /// here, inline, for every sample taken: most samples complete no point, and then no
    /// call is made.
    #[inline]
    fn emit(&mut self, flush: bool, out: &mut Output) {
        if flush || self.front_ready() {
            self.emit_ready(flush, out);
        }
    }

    #[inline(never)]
    fn emit_ready(&mut self, flush: bool, out: &mut Output) {
        while flush && !self.scale_q.is_empty() || self.front_ready() {
            let s = self.scale_q.pop_front().expect("a scale sample is waiting");
            if let Err(r) = self.point(s, out) {
                self.drop(r);
            }
        }
    }

    /// The estimate at the latest command stepped (e1).
    fn e1(&self) -> Option<&Estimate> {
        self.estimates[self.newest].as_ref()
    }

    /// The estimate at the command before it (e0).
    fn e0(&self) -> Option<&Estimate> {
        self.estimates[1 - self.newest].as_ref()
    }

    /// Steps the estimator through the commands up to the first at or after `t`.
    fn advance_estimator(&mut self, t: i64) {
        while self.e1().is_none_or(|e| e.cmd.t_ns < t) {
            let Some(c) = self.cmd_q.front() else {
                break;
            };
            let gap = self
                .e1()
                .is_some_and(|e| c.t_ns - e.cmd.t_ns > self.model.max_gap_ns);
            // The later estimate becomes the earlier one: the new one goes to the other slot,
            // in place when it holds one (not copied there from a temporary), stepped from the
            // command where it waits, then dropped from the queue (popped first, it was copied
            // out whole and its fields read back at once, waiting on that copy).
            let slot = 1 - self.newest;
            if let (false, Some(est), Some(e)) =
                (gap, self.estimator.as_mut(), self.estimates[slot].as_mut())
            {
                est.step_into(c, e);
                self.newest = slot;
                self.cmd_q.pop_front();
                continue;
            }
            let c = self.cmd_q.pop_front().expect("the front was just read");
            let est = match self.estimator.as_mut() {
                Some(est) if !gap => est.step(&c),
                Some(est) => est.restart(&c),
                None => {
                    let probe = self.probe_type_for(t);
                    let m = self.model.nominal[&probe].clone();
                    self.probe_type = probe;
                    self.probe_tip = None;
                    let mut est = Estimator::new(m);
                    let e = est.restart(&c);
                    self.estimator = Some(est);
                    e
                }
            };
            self.newest = slot;
            self.estimates[slot] = Some(est);
        }
    }

    fn probe_type_for(&self, _t: i64) -> String {
        // The tip active at the front of the probe buffer; the first tip otherwise.
        self.probe_q
            .front()
            .and_then(|p| self.model.tips.get(&p.tip_id))
            .or_else(|| self.model.tips.values().next())
            .map(|t| t.probe.clone())
            .expect("a built model has at least one tip")
    }

    fn point(&mut self, s: ScaleSample, out: &mut Output) -> Result<(), DropReason> {
        let t = s.t_ns;
        let gap = self.model.max_gap_ns;
        // Command bracket → estimate at t.
        self.advance_estimator(t);
        let e1 = self.e1().ok_or(DropReason::NoCommand)?;
        // At a command's own time the estimate is read in place below (not copied out here:
        // its fields were just written one by one, and a copy would read them back whole);
        // between two commands it is interpolated.
        let between = if e1.cmd.t_ns == t {
            None
        } else if e1.cmd.t_ns < t {
            return Err(DropReason::NoCommand);
        } else {
            let e0 = self
                .e0()
                .filter(|e| e.cmd.t_ns <= t)
                .ok_or(DropReason::NoCommand)?;
            if e1.cmd.t_ns - e0.cmd.t_ns > gap {
                return Err(DropReason::CommandGap);
            }
            Some(lerp_estimate(e0, e1, t))
        };
        // Probe bracket.
        while self.probe_q.len() >= 2 && self.probe_q[1].t_ns <= t {
            self.probe_q.pop_front();
        }
        let p0 = *self.probe_q.front().ok_or(DropReason::NoProbe)?;
        if p0.t_ns > t {
            return Err(DropReason::NoProbe);
        }
        let (defl_probe, force_n) = if p0.t_ns == t {
            (p0.deflection, p0.force_n)
        } else {
            let p1 = *self.probe_q.get(1).ok_or(DropReason::NoProbe)?;
            if p1.t_ns - p0.t_ns > gap {
                return Err(DropReason::ProbeGap);
            }
            let w = (t - p0.t_ns) as f64 / (p1.t_ns - p0.t_ns) as f64;
            // The force between two readings that both carry one; none otherwise.
            let force = match (p0.force_n, p1.force_n) {
                (Some(a), Some(b)) => Some(a + (b - a) * w),
                _ => None,
            };
            (p0.deflection + (p1.deflection - p0.deflection) * w, force)
        };
        // Temperatures measured up to t − delay.
        let t_temp = t - self.model.temperature_delay_ns;
        while self.temp_q.front().is_some_and(|p| p.t_ns <= t_temp) {
            let p = self.temp_q.pop_front().expect("non-empty");
            self.hold(&p);
        }
        let n_sensors = self.model.sensors.names().len();
        for slot in 0..n_sensors {
            if self.held_valid & (1 << slot) == 0 {
                return Err(DropReason::TemperatureMissing);
            }
            if t_temp - self.held[slot].1 > self.model.temperature_max_age_ns {
                return Err(DropReason::TemperatureStale);
            }
        }
        // Tip and probe model.
        let model: &Model = &self.model;
        let tip = model.tips.get(&p0.tip_id).ok_or(DropReason::UnknownTip)?;
        if self.probe_tip != Some(p0.tip_id) {
            if tip.probe != self.probe_type {
                if let Some(est) = self.estimator.as_mut() {
                    let e1 = self.estimates[self.newest]
                        .as_ref()
                        .expect("a point has an estimate");
                    est.switch_model(model.nominal[&tip.probe].clone(), &e1.cmd);
                }
                self.probe_type.clone_from(&tip.probe);
            }
            self.probe_tip = Some(p0.tip_id);
        }
        let settled = self.estimator.as_ref().is_some_and(|e| e.settled());

        let pose = match self.pose {
            Some(pose) if pose.is_for(p0.tip_id, p0.head_a1_deg, p0.head_a2_deg) => pose,
            _ => *self
                .pose
                .insert(TipPose::new(tip, p0.head_a1_deg, p0.head_a2_deg)),
        };
        let est = match &between {
            Some(e) => e,
            None => self.estimates[self.newest]
                .as_ref()
                .expect("a point has an estimate"),
        };
        let r = pose.machine_from_probe;
        let cmd = &est.cmd;
        let (f_hz, rot_axis) = rotation(&est.pos, &est.vel, &cmd.arc_center, cmd.arc_radius);
        let mut ctx = PointContext {
            t_ns: t,
            scale: s.pos,
            command: cmd.pos,
            est_pos: est.pos,
            est_vel: est.vel,
            est_acc: est.acc,
            arc_center: if cmd.arc_radius > 0.0 {
                cmd.arc_center
            } else {
                Vec3::zeros()
            },
            arc_radius: cmd.arc_radius,
            f_hz,
            rot_axis,
            deflection_probe: defl_probe,
            deflection: r * defl_probe,
            force_n,
            machine_from_probe: r,
            tip_shank: pose.shank,
            tip_bent: pose.bent,
            tip_radius: tip.radius_mm,
            tip_id: p0.tip_id,
            head_a1_deg: p0.head_a1_deg,
            head_a2_deg: p0.head_a2_deg,
            segment_id: cmd.segment_id,
            temps: [0.0; MAX_SENSORS],
            temps_valid: 0,
        };
        for (v, (celsius, _)) in ctx.temps.iter_mut().zip(&self.held).take(n_sensors) {
            *v = *celsius;
        }
        ctx.temps_valid = self.held_valid;

        // Judgement (only on consecutive scale samples).
        if self.last_judged_t.is_none_or(|l| t - l > gap) {
            self.judge.restart();
        }
        self.last_judged_t = Some(t);
        let version = model.settings.version;
        let action = model.settings.judgement.action;
        let threshold = model.settings.judgement.threshold_mm_s2;
        let (alarm_seq, stats) = (&mut self.alarm_seq, &mut self.stats);
        self.judge.update(t, s.pos, est.acc, settled, &mut |tr| {
            if tr.raised {
                stats.alarms_raised += 1;
            }
            out.alarms.push(Alarm {
                seq: *alarm_seq,
                t_ns: t,
                raised: tr.raised,
                axis: tr.axis,
                estimated_accel: tr.estimated,
                measured_accel: tr.measured,
                difference: tr.estimated - tr.measured,
                threshold,
                action,
                calibration_version: version,
            });
            *alarm_seq += 1;
        });
        let alarm = self.judge.any_raised();
        let suspend = alarm && action == AlarmAction::Suspend;

        let mut corrections = out.corrections_list();
        let point = synthesize_into(
            &ctx,
            &model.effects,
            suspend,
            model.settings.min_contact_deflection_mm,
            &mut corrections,
        );
        if !inside(&point, &corrections, model) {
            out.spare.push(corrections);
            return Err(DropReason::ImplausibleOutput);
        }
        for (n, c) in self.stats.effect_points.iter_mut().zip(&corrections) {
            *n += u64::from(*c != Vec3::zeros());
        }
        // Points across a jump of the scales or the probe (the jump gate) are flagged.
        let jumped = self.gates[GATE_SCALE].flags(t) | self.gates[GATE_PROBE].flags(t);
        let valid = settled && !alarm && !jumped;
        out.points.push(CorrectedPoint {
            seq: self.point_seq,
            t_ns: t,
            sample_seq: s.seq,
            surface: point.surface,
            tip_center: point.tip_center,
            normal: point.normal,
            corrections,
            calibration_version: version,
            estimator_valid: valid,
            segment_id: cmd.segment_id,
            tip_id: p0.tip_id,
        });
        if self.record_context {
            out.contexts.push(ctx);
        }
        self.point_seq += 1;
        self.stats.points_out += 1;
        if !valid {
            self.stats.points_invalid += 1;
        }
        Ok(())
    }
}
