//! The one way a plan is chosen. [`Stack::plan`] (and [`FrameMemory::plan`],
//! a stack of one) runs the policy's
//! frustum ranking through the index ([`FrameMemory::select`]) and, when the
//! policy carries co-visibility settings, re-ranks those candidates by what
//! each frame saw of the target's surface ([`covisibility::rerank`]). A new
//! selection strategy is a field of [`Policy`] and a branch here.

use crate::covisibility::{self, CoVisibilityStats, DepthGrid};
use crate::error::InputError;
use crate::frustum::Frustum;
use crate::index::{FrameMemory, SelectionStats, Stack};
use crate::policy::{ContextPlan, Policy};

/// A plan and what choosing it cost.
#[derive(Clone, Debug, PartialEq)]
pub struct Selection {
    pub plan: ContextPlan,
    /// The frustum stage's work (zero when co-visibility chose).
    pub stats: SelectionStats,
    /// What the co-visibility stage did, when the policy asked for it.
    pub covisibility: Option<CoVisibilityStats>,
}

impl FrameMemory {
    /// `policy`'s plan for `target` (see [`Stack::plan`]).
    pub fn plan<'a>(
        &self,
        policy: &Policy,
        target: &Frustum,
        previous: Option<&ContextPlan>,
        depth_of: impl Fn(u64) -> Option<&'a DepthGrid>,
    ) -> Result<Selection, InputError> {
        Stack::of(self).plan(policy, target, previous, depth_of)
    }
}

impl Stack<'_> {
    /// `policy`'s plan for `target`. `depth_of` gives a stored frame's coarse
    /// depth at the policy's co-visibility grid (unused without co-visibility);
    /// `previous`, the last plan for a nearby target, only speeds things up.
    pub fn plan<'a>(
        &self,
        policy: &Policy,
        target: &Frustum,
        previous: Option<&ContextPlan>,
        depth_of: impl Fn(u64) -> Option<&'a DepthGrid>,
    ) -> Result<Selection, InputError> {
        Ok(match &policy.covisibility {
            None => {
                let (plan, stats) = self.select(policy, target, previous);
                Selection { plan, stats, covisibility: None }
            }
            Some(settings) => {
                let (plan, stats) = covisibility::rerank(self, policy, target, settings, previous, depth_of)?;
                Selection { plan, stats: SelectionStats::default(), covisibility: Some(stats) }
            }
        })
    }
}
