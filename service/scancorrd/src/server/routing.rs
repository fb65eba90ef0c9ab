//! The routing of raw messages: a served machine's to its shard (a new one made served first),
//! the rest refused and counted; the streams' stalls.

use super::*;

impl State {
    /// Counts a refusal and logs it at most once per [`LOG_EVERY`] per reason.
    pub(super) fn refuse(&mut self, reason: Refusal, what: &str) {
        let r = &mut self.refused;
        *match reason {
            Refusal::NotServed => &mut r.not_served,
            Refusal::OverCapacity => &mut r.over_capacity,
            Refusal::BadKey => &mut r.bad_key,
            Refusal::BadQuery => &mut r.bad_query,
        } += 1;
        if let Some(n) = self.log.pass(reason) {
            warn!(
                reason = reason.name(),
                count = n,
                latest = %scancorr_proto::names::shown(what),
                "refused (logged at most once per {} s per reason)",
                LOG_EVERY.as_secs()
            );
        }
    }

    /// A raw message the routes gave the control task (see [`Routes`]).
    pub(super) async fn on_raw(&mut self, s: zenoh::sample::Sample, arrived: Instant) {
        let machine =
            Stream::parse_key(&self.cfg.prefix, s.key_expr().as_str()).map(|(m, _)| m.to_string());
        self.route_raw(s, arrived).await;
        if let Some(m) = machine {
            self.routes.done(&m);
        }
    }

    pub(super) async fn route_raw(&mut self, s: zenoh::sample::Sample, arrived: Instant) {
        let key = s.key_expr().as_str();
        // A wildcard or otherwise invalid machine id, or an unknown stream, is refused here.
        let parsed = Stream::parse_key(&self.cfg.prefix, key);
        if let Some((machine, _)) = parsed.filter(|(_, st)| Stream::MEASUREMENT.contains(st)) {
            // Distance probes and the micro-stage (v1.2) are measurements for calibration
            // procedures, not inputs of the correction: never decoded, counted on the
            // machine's status (no machine state is made for them), said once in the log.
            if !self.told_not_corrected {
                self.told_not_corrected = true;
                info!("messages on raw/distance and raw/stage (measurements the service does not correct) are skipped and counted as `not_corrected` on the status");
            }
            match self.machines.get_mut(machine) {
                Some(m) => {
                    m.not_corrected += 1;
                    m.input
                        .arrived
                        .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                }
                None => self.refused.not_corrected += 1,
            }
            return;
        }
        let Some((machine, sid)) =
            parsed.and_then(|(m, st)| Some((m.to_string(), wire::stream_id(st)?)))
        else {
            let key = key.to_string();
            self.refuse(Refusal::BadKey, &key);
            return;
        };
        if !self.cfg.serves(&machine) {
            self.refuse(Refusal::NotServed, &machine);
            return;
        }
        if !self.machines.contains_key(&machine) && self.machines.len() >= self.cfg.max_machines {
            self.refuse(Refusal::OverCapacity, &machine);
            return;
        }
        match self.machine(&machine).await {
            Ok(_) => {}
            Err(ServiceError::ServedElsewhere(_)) => {
                self.refused.served_elsewhere += 1;
                return;
            }
            Err(e) => {
                warn!(machine = %machine, error = %e, "cannot serve machine");
                return;
            }
        }
        // Decoded, corrected and published on the machine's shard, in arrival order (or shed,
        // counted, when its queue there is full); never waits.
        self.routes.deliver(&machine, sid, &s, arrived);
    }

    pub(super) fn check_stalls(&mut self) {
        let limit = Duration::from_millis(self.cfg.stall_after_ms);
        let arrivals = self.routes.last_arrivals();
        for (name, m) in self.machines.iter_mut() {
            let last_arrival = arrivals.get(name).copied().unwrap_or_default();
            for (k, at) in last_arrival.iter().enumerate() {
                if m.stalled[k] && at.is_some_and(|t| t.elapsed() <= limit) {
                    m.stalled[k] = false;
                    info!(machine = %name, stream = scancorr_core::sample::StreamId::ALL[k].name(), "stream resumed");
                }
            }
            let Some(scale) = last_arrival[1] else {
                continue;
            };
            if scale.elapsed() > limit {
                continue; // nothing is coming at all: the machine is idle, not stalled
            }
            for k in [0usize, 2, 3] {
                let silent = last_arrival[k].is_none_or(|t| t.elapsed() > limit);
                if silent && !m.stalled[k] {
                    m.stalled[k] = true;
                    warn!(machine = %name, stream = scancorr_core::sample::StreamId::ALL[k].name(), "stream stalled: no samples while the scales keep coming; no points are produced past it");
                }
            }
        }
    }
}
