//! Self-contained HTML reports (inline SVG, no scripts, no network): polar deviation plots,
//! residual breakdowns with failing bins highlighted, the candidate ranking, the error fall.
//!
//! One module per family (`lab`, `calibrate`, `thermal`), the SVG and HTML primitives in `svg`.

mod calibrate;
mod lab;
mod svg;
pub mod thermal;

pub use calibrate::straightness_pv_um;
pub use calibrate::{dynamic_map, dynamics, probe_force, straightness, tips};
pub use lab::{add, compare, diagnose, discover, history, history_text, HistoryRow};
pub use lab::{candidate_label, model_variants, tidy_diagnosis};
pub use lab::{heldout_explained, AddFigures, DIAGNOSIS_ORDER};
pub use svg::value_sigma;
pub use thermal::thermal_drift;
