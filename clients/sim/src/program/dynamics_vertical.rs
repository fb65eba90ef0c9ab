//! The dynamics program's rings standing on their edge (`dynamics-vertical`): the ring gauge of
//! `dynamics` set up with its axis along Y (the circle in the XZ plane) and along X (the circle
//! in the YZ plane), each scanned at three speeds in both directions with the reference stylus
//! turned horizontal along the ring's axis (head A2 = 90°: the stylus along +y; A1 = 90°, A2 =
//! 90°: along −x), as a user sets a ring up on a V-block.
//!
//! On these circles the carriage accelerates along Z and the probe measures along Z: P's Z row
//! and column and the servo phase of Z against X (and against Y) act on them, which rings in a
//! horizontal plane cannot show. The XZ rings stand at three places along X and two heights,
//! the YZ rings at two places along Y, so P's Z entries also change along the travel where the
//! rings spread.

use super::*;

/// Speeds, mm/s (the `dynamics` program's).
const SPEEDS: [f64; 4] = [15.0, 40.0, 80.0, 120.0];

/// Plans the rings about `position` (or the dynamics program's base).
pub(super) fn plan(b: &mut Builder, position: Option<V3>) {
    let base = position.unwrap_or(V3::new(500.0, 400.0, -280.0));
    // (ring centre, its axis, head A1, A2: the stylus along the axis into the bore).
    let xz = |dx: f64, dz: f64| (base + V3::new(dx, 0.0, dz), [0.0, 1.0, 0.0], 0.0, 90.0);
    let yz = |dy: f64| (base + V3::new(0.0, dy, 0.0), [1.0, 0.0, 0.0], 90.0, 90.0);
    let places = [
        xz(-250.0, 0.0),
        xz(0.0, 0.0),
        xz(250.0, 0.0),
        xz(0.0, -140.0),
        yz(-150.0),
        yz(150.0),
    ];
    for (i, (c, axis, a1, a2)) in places.into_iter().enumerate() {
        let mut ring = ring_feature(c, 0.45 + 0.7 * i as f64);
        ring.normal = axis;
        let f = b.feature(ring);
        b.set_tip(1, a1, a2);
        for v in SPEEDS {
            b.circle(f, v, 1.0, 0.3, 0.0);
            b.circle(f, v, -1.0, 0.3, PI);
        }
    }
    b.set_tip(1, 0.0, 0.0);
}
