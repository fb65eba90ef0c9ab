//! `record`: the bus into a bag, with the samples missing between recorded ones counted.

use super::*;

/// Samples missing between recorded ones: per (machine, stream), a `seq` more than one past
/// the last one seen. (A `seq` going back is a controller restart or a looped replay, not a
/// loss; samples before the first one recorded are not counted.)
#[derive(Default)]
struct Gaps {
    last: std::collections::BTreeMap<(String, Stream), u64>,
    missing: std::collections::BTreeMap<(String, Stream), u64>,
}

impl Gaps {
    fn see(&mut self, machine: &str, stream: Stream, seq: u64) {
        let key = (machine.to_string(), stream);
        if let Some(l) = self.last.get(&key) {
            if seq > l + 1 {
                *self.missing.entry(key.clone()).or_default() += seq - l - 1;
            }
        }
        self.last.insert(key, seq);
    }

    /// Notes the seqs in one message's payload.
    fn message(&mut self, stream: Stream, bytes: &[u8]) {
        if let Some(sid) = scancorr_core::wire::stream_id(stream) {
            if let Ok(d) = scancorr_core::wire::decode(sid, bytes) {
                for (m, s) in &d.samples {
                    self.see(m, stream, s.seq());
                }
            }
        } else if stream == Stream::Points {
            let b = scancorr_proto::v1::CorrectedPointBatch::decode(bytes);
            if let Ok(points) = b.map(|b| b.into_points()) {
                for p in points.iter().flatten() {
                    self.see(&p.machine_id, stream, p.seq);
                }
            }
        } else {
            // The v1.2 measurement streams (distance probes, micro-stage).
            match scancorr_bag::RawBatch::decode(stream, bytes) {
                Ok(scancorr_bag::RawBatch::Distance(b)) => b
                    .samples
                    .iter()
                    .for_each(|s| self.see(&s.machine_id, stream, s.seq)),
                Ok(scancorr_bag::RawBatch::Stage(b)) => b
                    .samples
                    .iter()
                    .for_each(|s| self.see(&s.machine_id, stream, s.seq)),
                _ => {}
            }
        }
    }

    fn total(&self) -> u64 {
        self.missing.values().sum()
    }

    fn describe(&self, prefix: &str) -> String {
        self.missing
            .iter()
            .map(|((m, st), n)| format!("{n} in {}", st.key(prefix, m)))
            .collect::<Vec<_>>()
            .join(", ")
    }
}

/// `record`: bus → bag until the bound, or Ctrl-C. An error, and no file, when nothing of the
/// scancorr streams arrived; an error (with the bag kept) when samples are missing between
/// recorded ones — the bus dropped them for this recorder. With `foxglove`, the corrected
/// points and alarms recorded are also written as Foxglove channels (`shared::foxglove`, as
/// `correct` writes them).
pub fn record(
    bus: &Bus,
    keys: &str,
    out: &Path,
    bound: Bound,
    mut foxglove: Option<crate::shared::foxglove::BusSinks>,
) -> Result<u64> {
    bus.check()?;
    bound.check()?;
    zenoh::key_expr::KeyExpr::try_from(keys).map_err(|e| {
        anyhow::anyhow!(
            "--keys {}: not a key expression: {}",
            scancorr_proto::names::shown(keys),
            one_line(&e.to_string())
        )
    })?;
    let file = AtomicOutput::new("--out", out)?;
    let conn = connect(bus)?;
    let (n, gaps) = conn.rt.block_on(async {
        let s = &conn.session;
        // zenoh's own handler holds 256 samples and then blocks its receiving thread: a
        // recorder that writes slower than a faster-than-real-time run arrives (points and
        // their Foxglove channels as well as raw streams, with `cmm/m1/**`) then holds its
        // link, and scancorrd drops the raw messages it forwards to it (droppable, their own
        // lane). The callback queues every sample without waiting (up to RECORD_QUEUE_BYTES),
        // and the loop below writes them.
        // (Each with the time it arrived: the bag's log time.)
        let (tx, mut sub) = tokio::sync::mpsc::unbounded_channel::<(zenoh::sample::Sample, u64)>();
        let queued = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let q = queued.clone();
        let _sub = s
            .declare_subscriber(keys)
            .callback(move |sample| {
                let len = sample.payload().len();
                while q.load(std::sync::atomic::Ordering::Relaxed) > RECORD_QUEUE_BYTES {
                    std::thread::sleep(Duration::from_millis(1));
                }
                q.fetch_add(len, std::sync::atomic::Ordering::Relaxed);
                let now = std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map(|d| d.as_nanos() as u64)
                    .unwrap_or(0);
                let _ = tx.send((sample, now));
            })
            .await
            .map_err(z)?;
        let mut w = BagWriter::from_file(file.file()?, file.path(), BagHeader { compression: scancorr_bag::Compression::Lz4, ..BagHeader::default() })
            .with_context(|| format!("creating {}", out.display()))?;
        if let Some(f) = &foxglove {
            f.write_program(&mut w)?;
        }
        let t0 = Instant::now();
        let mut last = None::<Instant>;
        let (mut n, mut other) = (0u64, 0u64);
        let mut gaps = Gaps::default();
        let mut last_flush = Instant::now();
        eprintln!("recording `{keys}` from {} → {}", bus.endpoints(), out.display());
        let mut progress = crate::shared::output::Progress::new();
        let ctrl_c = tokio::signal::ctrl_c();
        tokio::pin!(ctrl_c);
        // Once the bound is reached (or Ctrl-C), what was received before is still written.
        let mut draining = false;
        loop {
            let got = if draining {
                match sub.try_recv() {
                    Ok(x) if !bound.count.is_some_and(|c| n >= c) => Some(x),
                    _ => break,
                }
            } else {
                tokio::select! {
                    r = sub.recv() => match r { Some(x) => Some(x), None => break },
                    _ = tokio::time::sleep(Duration::from_millis(200)) => None,
                    _ = &mut ctrl_c => { draining = true; None }
                }
            };
            if let Some((sample, now)) = got {
                queued.fetch_sub(sample.payload().len(), std::sync::atomic::Ordering::Relaxed);
                let key = sample.key_expr().as_str();
                let Some((machine, stream)) = Stream::parse_key(&bus.prefix, key) else { other += 1; continue };
                let bytes = sample.payload().to_bytes();
                let publish = scancorr_bag::peek(stream, &bytes).and_then(|p| p.first_t_ns).map(|t| t.max(0) as u64).unwrap_or(now);
                w.write(stream, machine, &bus.prefix, now, publish, &bytes)?;
                if let Some(f) = &mut foxglove {
                    f.write(&mut w, now, machine, stream, &bytes)?;
                }
                gaps.message(stream, &bytes);
                n += 1;
                last = Some(Instant::now());
                progress.tick(|| format!("recording: {n} message(s) in {:.1} s", t0.elapsed().as_secs_f64()));
                if last_flush.elapsed() > Duration::from_secs(1) {
                    w.flush()?;
                    last_flush = Instant::now();
                }
            }
            if !draining && bound.done(t0, last, n) {
                draining = true;
            }
        }
        progress.finish();
        if n == 0 {
            if other > 0 {
                bail!("received nothing on `{keys}` that is a scancorr stream under prefix `{}` ({other} other message(s)) {}; nothing written", bus.prefix, bound.waited(t0));
            }
            bail!("received nothing on `{keys}` from {} {} (is anything publishing there?); nothing written", bus.endpoints(), bound.waited(t0));
        }
        w.finish().with_context(|| format!("finishing {}", out.display()))?;
        Ok::<_, anyhow::Error>((n, gaps))
    })?;
    file.commit()?;
    if gaps.total() > 0 {
        bail!(
            "recorded {n} message(s) → {}, but {} sample(s) are missing between them (seq gaps: {}): the bus dropped them on the way to this recorder (a publisher faster than real time?)",
            out.display(),
            gaps.total(),
            gaps.describe(&bus.prefix)
        );
    }
    Ok(n)
}

/// What `record` holds in memory, received and not yet written, before its subscriber waits
/// (and the bus may drop what it forwards to it, which the seq gaps then report).
const RECORD_QUEUE_BYTES: usize = 512 << 20;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gaps_count_missing_samples_not_restarts() {
        let mut g = Gaps::default();
        for seq in [5, 6, 7, 10, 11, 0, 1, 3] {
            g.see("m1", Stream::Scale, seq);
        }
        g.see("m2", Stream::Scale, 100);
        g.see("m1", Stream::Probe, 4);
        assert_eq!(g.total(), 3);
        assert_eq!(g.describe("cmm"), "3 in cmm/m1/raw/scale");
    }
}
