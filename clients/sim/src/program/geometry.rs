//! What a program is made of: the artifact features on the table with their true geometry,
//! the paths the carriage follows and the segments that time them.

use super::*;

/// One artifact feature on the table, with its true geometry.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Feature {
    /// Id (segments refer to it).
    pub id: u32,
    /// What the artifact is: `ring`, `sphere`, `straightedge`, `part`.
    pub artifact: String,
    /// Bore, boss or face.
    pub kind: FeatureKind,
    /// True centre (bore, boss) or a point of the face, mm.
    pub center: [f64; 3],
    /// True radius (bore, boss), mm.
    pub radius_mm: f64,
    /// Nominal (drawing) diameter, mm.
    pub nominal_diameter_mm: f64,
    /// Calibration certificate's diameter (ring, sphere), mm.
    pub certificate_diameter_mm: Option<f64>,
    /// Face normal (out of the material); for a bore or boss, its axis when it does not stand
    /// upright (zero: the axis along z, the circle horizontal).
    pub normal: [f64; 3],
    /// Form deviation: (harmonic or wavelength_mm, amplitude mm, phase rad).
    pub form: Vec<[f64; 3]>,
}

impl Feature {
    pub(super) fn c(&self) -> V3 {
        V3::from(self.center)
    }
    /// A bore's or boss's plane when its axis is not z: the in-plane axes (e1, e2) of
    /// [`circle_plane`]; None for an upright one.
    pub fn tilted_plane(&self) -> Option<(V3, V3)> {
        let n = V3::from(self.normal).try_normalize(1e-9)?;
        (n.z.abs() < 1.0 - 1e-9).then(|| circle_plane(&n))
    }
    /// Form deviation at angle θ (circles) or position s along the face.
    pub fn form_at(&self, s: f64) -> f64 {
        match self.kind {
            FeatureKind::Face => self
                .form
                .iter()
                .map(|f| f[1] * (TAU * s / f[0] + f[2]).sin())
                .sum(),
            _ => self
                .form
                .iter()
                .map(|f| f[1] * (f[0] * s + f[2]).sin())
                .sum(),
        }
    }
    /// The tip displacement the surface imposes on a free tip at `tip` with radius `r`
    /// (zero when not touching).
    pub fn push(&self, tip: &V3, r: f64) -> V3 {
        match self.kind {
            FeatureKind::Bore if self.tilted_plane().is_some() => {
                // A ring standing on its edge: the same contact in its own plane.
                let (e1, e2) = self.tilted_plane().unwrap_or((V3::x(), V3::y()));
                let d = tip - self.c();
                let (a, b) = (d.dot(&e1), d.dot(&e2));
                let dp = e1 * a + e2 * b;
                let dist = dp.norm();
                if dist == 0.0 {
                    return V3::zeros();
                }
                let limit = self.radius_mm + self.form_at(b.atan2(a)) - r;
                if dist > limit {
                    -dp / dist * (dist - limit)
                } else {
                    V3::zeros()
                }
            }
            FeatureKind::Bore => {
                let d = tip - self.c();
                let dxy = V3::new(d.x, d.y, 0.0);
                let dist = dxy.norm();
                if dist == 0.0 {
                    return V3::zeros();
                }
                let th = d.y.atan2(d.x);
                let limit = self.radius_mm + self.form_at(th) - r;
                if dist > limit {
                    -dxy / dist * (dist - limit)
                } else {
                    V3::zeros()
                }
            }
            FeatureKind::Boss => {
                let d = tip - self.c();
                let dist = d.norm();
                if dist == 0.0 {
                    return V3::zeros();
                }
                let th = d.y.atan2(d.x);
                let limit = self.radius_mm + self.form_at(th) + r;
                if dist < limit {
                    d / dist * (limit - dist)
                } else {
                    V3::zeros()
                }
            }
            FeatureKind::Face => {
                let n = V3::from(self.normal);
                let along = face_along(&n);
                let s = (tip - self.c()).dot(&along);
                let h = (tip - self.c()).dot(&n) - self.form_at(s) - r;
                if h < 0.0 {
                    -n * h
                } else {
                    V3::zeros()
                }
            }
        }
    }
}

/// The in-plane axes of a circle whose axis is the unit `n` (not along z): e1 = n × z
/// (normalised, the direction along a face of that normal, as the lab takes it), e2 = e1 × n
/// (up for an axis in the horizontal plane). Rotation from e1 towards e2 is about −n.
pub fn circle_plane(n: &V3) -> (V3, V3) {
    let e1 = n.cross(&V3::z()).try_normalize(1e-9).unwrap_or(V3::x());
    (e1, e1.cross(n))
}

/// The plane of a horizontal arc.
pub(super) fn horizontal() -> [V3; 2] {
    [V3::x(), V3::y()]
}

/// A carriage path.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Path {
    /// Straight line.
    Line {
        /// Start.
        from: V3,
        /// End.
        to: V3,
    },
    /// Arc: centre, radius, start angle, signed sweep (CCW > 0 about `plane`'s e1 × e2) in
    /// the plane spanned by `plane` (x, y: a horizontal arc).
    Arc {
        /// Centre (carriage coordinates).
        center: V3,
        /// Radius.
        radius: f64,
        /// Start angle, rad.
        start: f64,
        /// Signed sweep, rad.
        sweep: f64,
        /// Radial wave on the radius, mm (0: a plain arc): the radius is
        /// `radius + wave_mm·sin(wave_cycles·(θ − start))`, so a probe pressed against a
        /// round feature sees its deflection vary sinusoidally around it.
        wave_mm: f64,
        /// Waves per turn.
        wave_cycles: f64,
        /// The arc's plane: unit axes e1 (angle 0) and e2 (angle π/2).
        plane: [V3; 2],
    },
    /// The probe held at `at` while the carriage oscillates along `dir` (unit):
    /// `at + dir·amplitude·sin(s/amplitude)` at path length s, so a cruise speed v is a peak
    /// speed v and a peak acceleration v²/amplitude (as an arc of that radius), at
    /// f = v/(2π·amplitude); `cycles` whole periods.
    Weave {
        /// Mean carriage position.
        at: V3,
        /// Unit direction of the oscillation (a face's normal).
        dir: V3,
        /// Amplitude, mm.
        amplitude: f64,
        /// Periods.
        cycles: f64,
    },
    /// Standing still.
    Dwell {
        /// Where.
        at: V3,
        /// How long, s.
        seconds: f64,
    },
}

impl Path {
    pub(super) fn length(&self) -> f64 {
        match self {
            Path::Line { from, to } => (to - from).norm(),
            Path::Arc { radius, sweep, .. } => radius * sweep.abs(),
            Path::Weave {
                amplitude, cycles, ..
            } => TAU * amplitude * cycles,
            Path::Dwell { .. } => 0.0,
        }
    }
    pub(super) fn at(&self, s: f64) -> V3 {
        match *self {
            Path::Line { from, to } => {
                let l = (to - from).norm();
                if l == 0.0 {
                    from
                } else {
                    from + (to - from) * (s / l)
                }
            }
            Path::Arc {
                center,
                radius,
                start,
                sweep,
                wave_mm,
                wave_cycles,
                plane: [e1, e2],
            } => {
                let th = start + sweep.signum() * s / radius;
                let r = radius + wave_mm * (wave_cycles * (th - start)).sin();
                center + e1 * (r * th.cos()) + e2 * (r * th.sin())
            }
            Path::Weave {
                at, dir, amplitude, ..
            } => at + dir * (amplitude * (s / amplitude).sin()),
            Path::Dwell { at, .. } => at,
        }
    }
    /// Start point.
    pub fn start(&self) -> V3 {
        self.at(0.0)
    }
    /// End point.
    pub fn end(&self) -> V3 {
        self.at(self.length())
    }
}

/// One planned segment.
#[derive(Debug, Clone, PartialEq)]
pub struct Segment {
    /// Segment id in the command stream.
    pub id: u32,
    /// Kind.
    pub kind: SegmentKind,
    /// Carriage path.
    pub path: Path,
    /// Cruise speed, mm/s.
    pub speed: f64,
    /// Speed ramp duration at each end, s.
    pub ramp_s: f64,
    /// Feature in contact (scans and dwells).
    pub feature: Option<u32>,
    /// Nominal probe deflection, mm.
    pub deflection_mm: f64,
    /// Active tip and head angles.
    pub tip: u32,
    /// Head A1, degrees.
    pub a1_deg: f64,
    /// Head A2, degrees.
    pub a2_deg: f64,
    /// Duration, s (filled by planning).
    pub duration_s: f64,
}

impl Segment {
    pub(super) fn plan(&mut self) {
        self.duration_s = match self.path {
            Path::Dwell { seconds, .. } => seconds,
            _ => {
                let l = self.path.length();
                // A full speed ramp covers v·ramp/2 at each end; shorten the speed if needed.
                if l < self.speed * self.ramp_s {
                    self.speed = l / self.ramp_s;
                }
                if self.speed <= 0.0 {
                    0.0
                } else {
                    l / self.speed + self.ramp_s
                }
            }
        };
    }
    /// Distance along the path at time `t` since the start (smooth speed ramps:
    /// v(t) = v/2·(1 − cos(πt/ramp))).
    pub(super) fn s_at(&self, t: f64) -> f64 {
        let (v, tr, d) = (self.speed, self.ramp_s, self.duration_s);
        if matches!(self.path, Path::Dwell { .. }) || v == 0.0 {
            return 0.0;
        }
        let t = t.clamp(0.0, d);
        let ramp = |t: f64| 0.5 * v * (t - tr / PI * (PI * t / tr).sin());
        if t < tr {
            ramp(t)
        } else if t <= d - tr {
            v * tr / 2.0 + v * (t - tr)
        } else {
            self.path.length() - ramp(d - t)
        }
    }
    /// Carriage command at time `t` since the segment start.
    pub fn at(&self, t: f64) -> V3 {
        self.path.at(self.s_at(t))
    }
}
