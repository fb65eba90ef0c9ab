//! What every command shares: checked outputs and stdout (`output`), opening, reading and
//! correcting bags (`bags`), loading a calibration and committing a new version with its
//! closing lines (`calib`), the zenoh client (`bus`) and its replies as text (`human`), the
//! reports' provenance block (`provenance`), the simulation (`simulate`), the demo's loop
//! (`demo`) and synthetic calibrations and scans (`synth`).

#[macro_use]
pub mod output;
pub mod bags;
pub mod bus;
pub mod calib;
pub mod demo;
pub mod foxglove;
pub mod foxglove_ws;
pub mod human;
pub mod provenance;
pub mod simulate;
pub mod synth;
