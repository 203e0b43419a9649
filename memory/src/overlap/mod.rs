//! Field-of-view overlap `o_i = Vol(V_i ∩ V_t) / Vol(V_t)` (paper Eq. 6),
//! by three estimators that users can choose between.

mod exact;
mod sampled;

pub use exact::{Need, Polytope, clipped_volume, exact_overlap, overlap_unless_below};
pub(crate) use exact::overlap_within_unless_below;
pub use sampled::{MonteCarlo, ViewSamples, WorldMemBall};
use serde::{Deserialize, Serialize};

use crate::frustum::Frustum;

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, Default)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Estimator {
    /// Convex clipping in f64: the true volume ratio, deterministic.
    #[default]
    Exact,
    /// The paper's estimator: uniform points in the query frustum.
    MonteCarlo(MonteCarlo),
    /// WorldMem's code: points in a ball, angular FoV tests.
    #[serde(rename = "worldmem")]
    WorldMem(WorldMemBall),
}

impl Estimator {
    /// Overlap of each candidate with the query, in candidate order.
    pub fn overlaps<'a>(&self, query: &Frustum, candidates: impl IntoIterator<Item = &'a Frustum>) -> Vec<f64> {
        match self.samples(query) {
            None => candidates.into_iter().map(|c| exact_overlap(query, c)).collect(),
            Some(s) => candidates.into_iter().map(|c| s.overlap(c)).collect(),
        }
    }

    /// The sample set standing for the query's view, for sampled estimators.
    pub fn samples(&self, query: &Frustum) -> Option<ViewSamples> {
        match self {
            Estimator::Exact => None,
            Estimator::MonteCarlo(p) => Some(ViewSamples::monte_carlo(query, p)),
            Estimator::WorldMem(p) => Some(ViewSamples::worldmem(query, p)),
        }
    }

    /// Checks parameters, naming the bad one.
    pub fn validated(self) -> Result<Self, crate::InputError> {
        use crate::InputError;
        let positive = |field: &str, v: f64| {
            if v.is_finite() && v > 0.0 { Ok(()) } else { Err(InputError::NotPositive { field: field.into(), value: v }) }
        };
        match &self {
            Estimator::Exact => {}
            Estimator::MonteCarlo(p) => positive("estimator.samples", p.samples as f64)?,
            Estimator::WorldMem(p) => {
                positive("estimator.samples", p.samples as f64)?;
                positive("estimator.radius", p.radius)?;
                for (field, v) in [("estimator.hfov_deg", p.hfov_deg), ("estimator.vfov_deg", p.vfov_deg)] {
                    if !(v > 0.0 && v < 360.0) {
                        return Err(InputError::Invalid { field: field.into(), reason: format!("must lie in (0, 360), got {v}") });
                    }
                }
            }
        }
        Ok(self)
    }
}
