//! The model lab: compare the model with measurements of a known artifact, see where it
//! fails, learn which physical effect is missing, add it, refit and watch the error fall.
//!
//! Pure logic: bags are read and reports rendered by the CLI. The pieces:
//! [`program`] (what was measured), [`dataset`] (corrected scan points with their context),
//! [`fit`] (artifact fits with shared placements, the joint linear least squares),
//! [`analysis`] (compare, diagnose, add, structure of unexplained residuals).

pub mod analysis;
pub mod beyond;
pub mod candidates;
pub mod compare;
pub mod dataset;
pub mod discover;
pub mod fit;
pub mod nominal;
pub mod plan;
pub mod program;
pub mod select;
pub mod structure;
pub mod traces;
pub mod types;
pub mod version;

/// Why the lab cannot answer.
#[derive(Debug, Clone, thiserror::Error)]
pub enum LabError {
    /// The calibration is not valid.
    #[error(transparent)]
    Calibration(#[from] crate::calib::CalibError),
    /// The data cannot answer the question; the message says what measurement would.
    #[error("{0}")]
    Data(String),
}
