//! `scancorr calibrate …`: the measuring procedures' I/O — reading the bags and the starting
//! calibration, printing every parameter with its uncertainty, writing the new version. The
//! logic is `scancorr_core::calibrate`.

mod args;
mod dynamic_map;
mod dynamics;
pub mod plate;
mod platefile;
mod probe_force;
mod procedure;
mod scales;
pub mod straightness;
pub mod thermal;
mod tips;
mod zero_force;

use anyhow::Result;
use clap::Subcommand;

#[derive(Subcommand)]
pub enum CalibrateCmd {
    /// Thermal drift from a recording of hours (ISO 230-3): the measured displacement of the
    /// tool or probe against the part with the structure's temperatures (and the spindle
    /// speed), fitted on the first part and judged on a later held-out period; the drift
    /// from the temperatures through their heat paths' lags, each coefficient ± σ.
    ThermalDrift(thermal::Args),
    /// Qualify the styli on a master sphere: the offset of each tip and head angle from the
    /// reference tip gives the stylus lengths, the sphere's apparent size each tip's effective
    /// radius, the drift with temperature each stylus's expansion coefficient.
    Tips(tips::Args),
    /// The scales' expansion: a ball bar (two spheres of a certified centre distance) along
    /// each axis read several times as the room's temperature changes gives each scale's
    /// expansion coefficient (the change of the length with the scale's temperature) and the
    /// machine's length error at 20 °C, each ± σ. Writes the `scale_thermal` effect.
    Scales(scales::Args),
    /// Extrapolation to zero probing force: the same circles on the master sphere scanned
    /// at two or more deflections by each tip give that tip's force coefficients (stylus
    /// bending per mm of deflection along each probe axis).
    ProbeForce(probe_force::Args),
    /// The S1/F1/F2 joint method: a circle scanned slowly at deflection d1 (S1) and fast at
    /// d2 (F1) and at d1 (F2), in one direction, gives a per-point map of the fast scan's error
    /// (extrapolated to zero deflection against the slow scan) for that feature and speed; the
    /// map corrects later fast scans of like parts by the same part program (same segment ids).
    DynamicMap(dynamic_map::Args),
    /// The ring-gauge procedure: one ring at ≥ 5 positions along X (and along Y and Z), each
    /// at several speeds in both directions, gives the nominal time constants, the deflection
    /// matrix P(x, y, z) with cross-coupling, the servo phase with position-dependent
    /// coefficients and the servo gain in the form held-out rings prefer.
    Dynamics(dynamics::Args),
    /// Error separation of a guide's straightness from a straightedge's, without a perfect
    /// reference: distance probes on the carriage stepped along the travel (three probes
    /// with pitch, two probes, or one probe on a shear micro-stage). Writes the axis's
    /// guide_straightness (and pitch) table with its uncertainties.
    Straightness(straightness::Args),
    /// A plate's features (holes) measured against nominal: the similarity (offset,
    /// rotation, scale), the anisotropic scale/shear (quadrupole; scale per axis and
    /// squareness), higher-order terms chosen by cross-validation over holes, each ± σ, and
    /// the original plug-plate tool's fit. Reports only.
    Plate(plate::PlateArgs),
    /// Per-point extrapolation to zero force on a part: the same path scanned at ≥ 2 probing
    /// forces, each point's own line (a polynomial with ≥ 3) to zero force — the part's own
    /// bending (a thin wall) that the sphere's force coefficients cannot know.
    ZeroForce(zero_force::Args),
}

/// Runs a procedure.
pub fn exec(cmd: CalibrateCmd) -> Result<()> {
    crate::shared::output::started();
    match cmd {
        CalibrateCmd::Plate(a) => plate::run(a),
        CalibrateCmd::ZeroForce(a) => zero_force::run(a),
        CalibrateCmd::ThermalDrift(a) => thermal::run(a),
        CalibrateCmd::DynamicMap(a) => dynamic_map::exec(a),
        CalibrateCmd::Straightness(a) => straightness::run(a),
        CalibrateCmd::ProbeForce(a) => probe_force::exec(a),
        CalibrateCmd::Dynamics(a) => dynamics::exec(a),
        CalibrateCmd::Scales(a) => scales::exec(a),
        CalibrateCmd::Tips(a) => tips::exec(a),
    }
}
