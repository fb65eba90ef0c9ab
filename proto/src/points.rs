//! Point batches in either layout: one message per point (v1.0–v1.3) or packed blocks of
//! columns (v1.4, [`v1::CorrectedPointColumns`]). Readers call [`v1::CorrectedPointBatch::into_points`]
//! and get one [`v1::CorrectedPoint`] per point whichever layout was sent; [`pack`] builds the
//! packed form from points (what the service's direct encoder writes, for tests and tools).

use crate::v1;

/// A point batch that breaks the v1.4 rules: both layouts at once, or a block whose columns
/// do not hold one value per point (per point and effect for the corrections).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MalformedPoints(pub String);

impl std::fmt::Display for MalformedPoints {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "malformed CorrectedPointBatch: {}", self.0)
    }
}

impl std::error::Error for MalformedPoints {}

impl v1::CorrectedPointBatch {
    /// The batch's points, one message each: the per-point messages as they are, or every
    /// packed block unpacked in order (each point naming its block's machine and effects).
    pub fn into_points(self) -> Result<Vec<v1::CorrectedPoint>, MalformedPoints> {
        if self.columns.is_empty() {
            return Ok(self.points);
        }
        if !self.points.is_empty() {
            return Err(MalformedPoints(format!(
                "{} per-point messages and {} packed blocks in one batch",
                self.points.len(),
                self.columns.len()
            )));
        }
        let mut out = Vec::with_capacity(self.columns.iter().map(|c| c.seq.len()).sum());
        for (k, c) in self.columns.iter().enumerate() {
            check(c).map_err(|e| MalformedPoints(format!("block {k}: {e}")))?;
            unpack(c, &mut out);
        }
        Ok(out)
    }

    /// How many points the batch holds (in either layout), without unpacking.
    pub fn len(&self) -> usize {
        self.points.len() + self.columns.iter().map(|c| c.seq.len()).sum::<usize>()
    }

    /// No point.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Checks one block's column lengths.
pub fn check(c: &v1::CorrectedPointColumns) -> Result<(), String> {
    let n = c.seq.len();
    let per_point = [
        ("t_ns", c.t_ns.len()),
        ("sample_seq", c.sample_seq.len()),
        ("calibration_version", c.calibration_version.len()),
        ("estimator_valid", c.estimator_valid.len()),
        ("segment_id", c.segment_id.len()),
        ("tip_id", c.tip_id.len()),
        ("surface_x", c.surface_x.len()),
        ("surface_y", c.surface_y.len()),
        ("surface_z", c.surface_z.len()),
        ("tip_center_x", c.tip_center_x.len()),
        ("tip_center_y", c.tip_center_y.len()),
        ("tip_center_z", c.tip_center_z.len()),
        ("normal_x", c.normal_x.len()),
        ("normal_y", c.normal_y.len()),
        ("normal_z", c.normal_z.len()),
    ];
    for (name, len) in per_point {
        if len != n {
            return Err(format!("column `{name}` holds {len} values for {n} points"));
        }
    }
    let want = n
        .checked_mul(c.effects.len())
        .ok_or_else(|| format!("{n} points × {} effects overflow", c.effects.len()))?;
    for (name, len) in [
        ("correction_dx", c.correction_dx.len()),
        ("correction_dy", c.correction_dy.len()),
        ("correction_dz", c.correction_dz.len()),
    ] {
        if len != want {
            return Err(format!(
                "column `{name}` holds {len} values for {n} points × {} effects",
                c.effects.len()
            ));
        }
    }
    Ok(())
}

/// Appends a checked block's points.
fn unpack(c: &v1::CorrectedPointColumns, out: &mut Vec<v1::CorrectedPoint>) {
    let e = c.effects.len();
    let v = |x: &[f64], y: &[f64], z: &[f64], i: usize| {
        Some(v1::Vec3 {
            x: x[i],
            y: y[i],
            z: z[i],
        })
    };
    for i in 0..c.seq.len() {
        out.push(v1::CorrectedPoint {
            machine_id: c.machine_id.clone(),
            seq: c.seq[i],
            t_ns: c.t_ns[i],
            sample_seq: c.sample_seq[i],
            surface: v(&c.surface_x, &c.surface_y, &c.surface_z, i),
            tip_center: v(&c.tip_center_x, &c.tip_center_y, &c.tip_center_z, i),
            normal: v(&c.normal_x, &c.normal_y, &c.normal_z, i),
            corrections: c
                .effects
                .iter()
                .enumerate()
                .map(|(j, id)| v1::Correction {
                    effect: id.clone(),
                    dx: c.correction_dx[i * e + j],
                    dy: c.correction_dy[i * e + j],
                    dz: c.correction_dz[i * e + j],
                })
                .collect(),
            calibration_version: c.calibration_version[i],
            estimator_valid: c.estimator_valid[i],
            segment_id: c.segment_id[i],
            tip_id: c.tip_id[i],
        });
    }
}

/// Packs per-point messages into a v1.4 batch: one block per run of points with the same
/// machine and the same effect ids. A missing vector packs as zero.
pub fn pack(points: &[v1::CorrectedPoint]) -> v1::CorrectedPointBatch {
    let mut columns: Vec<v1::CorrectedPointColumns> = vec![];
    for p in points {
        let ids = p.corrections.iter().map(|c| &c.effect);
        let same = columns
            .last()
            .is_some_and(|c| c.machine_id == p.machine_id && c.effects.iter().eq(ids.clone()));
        if !same {
            columns.push(v1::CorrectedPointColumns {
                machine_id: p.machine_id.clone(),
                effects: ids.cloned().collect(),
                ..Default::default()
            });
        }
        let c = columns.last_mut().expect("a block was pushed");
        c.seq.push(p.seq);
        c.t_ns.push(p.t_ns);
        c.sample_seq.push(p.sample_seq);
        c.calibration_version.push(p.calibration_version);
        c.estimator_valid.push(p.estimator_valid);
        c.segment_id.push(p.segment_id);
        c.tip_id.push(p.tip_id);
        let v = |v: &Option<v1::Vec3>| v.unwrap_or_default();
        let (s, t, n) = (v(&p.surface), v(&p.tip_center), v(&p.normal));
        c.surface_x.push(s.x);
        c.surface_y.push(s.y);
        c.surface_z.push(s.z);
        c.tip_center_x.push(t.x);
        c.tip_center_y.push(t.y);
        c.tip_center_z.push(t.z);
        c.normal_x.push(n.x);
        c.normal_y.push(n.y);
        c.normal_z.push(n.z);
        for k in &p.corrections {
            c.correction_dx.push(k.dx);
            c.correction_dy.push(k.dy);
            c.correction_dz.push(k.dz);
        }
    }
    v1::CorrectedPointBatch {
        points: vec![],
        columns,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use prost::Message;

    fn point(k: u64, machine: &str, effects: &[&str]) -> v1::CorrectedPoint {
        let f = k as f64;
        v1::CorrectedPoint {
            machine_id: machine.into(),
            seq: k,
            t_ns: -(k as i64) * 1_000,
            sample_seq: k + 3,
            surface: Some(v1::Vec3 {
                x: f,
                y: -f,
                z: 0.5,
            }),
            tip_center: Some(v1::Vec3 {
                x: 0.0,
                y: f * 2.0,
                z: 1e-300,
            }),
            normal: Some(v1::Vec3::default()),
            corrections: effects
                .iter()
                .enumerate()
                .map(|(j, e)| v1::Correction {
                    effect: e.to_string(),
                    dx: f * 1e-3 + j as f64,
                    dy: -1e-6,
                    dz: 0.0,
                })
                .collect(),
            calibration_version: k / 3,
            estimator_valid: k % 2 == 0,
            segment_id: (k % 5) as u32,
            tip_id: 7,
        }
    }

    #[test]
    fn packed_batches_read_back_as_their_points_and_join_by_concatenation() {
        let a: Vec<_> = (0..5).map(|k| point(k, "m1", &["a", "", "b"])).collect();
        // A calibration swap (other effects) and no effect at all start new blocks.
        let b: Vec<_> = (5..9)
            .map(|k| point(k, "m1", &["c"]))
            .chain((9..11).map(|k| point(k, "m1", &[])))
            .collect();
        let pa = pack(&a);
        assert_eq!(pa.columns.len(), 1);
        let pb = pack(&b);
        assert_eq!(pb.columns.len(), 2);
        let mut bytes = pa.encode_to_vec();
        bytes.extend(pb.encode_to_vec());
        let both = v1::CorrectedPointBatch::decode(&bytes[..]).unwrap();
        assert_eq!(both.len(), 11);
        let want: Vec<_> = a.iter().chain(&b).cloned().collect();
        assert_eq!(both.into_points().unwrap(), want);
        // The per-point layout reads as it always did.
        let old = v1::CorrectedPointBatch {
            points: want.clone(),
            columns: vec![],
        };
        assert_eq!(old.into_points().unwrap(), want);
    }

    #[test]
    fn malformed_packed_batches_are_refused_with_the_column_named() {
        let good = pack(
            &(0..4)
                .map(|k| point(k, "m1", &["a", "b"]))
                .collect::<Vec<_>>(),
        );
        let mut short = good.clone();
        short.columns[0].normal_y.pop();
        let e = short.into_points().unwrap_err().to_string();
        assert!(
            e.contains("block 0") && e.contains("`normal_y` holds 3 values for 4"),
            "{e}"
        );
        let mut corr = good.clone();
        corr.columns[0].correction_dz.push(1.0);
        let e = corr.into_points().unwrap_err().to_string();
        assert!(
            e.contains("`correction_dz` holds 9 values for 4 points × 2 effects"),
            "{e}"
        );
        let mut both = good;
        both.points.push(point(9, "m1", &[]));
        let e = both.into_points().unwrap_err().to_string();
        assert!(
            e.contains("1 per-point messages and 1 packed blocks"),
            "{e}"
        );
    }
}
