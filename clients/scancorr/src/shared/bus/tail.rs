//! `tail`: a machine's points and alarms as they arrive, and what it says when none can.

use super::*;

/// `tail`: prints points and alarms as they arrive, until the bound or Ctrl-C; an error when
/// nothing arrived.
pub fn tail(bus: &Bus, machine: &str, bound: Bound, json: bool) -> Result<()> {
    crate::shared::output::check_machine("--machine", machine)?;
    bus.check()?;
    bound.check()?;
    let conn = connect(bus)?;
    let key = format!("{}/{machine}/**", bus.prefix);
    conn.rt.block_on(async {
        let s = &conn.session;
        let sub = s.declare_subscriber(key.as_str()).await.map_err(z)?;
        // A machine that streams with no calibration has no point to show: said at once.
        let mut said_uncorrected = false;
        if let Some(n) = no_calibration(s, &bus.prefix, machine).await {
            eprintln!("warning: {}", uncorrected_words(machine, n));
            said_uncorrected = true;
        }
        let t0 = Instant::now();
        let mut last_seq: Option<u64> = None;
        let mut last = None::<Instant>;
        let (mut n, mut bad) = (0u64, 0u64);
        let ctrl_c = tokio::signal::ctrl_c();
        tokio::pin!(ctrl_c);
        loop {
            tokio::select! {
                r = sub.recv_async() => {
                    let Ok(sample) = r else { break };
                    let Some((m, stream)) = Stream::parse_key(&bus.prefix, sample.key_expr().as_str()) else { continue };
                    let bytes = sample.payload().to_bytes();
                    match stream {
                        Stream::Points => {
                            // A payload that is no point batch is shown, counted, and skipped.
                            let points = match scancorr_proto::v1::CorrectedPointBatch::decode(&*bytes).map_err(|e| e.to_string()).and_then(|b| b.into_points().map_err(|e| e.to_string())) {
                                Ok(p) => p,
                                Err(e) => {
                                    bad += 1;
                                    if json { outln!("{}", serde_json::json!({"machine": m, "bad_point_batch": e, "bad_so_far": bad}))?; } else { outln!("!! {m}: a point batch that does not read ({bad} so far): {e}")?; }
                                    continue;
                                }
                            };
                            n += 1;
                            last = Some(Instant::now());
                            for p in &points {
                                if let Some(l) = last_seq { if p.seq != l + 1 {
                                    let missed = p.seq.saturating_sub(l + 1);
                                    if json { outln!("{}", serde_json::json!({"machine": m, "missed_points": missed, "before_seq": p.seq}))?; } else { outln!("!! {m}: missed {missed} point(s)")?; }
                                } }
                                last_seq = Some(p.seq);
                                if json {
                                    let v = |x: Option<scancorr_proto::v1::Vec3>| x.map(|v| [v.x, v.y, v.z]).unwrap_or_default();
                                    outln!("{}", serde_json::json!({"machine": m, "seq": p.seq, "t_ns": p.t_ns, "segment_id": p.segment_id, "tip_id": p.tip_id, "calibration_version": p.calibration_version, "estimator_valid": p.estimator_valid, "surface_mm": v(p.surface), "tip_center_mm": v(p.tip_center), "normal": v(p.normal)}))?;
                                }
                            }
                            if let (Some(p), false) = (points.last(), json) {
                                let s = p.surface.unwrap_or_default();
                                outln!("{m} #{:<9} t={:.3}s  surface ({:9.4} {:9.4} {:9.4}) mm  v{} {}{}", p.seq, p.t_ns as f64 * 1e-9, s.x, s.y, s.z, p.calibration_version, if p.estimator_valid { "" } else { "FLAGGED " }, if points.len() > 1 { format!("(+{} in batch)", points.len() - 1) } else { String::new() })?;
                            }
                        }
                        Stream::Alarms => {
                            if let Ok(a) = scancorr_proto::v1::EstimatorAlarm::decode(&*bytes) {
                                // The no-calibration alarm (no axis, no version; every estimator
                                // alarm names both): the machine is not corrected, said as such.
                                if a.axis == scancorr_proto::v1::Axis::Unspecified as i32 && a.calibration_version == 0 {
                                    if json {
                                        outln!("{}", serde_json::json!({"machine": m, "alarm": if a.raised { "raised" } else { "cleared" }, "kind": "no_calibration", "t_ns": a.t_ns}))?;
                                    } else if a.raised {
                                        outln!("{m} NOT CORRECTED: streaming with no calibration in use (no-calibration alarm raised at t={:.3}s); put one: `scancorr calib put --machine {m} --file CALIBRATION.json`", a.t_ns as f64 * 1e-9)?;
                                    } else {
                                        outln!("{m} calibration in use: the no-calibration alarm is cleared (t={:.3}s)", a.t_ns as f64 * 1e-9)?;
                                    }
                                    said_uncorrected |= a.raised;
                                    if !a.raised {
                                        n += 1;
                                        last = Some(Instant::now());
                                    }
                                    continue;
                                }
                                n += 1;
                                last = Some(Instant::now());
                                if json {
                                    outln!("{}", serde_json::json!({"machine": m, "alarm": if a.raised { "raised" } else { "cleared" }, "axis": format!("{:?}", a.axis()), "t_ns": a.t_ns, "estimated_accel_mm_s2": a.estimated_accel, "measured_accel_mm_s2": a.measured_accel, "threshold_mm_s2": a.threshold}))?;
                                } else {
                                    outln!("{m} ALARM {} axis {:?} t={:.3}s estimated {:.1} measured {:.1} mm/s² (threshold {:.0})", if a.raised { "RAISED" } else { "cleared" }, a.axis(), a.t_ns as f64 * 1e-9, a.estimated_accel, a.measured_accel, a.threshold)?;
                                }
                            }
                        }
                        _ => {}
                    }
                }
                _ = tokio::time::sleep(Duration::from_millis(200)) => {}
                _ = &mut ctrl_c => break,
            }
            if bound.done(t0, last, n) {
                break;
            }
        }
        if n == 0 {
            // No point, because the service has no calibration for the machine: not the
            // streams' fault.
            if let Some(u) = no_calibration(s, &bus.prefix, machine).await {
                bail!("received no point on `{key}` {}: {}", bound.waited(t0), uncorrected_words(machine, u));
            }
            if said_uncorrected {
                bail!("received no point on `{key}` {}: machine `{machine}` streamed with no calibration in use (its no-calibration alarm was raised); put one: `scancorr calib put --machine {machine} --file CALIBRATION.json`", bound.waited(t0));
            }
            bail!(
                "received nothing on `{key}` from {} {} (are machine `{machine}`'s raw streams reaching scancorrd?)",
                bus.endpoints(),
                bound.waited(t0)
            );
        }
        Ok(())
    })
}

/// The samples of `machine` that its scancorrd received with no calibration in use, when it
/// has none in use and received some (its status: `calibration_version` null,
/// `uncorrected_samples`); None otherwise, or when no scancorrd answers within 3 s.
async fn no_calibration(s: &zenoh::Session, prefix: &str, machine: &str) -> Option<u64> {
    let mut found = None;
    let status = format!("{prefix}/{machine}/status");
    for v in json_answers(s, status, Duration::from_secs(3)).await? {
        let n = v["uncorrected_samples"].as_u64().unwrap_or(0);
        if v["served"] == true && v["calibration_version"].is_null() && n > 0 {
            found = Some(found.unwrap_or(0).max(n));
        }
    }
    found
}

/// What `tail` says of a machine that streams with no calibration in use.
fn uncorrected_words(machine: &str, samples: u64) -> String {
    format!(
        "machine `{machine}` is not corrected: scancorrd has no calibration in use for it, so it publishes no point \
         ({samples} sample(s) streamed uncorrected: `uncorrected_samples` on `scancorr status --machine {machine}`); \
         its streams are arriving. Put one: `scancorr calib put --machine {machine} --file CALIBRATION.json`"
    )
}
