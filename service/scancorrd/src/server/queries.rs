//! The status and calibration queryables: a machine's status, calibration reads, puts and
//! rollbacks with their audit records.

use super::*;
use crate::store::Audit;
use scancorr_core::Calibration;

impl State {
    pub(super) async fn on_status(&mut self, q: zenoh::query::Query) {
        let key = q.key_expr().as_str().to_string();
        let Some(machine) = scancorr_proto::machine_of(&self.cfg.prefix, &key, "status") else {
            self.refuse(Refusal::BadQuery, &key);
            let _ = q
                .reply_err(format!(
                    "{}: not the status key of one machine ({}/<machine>/status)",
                    scancorr_proto::names::shown(&key),
                    self.cfg.prefix
                ))
                .await;
            return;
        };
        let machine = machine.to_string();
        if self.answered_elsewhere(&machine) {
            return;
        }
        let Some(m) = self.machines.get(&machine) else {
            let body = json!({"machine": machine, "served": false, "refused": self.refused_now()});
            let _ = q.reply(q.key_expr().clone(), body.to_string()).await;
            return;
        };
        if q.parameters().contains_key("input") {
            // Only what arrived of the machine's input, read where it is counted, at once:
            // what `replay` asks to learn that its messages arrived, and to pace itself.
            // `calibrated`: a calibration is in use (put or loaded, not quarantined): when
            // false, what arrives is counted as uncorrected and no point is published.
            let calibrated = m.point_cost_us.is_some() && m.quarantined.is_none();
            let body = json!({"machine": machine, "served": true, "calibrated": calibrated, "input": m.input.figures()});
            let _ = q.reply(q.key_expr().clone(), body.to_string()).await;
            return;
        }
        let stalled: Vec<&str> = (0..4)
            .filter(|k| m.stalled[*k])
            .map(|k| scancorr_core::sample::StreamId::ALL[k].name())
            .collect();
        let base = json!({
            "machine": machine,
            "served": true,
            "quarantined": m.quarantined,
            "output": m.outbox.figures(),
            // With fail-over: active or standby for this machine, since when.
            "failover": m.fo.as_ref().map(super::failover::fo_json),
            // Raw messages that reached the service, and those it shed (its shard fell
            // behind real time with them, or their queue there was full).
            "input": m.input.figures(),
            // What its calibration costs per point, measured on a reference point when it was
            // put or loaded, and the limit a put is held to (0: none).
            "point_cost_us": m.point_cost_us.map(|c| (c * 100.0).round() / 100.0),
            "max_point_cost_us": self.cfg.max_point_cost_us,
            "stalled": stalled,
            // Wall time since the newest raw message arrived, ms.
            "last_sample_age_ms": self.routes.last_arrival(&machine).iter().flatten().map(|t| t.elapsed()).min().map(|d| d.as_secs_f64() * 1e3),
            "worker": m.shard,
        });
        let not_corrected = m.not_corrected;
        let h = &self.shards[m.shard];
        let (jobs, board, asked, slot) = (
            h.jobs.clone(),
            h.board.clone(),
            h.snaps_asked.clone(),
            m.slot,
        );
        // The snapshot is taken on the machine's shard after the messages routed before this
        // query (so a status after a put or a replay sees them), awaited by a task of its
        // own: this loop never waits on a shard. A shard that does not answer within
        // STATUS_WAIT (or already has many snapshots to take) is answered for with its latest
        // published snapshot, its age said.
        tokio::spawn(async move {
            let fresh = if asked.fetch_add(1, std::sync::atomic::Ordering::AcqRel) < MAX_SNAPS_ASKED
            {
                let (tx, rx) = tokio::sync::oneshot::channel();
                match jobs.send(Job::Snap(machine.clone(), tx)) {
                    Ok(()) => tokio::time::timeout(STATUS_WAIT, rx)
                        .await
                        .ok()
                        .and_then(|r| r.ok()),
                    Err(_) => None,
                }
            } else {
                asked.fetch_sub(1, std::sync::atomic::Ordering::AcqRel);
                None
            };
            let is_fresh = fresh.is_some();
            let snap = fresh.or_else(|| board.get(slot));
            let body = status_body(base, snap.as_ref(), not_corrected, is_fresh);
            let _ = q.reply(q.key_expr().clone(), body.to_string()).await;
        });
    }

    pub(super) async fn on_calibration(&mut self, q: zenoh::query::Query) {
        let key = q.key_expr().as_str().to_string();
        let write = key.ends_with("/calibration/write");
        let suffix = if write {
            "calibration/write"
        } else {
            "calibration"
        };
        let Some(machine) = scancorr_proto::machine_of(&self.cfg.prefix, &key, suffix) else {
            self.refuse(Refusal::BadQuery, &key);
            let _ = q
                .reply_err(format!(
                    "{}: not the calibration key of one machine ({}/<machine>/calibration; machine ids are 1–{} characters of A–Z a–z 0–9 _ - .)",
                    scancorr_proto::names::shown(&key),
                    self.cfg.prefix,
                    scancorr_proto::names::MAX_NAME_LEN
                ))
                .await;
            return;
        };
        let machine = machine.to_string();
        if self.answered_elsewhere(&machine) {
            return;
        }
        // Changes (put, rollback) on the write key only, reads on the other: access control
        // gives them to different roles.
        if write != (q.payload().is_some() || q.parameters().contains_key("rollback")) {
            let _ = q
                .reply_err(scancorr_proto::calibration_keys_misused(
                    &self.cfg.prefix,
                    &machine,
                    write,
                ))
                .await;
            return;
        }
        if q.payload().is_some()
            && !self.machines.contains_key(&machine)
            && self.cfg.serves(&machine)
            && self.served_elsewhere(&machine).await
        {
            return;
        }
        let reply = match q.payload() {
            Some(p) => {
                let audit = audit_of(&q, "put".into());
                self.put_calibration(&machine, &p.to_bytes(), audit).await
            }
            None => {
                let params = q.parameters();
                if let Some(to) = params.get("rollback") {
                    let to = to.to_string();
                    self.rollback(&machine, &to, audit_of(&q, format!("rollback to v{to}")))
                        .await
                } else if params.contains_key("history") {
                    self.store
                        .history(&machine)
                        .map(|h| serde_json::to_string(&h).expect("serialisable"))
                        .map_err(|e| e.to_string())
                } else if let Some(v) = params.get("version") {
                    match v.parse::<u64>() {
                        Ok(v) => match self.store.get(&machine, v) {
                            Ok(Some(c)) => Ok(c.to_json()),
                            Ok(None) => Err(format!(
                                "machine `{machine}` has no calibration version {v}"
                            )),
                            Err(e) => Err(e.to_string()),
                        },
                        Err(_) => Err(format!("version `{v}` is not a number")),
                    }
                } else {
                    match self.store.current(&machine) {
                        Ok(Some(c)) => Ok(c.to_json()),
                        Ok(None) => Err(format!("machine `{machine}` has no calibration")),
                        Err(e) => Err(e.to_string()),
                    }
                }
            }
        };
        let _ = match reply {
            Ok(body) => q.reply(q.key_expr().clone(), body).await,
            Err(e) => q.reply_err(e).await,
        };
    }

    /// Makes version `to` current again as a new version (its parent the current one).
    pub(super) async fn rollback(
        &mut self,
        machine: &str,
        to: &str,
        audit: Audit,
    ) -> Result<String, String> {
        let v: u64 = to.parse().map_err(|_| {
            format!(
                "rollback `{}`: not a version number",
                scancorr_proto::names::shown(to)
            )
        })?;
        let mut cal = match self.store.get(machine, v) {
            Ok(Some(c)) => c,
            Ok(None) => {
                return Err(format!(
                    "machine `{machine}` has no calibration version {v}"
                ))
            }
            Err(e) => return Err(e.to_string()),
        };
        let current = self
            .store
            .current(machine)
            .ok()
            .flatten()
            .map(|c| c.version);
        if current == Some(v) {
            return Err(format!(
                "version {v} of machine `{machine}` is already current"
            ));
        }
        cal.parent_version = current;
        cal.note = format!("rollback to v{v} ({})", cal.note);
        let doc = cal.to_json();
        self.put_calibration(machine, doc.as_bytes(), audit).await
    }

    pub(super) async fn put_calibration(
        &mut self,
        machine: &str,
        bytes: &[u8],
        audit: Audit,
    ) -> Result<String, String> {
        let max = self.cfg.max_message_bytes.min(crate::store::MAX_DOC_BYTES);
        if bytes.len() > max {
            return Err(format!(
                "the calibration document has {} bytes, more than the {max} this service accepts",
                bytes.len()
            ));
        }
        let text = std::str::from_utf8(bytes)
            .map_err(|_| "the calibration document is not UTF-8 text".to_string())?;
        let cal = Calibration::from_json(text).map_err(|e| e.to_string())?;
        cal.check_machine(machine).map_err(|e| e.to_string())?;
        let built = cal.build().map_err(|e| e.to_string())?;
        // What a point would cost, measured on a reference point: a calibration the service
        // could not run in real time is refused here, before it is stored or swapped in.
        let cost_us = crate::cost::point_cost_us(&built, crate::cost::AT_PUT);
        drop(built);
        let limit = self.cfg.max_point_cost_us;
        if limit > 0.0 && cost_us > limit {
            warn!(
                machine,
                point_cost_us = cost_us.round(),
                limit_us = limit,
                "calibration refused: it costs more CPU per point than `max_point_cost_us`"
            );
            return Err(crate::cost::refusal(&cal, cost_us, limit));
        }
        if !self.cfg.serves(machine) {
            return Err(format!("this service does not serve machine `{machine}`"));
        }
        if !self.machines.contains_key(machine) && self.machines.len() >= self.cfg.max_machines {
            self.refuse(Refusal::OverCapacity, machine);
            return Err(format!(
                "this service serves its maximum of {} machines; `{machine}` is not one of them",
                self.cfg.max_machines
            ));
        }
        let stored = self
            .store
            .put_audited(cal, Some(&audit))
            .map_err(|e| e.to_string())?;
        let model = Arc::new(stored.build().map_err(|e| e.to_string())?);
        self.machine(machine).await.map_err(|e| e.to_string())?;
        let m = self.machines.get_mut(machine).expect("served");
        if m.quarantined.take().is_some() {
            info!(machine, "quarantine lifted: a valid calibration was put");
        }
        // Swapped on the machine's shard between two messages: every message routed before
        // is corrected with the old model, every one after with the new.
        self.shards[m.shard]
            .jobs
            .send(Job::Model(machine.to_string(), model))
            .map_err(|_| "the correcting workers have stopped".to_string())?;
        m.puts += 1;
        m.point_cost_us = Some(cost_us);
        info!(
            machine,
            version = stored.version,
            parent = stored.parent_version,
            "calibration applied"
        );
        Ok(json!({"machine": machine, "version": stored.version, "parent_version": stored.parent_version}).to_string())
    }
}

/// A served machine's status: `base` (what the control task knows) with its shard's snapshot
/// (`fresh`: taken for this query; else the latest published, or none yet).
fn status_body(
    mut base: serde_json::Value,
    snap: Option<&Snap>,
    not_corrected: u64,
    fresh: bool,
) -> serde_json::Value {
    let c = snap.and_then(|s| s.core.as_ref());
    let stats = c.map(|c| &c.stats);
    let (version, pending, wm) = match c {
        Some(c) => (Some(c.version), c.pending, c.watermarks),
        None => (None, [0; 4], [None; 4]),
    };
    let mut extra = snap.map(|s| s.extra.clone()).unwrap_or_default();
    extra.not_corrected = not_corrected;
    let more = json!({
        "calibration_version": version,
        // Samples that arrived while no calibration was in use (never put, or quarantined):
        // counted, not corrected; the log and an alarm on the machine's alarm key say so.
        "uncorrected_samples": extra.no_calibration,
        "streaming_uncalibrated": c.is_none() && extra.no_calibration > 0,
        "samples_in": stats.map(|s| s.samples()).unwrap_or(0),
        "points_out": stats.map(|s| s.points_out).unwrap_or(0),
        "points_flagged": stats.map(|s| s.points_invalid).unwrap_or(0),
        "dropped": stats.map(|s| s.dropped_by_name().into_iter().map(|(k, v)| (k.to_string(), v)).collect::<BTreeMap<_, _>>()).unwrap_or_default(),
        "alarms_raised": stats.map(|s| s.alarms_raised).unwrap_or(0),
        "clock_resets": stats.map(|s| s.clock_resets).unwrap_or(0),
        "seq_resets": stats.map(|s| s.seq_resets).unwrap_or(0),
        // Samples missing in the streams' seq (lost on the way: a router down, a link
        // dropped; or shed by this service, see `input`), per stream.
        "samples_missing": stats.map(|s| json!({"command": s.samples_missing[0], "scale": s.samples_missing[1], "probe": s.samples_missing[2], "temperature": s.samples_missing[3]})),
        "seq_gaps": stats.map(|s| json!({"command": s.seq_gaps[0], "scale": s.seq_gaps[1], "probe": s.seq_gaps[2], "temperature": s.seq_gaps[3]})),
        "effect_points": snap.map(|s| s.ids.iter().cloned().zip(stats.map(|s| s.effect_points.clone()).unwrap_or_default()).collect::<BTreeMap<_, _>>()).unwrap_or_default(),
        "inactive_effects": c.map(|c| c.inactive.clone()).unwrap_or_default(),
        "messages": extra,
        "pending": {"command": pending[0], "scale": pending[1], "probe": pending[2], "temperature": pending[3]},
        "watermarks_ns": wm,
        // In the controller's own clock (which need not be wall time): how far the newest
        // point lags the newest sample taken in (samples waiting for the other streams to
        // join them).
        "stream_lag_ms": match (wm.iter().flatten().max(), snap.and_then(|s| s.last_point_t_ns)) {
            (Some(newest), Some(point)) => Some((newest - point).max(0) as f64 * 1e-6),
            _ => None,
        },
        "state_bytes": c.map(|c| c.state_bytes).unwrap_or(0),
        "max_pending": c.map(|c| c.max_pending),
        // The shard's measure of the machine's correction: CPU time, the cost of a point now
        // (µs, a running mean), how long its newest message waited on the shard (ms).
        "cpu_s": snap.map(|s| (s.busy_s * 1e3).round() / 1e3),
        "cost_us_per_point": snap.map(|s| (s.cost_us_per_point * 100.0).round() / 100.0),
        "queue_wait_ms": snap.map(|s| (s.wait_ms * 10.0).round() / 10.0),
        // False: the shard did not answer in time; these figures are its latest published.
        "snapshot_fresh": fresh,
    });
    if let (Some(b), serde_json::Value::Object(m)) = (base.as_object_mut(), more) {
        b.extend(m);
    }
    base
}

/// The audit record of a request: now (the service's clock), who asked, and the action.
///
/// `by` is what the requester said in the query's attachment (at most 256 printable
/// characters): `user@host; zid=<its session's zenoh id>; cn=<its certificate's common name>`
/// (`scancorr` sends all three: the zenoh id of the session that asked and the subject of the
/// certificate it connected with, which the router's access control admitted for its role),
/// recorded as `alice@cmm-3 (claimed), zenoh id 5f1e…, certificate CN operator`. zenoh
/// 1.10.2's stable query API gives a queryable nothing of the querier's connection (neither
/// its zenoh id nor its certificate; only the router that admitted it knows them), so the
/// service records what the requester's session says and never invents a user: a claim
/// without a user (none, or `unknown`, what older clients said when `$USER` was not set) is
/// recorded as `unnamed`, with the zenoh id and certificate when given.
fn audit_of(q: &zenoh::query::Query, action: String) -> Audit {
    let claim = q
        .attachment()
        .and_then(|a| a.try_to_string().ok().map(|s| s.to_string()))
        .map(|s| {
            s.chars()
                .filter(|c| !c.is_control())
                .take(256)
                .collect::<String>()
        })
        .filter(|s| !s.trim().is_empty());
    Audit {
        at: rfc3339_now(),
        by: audit_by(claim.as_deref()),
        action,
    }
}

/// The audit record's `by` for a requester's claim (see [`audit_of`]).
fn audit_by(claim: Option<&str>) -> String {
    let Some(c) = claim else {
        return "unnamed (the request named no requester)".into();
    };
    let mut parts = c.split(';').map(str::trim);
    let who = parts.next().unwrap_or("");
    let (mut zid, mut cn) = (None, None);
    for p in parts {
        match p.split_once('=') {
            Some(("zid", v)) if !v.trim().is_empty() => zid = Some(v.trim()),
            Some(("cn", v)) if !v.trim().is_empty() => cn = Some(v.trim()),
            _ => {}
        }
    }
    let (user, host) = match who.split_once('@') {
        Some((u, h)) => (u.trim(), Some(h.trim())),
        None => (who.trim(), None),
    };
    let nameless = user.is_empty() || user.eq_ignore_ascii_case("unknown");
    let mut by = match (nameless, host) {
        (false, _) => format!("{who} (claimed)"),
        (true, Some(h)) if !h.is_empty() => {
            format!("unnamed@{h} (claimed; the requester named no user)")
        }
        (true, _) if zid.is_some() => "unnamed (claimed; the requester named no user)".into(),
        (true, _) => return "unnamed (the request named no requester)".into(),
    };
    if let Some(z) = zid {
        by += &format!(", zenoh id {z}");
    }
    if let Some(c) = cn {
        by += &format!(", certificate CN {c}");
    }
    by
}

/// The wall clock as RFC 3339 UTC (seconds).
fn rfc3339_now() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0) as i64;
    scancorr_core::calib::rfc3339_utc(secs)
}

#[cfg(test)]
mod audit_tests {
    use super::audit_by;

    #[test]
    fn a_claim_without_a_user_is_never_recorded_as_a_user() {
        assert_eq!(audit_by(Some("alice@cmm-3")), "alice@cmm-3 (claimed)");
        assert_eq!(
            audit_by(Some("unknown@vm")),
            "unnamed@vm (claimed; the requester named no user)"
        );
        assert_eq!(
            audit_by(Some("@vm")),
            "unnamed@vm (claimed; the requester named no user)"
        );
        assert_eq!(audit_by(None), "unnamed (the request named no requester)");
        assert_eq!(audit_by(Some("Unknown")), audit_by(None));
        for c in [None, Some("unknown@vm"), Some("unknown")] {
            assert!(!audit_by(c).contains("unknown"), "{c:?}");
        }
        // What `scancorr` sends: the session's zenoh id and its certificate's subject.
        assert_eq!(
            audit_by(Some("alice@cmm-3; zid=5f1e2a; cn=operator")),
            "alice@cmm-3 (claimed), zenoh id 5f1e2a, certificate CN operator"
        );
        assert_eq!(
            audit_by(Some("uid 0@vm; zid=5f1e2a")),
            "uid 0@vm (claimed), zenoh id 5f1e2a"
        );
        assert_eq!(
            audit_by(Some("unknown@vm; zid=5f1e2a; cn=lab")),
            "unnamed@vm (claimed; the requester named no user), zenoh id 5f1e2a, certificate CN lab"
        );
    }
}
