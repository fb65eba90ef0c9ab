//! The builder that lays a program out as segments from its home: features placed, scans
//! and moves between them with the tip and head angles they need.

use super::*;

/// The master sphere (certified diameter 25.0004 mm) at `position` or its usual place.
pub(super) fn master_sphere(position: Option<V3>) -> Feature {
    Feature {
        id: 0,
        artifact: "sphere".into(),
        kind: FeatureKind::Boss,
        center: position.unwrap_or(V3::new(620.0, 220.0, -360.0)).into(),
        radius_mm: 25.0004 / 2.0,
        nominal_diameter_mm: 25.0,
        certificate_diameter_mm: Some(25.0004),
        normal: [0.0; 3],
        form: vec![[2.0, 0.01e-3, 0.2]],
    }
}

pub(super) struct Builder<'a> {
    pub(super) m: &'a TrueMachine,
    pub(super) features: Vec<Feature>,
    pub(super) segs: Vec<Segment>,
    pub(super) carriage: V3,
    pub(super) tip: u32,
    pub(super) a1: f64,
    pub(super) a2: f64,
}

impl<'a> Builder<'a> {
    pub(super) fn stylus(&self, tip: u32) -> &Stylus {
        self.m.stylus(tip).expect("program uses known tips")
    }
    pub(super) fn offset(&self, tip: u32, a1: f64, a2: f64) -> V3 {
        let (s, b) = self.stylus(tip).limbs();
        head_rotation(a1, a2) * (s + b)
    }
    pub(super) fn push(
        &mut self,
        kind: SegmentKind,
        path: Path,
        speed: f64,
        ramp: f64,
        feature: Option<u32>,
        defl: f64,
    ) {
        let mut s = Segment {
            id: self.segs.len() as u32 + 1,
            kind,
            path,
            speed,
            ramp_s: ramp,
            feature,
            deflection_mm: defl,
            tip: self.tip,
            a1_deg: self.a1,
            a2_deg: self.a2,
            duration_s: 0.0,
        };
        s.plan();
        self.carriage = s.path.end();
        self.segs.push(s);
    }
    pub(super) fn move_to(&mut self, to: V3) {
        if (to - self.carriage).norm() > 1e-9 {
            self.push(
                SegmentKind::Move,
                Path::Line {
                    from: self.carriage,
                    to,
                },
                120.0,
                0.3,
                None,
                0.0,
            );
        }
    }
    pub(super) fn set_tip(&mut self, tip: u32, a1: f64, a2: f64) {
        self.tip = tip;
        self.a1 = a1;
        self.a2 = a2;
    }
    pub(super) fn feature(&mut self, mut f: Feature) -> u32 {
        f.id = self.features.len() as u32 + 1;
        let id = f.id;
        self.features.push(f);
        id
    }
    /// Approach, stand in contact, scan the path, stand again.
    pub(super) fn scan(&mut self, path: Path, speed: f64, ramp: f64, fid: u32, defl: f64) {
        self.move_to(path.start());
        let dwell = |at, seconds| Path::Dwell { at, seconds };
        self.push(
            SegmentKind::Dwell,
            dwell(path.start(), 0.25),
            0.0,
            0.0,
            Some(fid),
            defl,
        );
        self.push(SegmentKind::Scan, path, speed, ramp, Some(fid), defl);
        self.push(
            SegmentKind::Dwell,
            dwell(self.carriage, 0.15),
            0.0,
            0.0,
            Some(fid),
            defl,
        );
    }
    /// A circle scan of a bore or boss: one turn plus the ramps, dwell before and after; in
    /// the feature's own plane when its axis is not z (a ring standing on its edge).
    pub(super) fn circle(&mut self, fid: u32, speed: f64, dir: f64, defl: f64, start: f64) {
        let f = self.features[fid as usize - 1].clone();
        let r_tip = self.stylus(self.tip).radius_mm;
        let off = self.offset(self.tip, self.a1, self.a2);
        let path_r = match f.kind {
            FeatureKind::Bore => f.radius_mm - r_tip + defl,
            _ => f.radius_mm + r_tip - defl,
        };
        let nominal_r = match f.kind {
            FeatureKind::Bore => f.nominal_diameter_mm / 2.0 - r_tip + defl,
            _ => f.nominal_diameter_mm / 2.0 + r_tip - defl,
        };
        let _ = path_r;
        let center = f.c() - off;
        let ramp = (speed / 150.0).max(0.4);
        let sweep = dir * (TAU + speed * ramp / nominal_r);
        let path = Path::Arc {
            center,
            radius: nominal_r,
            start,
            sweep,
            wave_mm: 0.0,
            wave_cycles: 0.0,
            plane: f.tilted_plane().map_or(horizontal(), |(e1, e2)| [e1, e2]),
        };
        self.scan(path, speed, ramp, fid, defl);
    }
    /// A circle on a sphere (a boss feature) at latitude `lat_deg` of the tip centre: one turn
    /// plus the ramps, the tip pressed in by `defl` along the sphere's radius.
    pub(super) fn sphere_circle(
        &mut self,
        fid: u32,
        speed: f64,
        dir: f64,
        defl: f64,
        lat_deg: f64,
    ) {
        self.sphere_arc(fid, speed, dir, defl, lat_deg, 1.0);
    }
    /// `turns` of a circle on a sphere from angle 0 (plus the ramps), as [`Self::sphere_circle`].
    pub(super) fn sphere_arc(
        &mut self,
        fid: u32,
        speed: f64,
        dir: f64,
        defl: f64,
        lat_deg: f64,
        turns: f64,
    ) {
        self.sphere_wave(fid, speed, dir, defl, lat_deg, turns, (0.0, 0.0));
    }
    /// As [`Self::sphere_arc`], the deflection varying as `defl + a·sin(n·θ)` around the
    /// circle (`wave` = (a mm, n per turn)).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn sphere_wave(
        &mut self,
        fid: u32,
        speed: f64,
        dir: f64,
        defl: f64,
        lat_deg: f64,
        turns: f64,
        wave: (f64, f64),
    ) {
        let f = self.features[fid as usize - 1].clone();
        let r_tip = self.stylus(self.tip).radius_mm;
        let off = self.offset(self.tip, self.a1, self.a2);
        let rho = f.nominal_diameter_mm / 2.0 + r_tip - defl;
        let lat = lat_deg.to_radians();
        let (h, radius) = (rho * lat.sin(), rho * lat.cos());
        let center = f.c() + V3::new(0.0, 0.0, h) - off;
        let ramp = (speed / 150.0).max(0.4);
        let path = Path::Arc {
            center,
            radius,
            start: 0.0,
            sweep: dir * (turns * TAU + speed * ramp / radius),
            // The path's radius shrinks where the deflection grows: moving the tip in by δ
            // horizontally presses it in by δ·cos(lat) along the sphere's radius.
            wave_mm: -wave.0 / lat.cos(),
            wave_cycles: wave.1,
            plane: horizontal(),
        };
        self.scan(path, speed, ramp, fid, defl);
    }
    /// A radial approach to a sphere at latitude 0 and angle `theta`: the tip pressed in from
    /// `d0` to `d1` along the sphere's radius at `speed`.
    pub(super) fn sphere_approach(&mut self, fid: u32, theta: f64, d0: f64, d1: f64, speed: f64) {
        let f = self.features[fid as usize - 1].clone();
        let r_tip = self.stylus(self.tip).radius_mm;
        let off = self.offset(self.tip, self.a1, self.a2);
        let u = V3::new(theta.cos(), theta.sin(), 0.0);
        let at = |d: f64| f.c() + u * (f.nominal_diameter_mm / 2.0 + r_tip - d) - off;
        let path = Path::Line {
            from: at(d0),
            to: at(d1),
        };
        self.scan(path, speed, 0.4, fid, d0);
    }
    /// A line along a face from `s0` to `s1` (positions along the face).
    pub(super) fn face_line(&mut self, fid: u32, s0: f64, s1: f64, speed: f64, defl: f64) {
        let f = self.features[fid as usize - 1].clone();
        let n = V3::from(f.normal);
        let along = face_along(&n);
        let r_tip = self.stylus(self.tip).radius_mm;
        let off = self.offset(self.tip, self.a1, self.a2);
        let base = f.c() + n * (r_tip - defl) - off;
        let path = Path::Line {
            from: base + along * s0,
            to: base + along * s1,
        };
        self.scan(path, speed, 0.4, fid, defl);
    }
    /// The probe pressed on a face by `defl` at `at` along it while the carriage oscillates
    /// along the face's normal with amplitude `amp` at `freq` Hz for `cycles` periods (the
    /// deflection swings defl ∓ amp; the acceleration amp·(2π·freq)² lies along the normal).
    pub(super) fn face_weave(
        &mut self,
        fid: u32,
        at: f64,
        amp: f64,
        freq: f64,
        cycles: f64,
        defl: f64,
    ) {
        let f = self.features[fid as usize - 1].clone();
        let n = V3::from(f.normal);
        let along = face_along(&n);
        let r_tip = self.stylus(self.tip).radius_mm;
        let off = self.offset(self.tip, self.a1, self.a2);
        let path = Path::Weave {
            at: f.c() + n * (r_tip - defl) - off + along * at,
            dir: n,
            amplitude: amp,
            cycles,
        };
        self.scan(
            path,
            TAU * freq * amp,
            scancorr_core::lab::plan::WEAVE_RAMP_S,
            fid,
            defl,
        );
    }
}

/// The direction along a face of normal `n` (n × z; x for a face whose normal is z), as the
/// lab takes it.
pub(super) fn face_along(n: &V3) -> V3 {
    n.cross(&V3::z()).try_normalize(1e-9).unwrap_or(V3::x())
}

pub(super) fn ring_feature(at: V3, form_seed: f64) -> Feature {
    Feature {
        id: 0,
        artifact: "ring".into(),
        kind: FeatureKind::Bore,
        center: at.into(),
        radius_mm: 50.0012 / 2.0,
        nominal_diameter_mm: 50.0,
        certificate_diameter_mm: Some(50.0012),
        normal: [0.0; 3],
        form: vec![
            [2.0, 0.02e-3, form_seed],
            [3.0, 0.015e-3, 2.0 * form_seed],
            [5.0, 0.01e-3, 0.3],
        ],
    }
}

/// The S1/F1/F2 joint method's scans (`dynamic-map`) of circle `f`, all counter-clockwise from
/// angle 0 on one path: S1 slow at d1, F2 fast at d1, F1 fast at d2. A like part
/// (`dynamic-map-part`) gets the first two only — its slow scan and its fast scan — so its
/// fast scan has F2's segment id (the same part program).
pub(super) fn dynamic_map_scans(b: &mut Builder, f: u32, like_part: bool) {
    const SLOW: f64 = 5.0;
    const FAST: f64 = 80.0;
    const D1: f64 = 0.3;
    const D2: f64 = 0.5;
    b.circle(f, SLOW, 1.0, D1, 0.0);
    b.circle(f, FAST, 1.0, D1, 0.0);
    if !like_part {
        b.circle(f, FAST, 1.0, D2, 0.0);
    }
}

/// Where every program starts and ends: the carriage high over the middle of the table.
pub(super) const HOME: V3 = V3::new(500.0, 400.0, -100.0);

impl<'a> Builder<'a> {
    /// A program's start: the carriage at its home, tip 1 at head angles 0°, half a second's
    /// dwell.
    pub(super) fn at_home(m: &'a TrueMachine) -> Builder<'a> {
        let home = HOME;
        let mut b = Builder {
            m,
            features: vec![],
            segs: vec![],
            carriage: home,
            tip: 1,
            a1: 0.0,
            a2: 0.0,
        };
        b.push(
            SegmentKind::Move,
            Path::Dwell {
                at: home,
                seconds: 0.5,
            },
            0.0,
            0.0,
            None,
            0.0,
        );
        b
    }
}
