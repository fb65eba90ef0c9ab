//! The Prometheus text the metrics endpoint serves.

use super::*;

impl State {
    /// The Prometheus text: per machine, samples in (per stream), points out and flagged,
    /// drops by reason, samples missing in seq, alarms, the calibration version and puts,
    /// queue depths (samples pending the join, bytes waiting to be published) and the
    /// processing lag; refusals before a machine by reason.
    pub(super) fn metrics(&self) -> String {
        let snaps = self.snaps();
        use crate::metrics::Render;
        let mut r = Render::default();
        let streams = ["command", "scale", "probe", "temperature"];
        type Samples = Option<Vec<(Vec<(&'static str, String)>, f64)>>;
        let metric = |r: &mut Render,
                      name: &str,
                      kind: &str,
                      help: &str,
                      f: &dyn Fn(&Machine, &Snap) -> Samples| {
            r.metric(name, kind, help);
            for (machine, m) in &self.machines {
                let Some(s) = snaps.get(machine) else {
                    continue;
                };
                for (labels, v) in f(m, s).unwrap_or_default() {
                    let mut l: Vec<(&str, &str)> = vec![("machine", machine.as_str())];
                    l.extend(labels.iter().map(|(k, v)| (*k, v.as_str())));
                    r.sample(name, &l, v);
                }
            }
        };
        metric(
            &mut r,
            "scancorr_samples_in_total",
            "counter",
            "Raw samples taken in, per stream.",
            &|_m, s| {
                s.core.as_ref().map(|c| {
                    let s = &c.stats;
                    (0..4)
                        .map(|k| {
                            (
                                vec![("stream", streams[k].to_string())],
                                s.samples_in[k] as f64,
                            )
                        })
                        .collect()
                })
            },
        );
        metric(
            &mut r,
            "scancorr_points_out_total",
            "counter",
            "Corrected points produced.",
            &|_m, s| {
                s.core
                    .as_ref()
                    .map(|c| vec![(vec![], c.stats.points_out as f64)])
            },
        );
        metric(
            &mut r,
            "scancorr_points_flagged_total",
            "counter",
            "Points produced while an estimator alarm was raised.",
            &|_m, s| {
                s.core
                    .as_ref()
                    .map(|c| vec![(vec![], c.stats.points_invalid as f64)])
            },
        );
        metric(
            &mut r,
            "scancorr_samples_dropped_total",
            "counter",
            "Samples dropped by the core, by reason.",
            &|_m, s| {
                s.core.as_ref().map(|c| {
                    c.stats
                        .dropped_by_name()
                        .into_iter()
                        .map(|(k, v)| (vec![("reason", k.to_string())], v as f64))
                        .collect()
                })
            },
        );
        metric(
            &mut r,
            "scancorr_samples_missing_total",
            "counter",
            "Samples missing in a stream's seq (lost before the service), per stream.",
            &|_m, s| {
                s.core.as_ref().map(|c| {
                    let s = &c.stats;
                    (0..4)
                        .map(|k| {
                            (
                                vec![("stream", streams[k].to_string())],
                                s.samples_missing[k] as f64,
                            )
                        })
                        .collect()
                })
            },
        );
        metric(
            &mut r,
            "scancorr_messages_refused_total",
            "counter",
            "Raw messages refused for a machine, by reason.",
            &|_m, s| {
                let e = &s.extra;
                Some(vec![
                    (vec![("reason", "malformed".into())], e.malformed as f64),
                    (vec![("reason", "empty".into())], e.empty as f64),
                    (
                        vec![("reason", "wrong_stream".into())],
                        e.wrong_stream as f64,
                    ),
                    (vec![("reason", "untagged".into())], e.untagged as f64),
                    (
                        vec![("reason", "wrong_machine".into())],
                        e.wrong_machine as f64,
                    ),
                    (
                        vec![("reason", "no_calibration".into())],
                        e.no_calibration as f64,
                    ),
                ])
            },
        );
        metric(
            &mut r,
            "scancorr_uncorrected_samples_total",
            "counter",
            "Samples that arrived while the machine had no calibration in use (counted, not corrected).",
            &|_m, s| Some(vec![(vec![], s.extra.no_calibration as f64)]),
        );
        metric(
            &mut r,
            "scancorr_points_dropped_backpressure_total",
            "counter",
            "Points not published because the machine's subscribers did not keep up.",
            &|m, _s| {
                m.outbox.figures()["points_dropped_backpressure"]
                    .as_f64()
                    .map(|v| vec![(vec![], v)])
            },
        );
        metric(
            &mut r,
            "scancorr_messages_shed_total",
            "counter",
            "Raw messages shed before correction, by reason: late (the machine's shard fell behind real time with them) or queue_full (its queue on the shard was full).",
            &|m, _s| {
                use std::sync::atomic::Ordering::Relaxed;
                Some(vec![
                    (
                        vec![("reason", "late".into())],
                        m.input.shed_late.load(Relaxed) as f64,
                    ),
                    (
                        vec![("reason", "queue_full".into())],
                        m.input.shed_queue_full.load(Relaxed) as f64,
                    ),
                ])
            },
        );
        metric(
            &mut r,
            "scancorr_alarms_raised_total",
            "counter",
            "Estimator-validity alarms raised.",
            &|_m, s| {
                s.core
                    .as_ref()
                    .map(|c| vec![(vec![], c.stats.alarms_raised as f64)])
            },
        );
        metric(
            &mut r,
            "scancorr_calibration_version",
            "gauge",
            "The calibration version in use.",
            &|_m, s| s.core.as_ref().map(|c| vec![(vec![], c.version as f64)]),
        );
        metric(
            &mut r,
            "scancorr_calibration_puts_total",
            "counter",
            "Calibrations put since the service started.",
            &|m, _s| Some(vec![(vec![], m.puts as f64)]),
        );
        metric(
            &mut r,
            "scancorr_pending_samples",
            "gauge",
            "Samples waiting in the join for the other streams, per stream.",
            &|_m, s| {
                s.core.as_ref().map(|c| {
                    let p = c.pending;
                    (0..4)
                        .map(|k| (vec![("stream", streams[k].to_string())], p[k] as f64))
                        .collect()
                })
            },
        );
        metric(
            &mut r,
            "scancorr_publish_queue_bytes",
            "gauge",
            "Corrected output waiting to be published.",
            &|m, _s| {
                m.outbox.figures()["queued_bytes"]
                    .as_f64()
                    .map(|v| vec![(vec![], v)])
            },
        );
        metric(
            &mut r,
            "scancorr_processing_lag_seconds",
            "gauge",
            "How far the newest point lags the newest sample taken in (controller clock).",
            &|_m, s| {
                let wm = s.core.as_ref()?.watermarks;
                let newest = wm.iter().flatten().max()?;
                let point = s.last_point_t_ns?;
                Some(vec![(vec![], (newest - point).max(0) as f64 * 1e-9)])
            },
        );
        metric(
            &mut r,
            "scancorr_quarantined",
            "gauge",
            "1 when the machine's stored calibration cannot be used.",
            &|m, _s| {
                Some(vec![(
                    vec![],
                    if m.quarantined.is_some() { 1.0 } else { 0.0 },
                )])
            },
        );
        r.metric(
            "scancorr_refused_total",
            "counter",
            "Samples and requests refused before a machine, by reason.",
        );
        if let Ok(serde_json::Value::Object(o)) = serde_json::to_value(self.refused_now()) {
            for (k, v) in o {
                r.sample(
                    "scancorr_refused_total",
                    &[("reason", k.as_str())],
                    v.as_f64().unwrap_or(0.0),
                );
            }
        }
        if self.cfg.failover.enabled {
            // Fail-over: per machine, whether this instance is active for it, since when, its
            // take-overs and the split brains it saw.
            metric(
                &mut r,
                "scancorr_failover_active",
                "gauge",
                "1 while this instance is active for the machine, 0 while it stands by.",
                &|m, _| {
                    m.fo.as_ref()
                        .map(|f| vec![(vec![], (f.role == failover::Role::Active) as u8 as f64)])
                },
            );
            metric(
                &mut r,
                "scancorr_failover_role_since_seconds",
                "gauge",
                "When this instance became active or standby for the machine (Unix time, s).",
                &|m, _| {
                    m.fo.as_ref()
                        .map(|f| vec![(vec![], f.since_ms as f64 / 1e3)])
                },
            );
            metric(
                &mut r,
                "scancorr_failover_takeovers_total",
                "counter",
                "Times this instance took the machine over from another.",
                &|m, _| m.fo.as_ref().map(|f| vec![(vec![], f.takeovers as f64)]),
            );
            metric(
                &mut r,
                "scancorr_failover_split_brains_total",
                "counter",
                "Times another instance was seen active for the machine while this one was.",
                &|m, _| m.fo.as_ref().map(|f| vec![(vec![], f.split_brains as f64)]),
            );
        }
        r.metric("scancorr_machines", "gauge", "Machines served.");
        r.sample("scancorr_machines", &[], self.machines.len() as f64);
        if let Some(u) = &self.uplink {
            r.metric(
                "scancorr_routers_connected",
                "gauge",
                "Routers this client is connected to (0: cut off from the bus).",
            );
            r.sample("scancorr_routers_connected", &[], u.routers() as f64);
            r.metric(
                "scancorr_router_losses_total",
                "counter",
                "Times the last router was lost.",
            );
            r.sample("scancorr_router_losses_total", &[], u.losses() as f64);
            r.metric(
                "scancorr_router_down_seconds_total",
                "counter",
                "Seconds spent without a router.",
            );
            r.sample(
                "scancorr_router_down_seconds_total",
                &[],
                u.down_s(Instant::now()),
            );
        }
        r.finish()
    }
}
