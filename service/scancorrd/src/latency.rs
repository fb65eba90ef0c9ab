//! The latency the service adds, measured inside it: from a raw message's arrival (zenoh's
//! callback handing it to the service) to the publication of the points it completed (the
//! `put` returned). A log-scale histogram — 8 buckets per octave from 1 µs, so a percentile is
//! known to within 9 % — of fixed size (under 1 KiB per machine), cheap enough to record every
//! batch. A percentile is reported as the upper edge of its bucket, or the largest latency
//! recorded when that is lower (a bound, as HdrHistogram's highest equivalent value): between
//! 1 µs and 4.5 min the true value lies between it and it divided by
//! 1 + [`Latency::bucket_width`]. The figures carry that width, so that a reader comparing a
//! percentile with a target close to it knows when the histogram cannot tell.

use std::time::Duration;

/// Buckets per octave.
const PER_OCTAVE: f64 = 8.0;
/// 1 µs … 2^28 µs (4.5 min).
const BUCKETS: usize = 28 * 8;

/// A latency histogram.
#[derive(Debug, Clone)]
pub struct Latency {
    counts: Box<[u32; BUCKETS]>,
    n: u64,
    max_us: f64,
}

impl Default for Latency {
    fn default() -> Self {
        Latency {
            counts: Box::new([0; BUCKETS]),
            n: 0,
            max_us: 0.0,
        }
    }
}

impl Latency {
    /// Records one latency.
    pub fn record(&mut self, d: Duration) {
        let us = d.as_secs_f64() * 1e6;
        let k = if us <= 1.0 {
            0
        } else {
            ((us.log2() * PER_OCTAVE) as usize).min(BUCKETS - 1)
        };
        self.counts[k] = self.counts[k].saturating_add(1);
        self.n += 1;
        self.max_us = self.max_us.max(us);
    }

    /// How many were recorded.
    pub fn count(&self) -> u64 {
        self.n
    }

    /// The `q`-quantile (0…1), µs: the upper edge of the bucket that holds it (never above the
    /// largest recorded); `None` when nothing was recorded.
    pub fn quantile_us(&self, q: f64) -> Option<f64> {
        if self.n == 0 {
            return None;
        }
        let want = ((q.clamp(0.0, 1.0) * self.n as f64).ceil() as u64).max(1);
        let mut seen = 0u64;
        for (k, c) in self.counts.iter().enumerate() {
            seen += *c as u64;
            if seen >= want {
                return Some(2f64.powf((k + 1) as f64 / PER_OCTAVE).min(self.max_us));
            }
        }
        Some(self.max_us)
    }

    /// The relative width of a bucket: the upper edge of one over its lower edge, less 1
    /// (2^(1/8) − 1, about 0.09).
    pub fn bucket_width() -> f64 {
        2f64.powf(1.0 / PER_OCTAVE) - 1.0
    }

    /// Count, p50, p99, p99.9 and max, µs, and the buckets' width, % (rounded up to 0.1 %: a
    /// percentile `p` says the true value lies in `[p / (1 + width), p]`); JSON, null
    /// percentiles when empty.
    pub fn figures(&self) -> serde_json::Value {
        let r = |x: Option<f64>| x.map(|v| (v * 10.0).round() / 10.0);
        serde_json::json!({
            "bucket_width_pct": (Self::bucket_width() * 1000.0).ceil() / 10.0,
            "count": self.n,
            "p50": r(self.quantile_us(0.5)),
            "p99": r(self.quantile_us(0.99)),
            "p999": r(self.quantile_us(0.999)),
            "max": (self.n > 0).then_some((self.max_us * 10.0).round() / 10.0),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_within_the_bucket_resolution() {
        let mut l = Latency::default();
        assert_eq!(l.quantile_us(0.5), None);
        assert!(l.figures()["p99"].is_null());
        // 1 … 1000 µs, uniformly.
        for us in 1..=1000u64 {
            l.record(Duration::from_micros(us));
        }
        let p50 = l.quantile_us(0.5).unwrap();
        let p99 = l.quantile_us(0.99).unwrap();
        assert!((500.0..=500.0 * 1.1).contains(&p50), "{p50}");
        assert!((990.0..=1000.0).contains(&p99), "{p99}");
        assert_eq!(l.quantile_us(1.0), Some(1000.0));
        assert_eq!(l.count(), 1000);
        // Each percentile bounds the true one from above, within the buckets' stated width.
        let width = l.figures()["bucket_width_pct"].as_f64().unwrap() / 100.0;
        assert!((0.0905..=0.091).contains(&width), "{width}");
        for q in [0.1, 0.25, 0.5, 0.9, 0.99, 0.999] {
            let truth = (q * 1000.0_f64).ceil();
            let p = l.quantile_us(q).unwrap();
            assert!(
                truth <= p && p <= truth * (1.0 + width),
                "q {q}: {p} for {truth} (width {width})"
            );
        }
        // Sub-microsecond and absurd values land in the end buckets.
        l.record(Duration::from_nanos(10));
        l.record(Duration::from_secs(3600));
        assert_eq!(l.count(), 1002);
        assert_eq!(l.figures()["max"], 3.6e9);
    }
}
