//! Compare: the model's residual against the artifacts, binned by what differs (feature,
//! direction, speed, position …), with each circle's harmonics, the tracking residual per
//! segment and one trace per circle, direction and speed.

use super::dataset::Dataset;
use super::program::FeatureKind;
use super::types::{nuisance_ss, prepare, rms_um};
use super::LabError;
use serde::Serialize;

/// A bin of a residual breakdown.
#[derive(Debug, Clone, Serialize)]
pub struct Bin {
    /// Feature binned by.
    pub feature: String,
    /// Bin label.
    pub bin: String,
    /// Points.
    pub n: usize,
    /// Residual RMS, µm.
    pub rms_um: f64,
    /// Mean residual, µm.
    pub mean_um: f64,
    /// Stands out from the rest.
    pub failing: bool,
    /// A worse failing bin of another feature holding (≥ 80 % of the smaller's) points: this
    /// one is those scans seen another way (`feature bin`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub same_points_as: Option<String>,
}

/// |a ∩ b| / min(|a|, |b|) of two sorted index lists (the overlap coefficient).
fn overlap(a: &[u32], b: &[u32]) -> f64 {
    let (mut i, mut j, mut both) = (0, 0, 0usize);
    while i < a.len() && j < b.len() {
        match a[i].cmp(&b[j]) {
            std::cmp::Ordering::Less => i += 1,
            std::cmp::Ordering::Greater => j += 1,
            std::cmp::Ordering::Equal => {
                both += 1;
                i += 1;
                j += 1;
            }
        }
    }
    let small = a.len().min(b.len());
    if small == 0 {
        0.0
    } else {
        both as f64 / small as f64
    }
}

/// Harmonics of a circle feature's residual.
#[derive(Debug, Clone, Serialize)]
pub struct Harmonics {
    /// Feature index.
    pub feature: usize,
    /// Artifact name.
    pub artifact: String,
    /// Amplitudes of 1θ…5θ, µm.
    pub amplitude_um: [f64; 5],
}

/// A comparison of the model with the artifacts.
#[derive(Debug, Clone, Serialize)]
pub struct Comparison {
    /// Residual RMS (all points, shared placements), µm.
    pub rms_um: f64,
    /// Peak-to-valley, µm.
    pub pv_um: f64,
    /// Noise floor, µm.
    pub noise_floor_um: f64,
    /// Bins that stand out, worst first.
    pub failures: Vec<Bin>,
    /// Every bin.
    pub bins: Vec<Bin>,
    /// Harmonics per circle feature.
    pub harmonics: Vec<Harmonics>,
    /// Tracking residual of the nominal model by segment: (bag, segment, µm), worst first.
    pub tracking: Vec<(usize, u32, f64)>,
    /// Points.
    pub points: usize,
    /// One trace per circle feature, direction and speed (see [`super::traces`]).
    pub traces: Vec<super::traces::Trace>,
    /// Residual per point, µm (for plots).
    #[serde(skip)]
    pub residual_um: Vec<f64>,
}

impl Comparison {
    /// The failing bins that hold (nearly) the points of failing bin `b`, seen through another
    /// feature (`feature bin` labels).
    pub fn same_points(&self, b: &Bin) -> Vec<String> {
        let label = format!("{} {}", b.feature, b.bin);
        self.failures
            .iter()
            .filter(|o| o.same_points_as.as_deref() == Some(label.as_str()))
            .map(|o| format!("{} {}", o.feature, o.bin))
            .collect()
    }
}

/// Compares the dataset's corrected points with their artifacts.
pub fn compare(ds: &Dataset) -> Result<Comparison, LabError> {
    let prep = prepare(ds)?;
    let art = &prep.art;
    let all: Vec<bool> = ds
        .points
        .iter()
        .map(|p| art.features[p.feature].is_some())
        .collect();
    let (ss, n) = nuisance_ss(ds, art, &art.residual, &all);
    let res_um: Vec<f64> = art.residual.iter().map(|e| e * 1e3).collect();
    let (mn, mx) = res_um
        .iter()
        .zip(&all)
        .filter(|(_, a)| **a)
        .fold((f64::MAX, f64::MIN), |(a, b), (r, _)| {
            (a.min(*r), b.max(*r))
        });
    let rms = rms_um(ss, n);
    let noise = ds.noise_floor_um;
    let mut bins = vec![];
    type Key = Box<dyn Fn(&super::dataset::LabPoint) -> Option<String>>;
    let q = |v: f64, edges: &[f64], unit: &str| -> String {
        let i = edges.partition_point(|e| *e <= v);
        match i {
            0 => format!("< {}{unit}", fmt(edges[0])),
            i if i == edges.len() => format!("≥ {}{unit}", fmt(edges[edges.len() - 1])),
            i => format!("{}–{}{unit}", fmt(edges[i - 1]), fmt(edges[i])),
        }
    };
    /// Three significant digits (no bin edge prints as 0.000 or as its neighbour).
    fn fmt(x: f64) -> String {
        let a = x.abs();
        if a == 0.0 || !a.is_finite() {
            "0".to_string()
        } else if a >= 100.0 {
            format!("{x:.0}")
        } else {
            let d = (2 - a.log10().floor() as i32).clamp(0, 9) as usize;
            format!("{x:.d$}")
        }
    }
    // Bins in value order: "< a", "a–b" by a, "≥ b"; categories alphabetically.
    fn order(label: &str) -> (f64, String) {
        let num = |t: &str| {
            t.split_whitespace()
                .next()
                .and_then(|x| x.parse::<f64>().ok())
        };
        if let Some(r) = label.strip_prefix("< ") {
            (num(r).map(|_| f64::MIN).unwrap_or(0.0), label.to_string())
        } else if let Some(r) = label.strip_prefix("≥ ") {
            (num(r).map(|_| f64::MAX).unwrap_or(0.0), label.to_string())
        } else if let Some(a) = label
            .split_once('–')
            .and_then(|(a, _)| a.parse::<f64>().ok())
        {
            (a, label.to_string())
        } else {
            (0.0, label.to_string())
        }
    }
    let quantiles = |vals: Vec<f64>| -> Vec<f64> {
        let mut v: Vec<f64> = vals.into_iter().filter(|x| x.is_finite()).collect();
        v.sort_by(|a, b| a.total_cmp(b));
        if v.is_empty() {
            return vec![0.0];
        }
        let mut e: Vec<f64> = (1..5)
            .map(|k| v[(v.len() * k / 5).min(v.len() - 1)])
            .collect();
        // Edges that print alike would make a bin that reads `a–a`.
        e.dedup_by(|a, b| fmt(*a) == fmt(*b));
        e
    };
    let edges_speed = quantiles(ds.points.iter().map(|p| p.ctx.est_vel.norm()).collect());
    let edges_acc = quantiles(ds.points.iter().map(|p| p.ctx.est_acc.norm()).collect());
    let edges_f = quantiles(
        ds.points
            .iter()
            .filter(|p| p.ctx.f_hz > 0.0)
            .map(|p| p.ctx.f_hz)
            .collect(),
    );
    let edges_t = quantiles(ds.points.iter().map(|p| p.ctx.t_ns as f64 * 1e-9).collect());
    let edges_temp = quantiles(
        ds.points
            .iter()
            .filter(|p| p.ctx.temps_valid & 1 != 0)
            .map(|p| p.ctx.temps[0])
            .collect(),
    );
    let edges_defl = quantiles(ds.points.iter().map(|p| p.ctx.deflection.norm()).collect());
    let sensor0 = ds.sensors.names().first().cloned().unwrap_or_default();
    let centers: Vec<[f64; 3]> = ds.features.iter().map(|(_, f)| f.nominal_center).collect();
    let names: Vec<String> = ds
        .features
        .iter()
        .map(|(_, f)| f.artifact.clone())
        .collect();
    let keys: Vec<(String, Key)> = vec![
        (
            "speed".into(),
            Box::new(move |p| Some(q(p.ctx.est_vel.norm(), &edges_speed, " mm/s"))),
        ),
        (
            "acceleration".into(),
            Box::new(move |p| Some(q(p.ctx.est_acc.norm(), &edges_acc, " mm/s²"))),
        ),
        (
            "rotation frequency".into(),
            Box::new(move |p| (p.ctx.f_hz > 0.0).then(|| q(p.ctx.f_hz, &edges_f, " Hz"))),
        ),
        (
            "direction".into(),
            Box::new(|p| {
                Some(match p.direction {
                    1 => "CCW".into(),
                    -1 => "CW".into(),
                    _ => "line".into(),
                })
            }),
        ),
        (
            "phase".into(),
            Box::new(|p| Some(format!("{:?}", p.phase).to_lowercase())),
        ),
        (
            "position".into(),
            Box::new(move |p| {
                let c = centers[p.feature];
                Some(format!(
                    "{} {} at ({:.0}, {:.0}, {:.0})",
                    names[p.feature],
                    p.feature + 1,
                    c[0],
                    c[1],
                    c[2]
                ))
            }),
        ),
        (
            format!("temperature ({sensor0})"),
            Box::new(move |p| {
                (p.ctx.temps_valid & 1 != 0).then(|| q(p.ctx.temps[0], &edges_temp, " °C"))
            }),
        ),
        (
            "deflection".into(),
            Box::new(move |p| Some(q(p.ctx.deflection.norm(), &edges_defl, " mm"))),
        ),
        (
            "stylus/head".into(),
            Box::new(|p| {
                Some(format!(
                    "tip {} A1={:.0}° A2={:.0}°",
                    p.ctx.tip_id, p.ctx.head_a1_deg, p.ctx.head_a2_deg
                ))
            }),
        ),
        (
            "time".into(),
            Box::new(move |p| Some(q(p.ctx.t_ns as f64 * 1e-9, &edges_t, " s"))),
        ),
    ];
    // The points of each failing bin, to tell bins that are the same scans seen through
    // correlated features (speed, acceleration, rotation frequency on one ring).
    let mut members: Vec<Vec<u32>> = vec![];
    for (name, key) in &keys {
        type Acc = (usize, f64, f64, Vec<u32>);
        let mut acc: std::collections::BTreeMap<String, Acc> = Default::default();
        for (i, p) in ds.points.iter().enumerate() {
            if !all[i] {
                continue;
            }
            if let Some(k) = key(p) {
                let a = acc.entry(k).or_default();
                a.0 += 1;
                a.1 += res_um[i];
                a.2 += res_um[i] * res_um[i];
                a.3.push(i as u32);
            }
        }
        let mut acc: Vec<(String, Acc)> = acc.into_iter().collect();
        acc.sort_by(|a, b| {
            let (oa, ob) = (order(&a.0), order(&b.0));
            oa.0.total_cmp(&ob.0).then(oa.1.cmp(&ob.1))
        });
        for (k, (cnt, s, s2, idx)) in acc {
            let r = (s2 / cnt as f64).sqrt();
            let failing = cnt >= 30 && r > 1.3 * rms && r > 2.0 * noise;
            bins.push(Bin {
                feature: name.clone(),
                bin: k,
                n: cnt,
                rms_um: r,
                mean_um: s / cnt as f64,
                failing,
                same_points_as: None,
            });
            members.push(if failing { idx } else { vec![] });
        }
    }
    let mut order_fail: Vec<usize> = (0..bins.len()).filter(|&b| bins[b].failing).collect();
    order_fail.sort_by(|a, b| bins[*b].rms_um.total_cmp(&bins[*a].rms_um));
    // Greedy groups: a failing bin that shares ≥ 80 % of the smaller one's points with a
    // worse one of another feature is that one seen another way.
    let mut leaders: Vec<usize> = vec![];
    for &b in &order_fail {
        let lead = leaders.iter().copied().find(|&l| {
            bins[l].feature != bins[b].feature && overlap(&members[l], &members[b]) >= 0.8
        });
        match lead {
            Some(l) => {
                bins[b].same_points_as = Some(format!("{} {}", bins[l].feature, bins[l].bin))
            }
            None => leaders.push(b),
        }
    }
    let failures: Vec<Bin> = order_fail.iter().map(|&b| bins[b].clone()).collect();
    // Harmonics of circle features.
    let mut harmonics = vec![];
    for (fi, f) in art.features.iter().enumerate() {
        let Some(f) = f else { continue };
        if f.kind == FeatureKind::Face {
            continue;
        }
        let mut amp = [0.0; 5];
        let idx: Vec<usize> = (0..ds.points.len())
            .filter(|&i| ds.points[i].feature == fi)
            .collect();
        for (k, a) in amp.iter_mut().enumerate() {
            let kk = (k + 1) as f64;
            let th = |i: usize| {
                (ds.points[i].surface.y - f.center.y).atan2(ds.points[i].surface.x - f.center.x)
                    * kk
            };
            let (mut cc, mut cs, mut ss_, mut bc, mut bs) = (0.0, 0.0, 0.0, 0.0, 0.0);
            for &i in &idx {
                let (s, c) = th(i).sin_cos();
                cc += c * c;
                cs += c * s;
                ss_ += s * s;
                bc += c * res_um[i];
                bs += s * res_um[i];
            }
            let det = cc * ss_ - cs * cs;
            if det > 1e-12 {
                let (x, y) = ((ss_ * bc - cs * bs) / det, (cc * bs - cs * bc) / det);
                *a = x.hypot(y);
            }
        }
        harmonics.push(Harmonics {
            feature: fi,
            artifact: ds.features[fi].1.artifact.clone(),
            amplitude_um: amp,
        });
    }
    let mut tracking = ds.tracking.clone();
    tracking.sort_by(|a, b| b.2.total_cmp(&a.2));
    tracking.truncate(20);
    Ok(Comparison {
        rms_um: rms,
        pv_um: if mx >= mn { mx - mn } else { 0.0 },
        noise_floor_um: noise,
        failures,
        bins,
        harmonics,
        tracking,
        points: n,
        traces: super::traces::traces(ds, &res_um),
        residual_um: res_um,
    })
}
