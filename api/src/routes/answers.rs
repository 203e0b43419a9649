//! Answer types more than one resource returns: poses and context plans.

use memory::{ContextPlan, Policy, Pose};
use serde::Serialize;
use utoipa::ToSchema;


/// A camera pose as the server answers it: OpenCV camera-to-world.
#[derive(Serialize, ToSchema)]
pub struct PoseAnswer {
    /// Row-major 3×3 rotation.
    pub rotation: [[f64; 3]; 3],
    /// The camera centre in world units.
    pub position: [f64; 3],
}

impl PoseAnswer {
    pub(crate) fn of(p: &Pose) -> PoseAnswer {
        PoseAnswer { rotation: p.rotation_rows(), position: p.position().to_array() }
    }
}

/// One context slot: its rate and the stored frame in it (null when empty).
#[derive(Serialize, ToSchema)]
pub struct SlotAnswer {
    pub slot: usize,
    /// Compression rate: 1, 4 or 16.
    pub rate: u32,
    pub frame: Option<u64>,
    pub time: Option<u64>,
    /// Share of the query view the frame's frustum covers.
    pub overlap: Option<f64>,
    pub score: Option<f64>,
}

#[derive(Serialize, ToSchema)]
pub struct PlanAnswer {
    #[schema(example = "worldpack")]
    pub policy: String,
    pub slots: Vec<SlotAnswer>,
}

impl PlanAnswer {
    pub(crate) fn of(policy: &Policy, plan: &ContextPlan) -> PlanAnswer {
        let slots = plan
            .slots
            .iter()
            .enumerate()
            .map(|(i, s)| SlotAnswer {
                slot: i,
                rate: s.rate,
                frame: s.frame.map(|f| f.id),
                time: s.frame.map(|f| f.time),
                overlap: s.frame.map(|f| f.overlap),
                score: s.frame.map(|f| f.score),
            })
            .collect();
        PlanAnswer { policy: policy.kind.name().to_string(), slots }
    }
}
