//! WorldPack's geometry-first frame memory.
//!
//! Every past frame keeps its camera pose; selection scores each one by how
//! much of the target view its frustum covers (with a mild recency penalty),
//! ranks them, and packs the best into the model's context at compression
//! rates chosen by rank. See `docs/architecture.md` for the map and
//! `docs/conventions.md` for the axes.
//!
//! - [`pose`] and [`camera`]: poses (OpenCV camera-to-world) and intrinsics,
//!   with conversions from OpenCV extrinsics, OpenGL and 5-D Minecraft poses.
//! - [`frustum`]: truncated view frusta (f64 planes + a `parry3d` polyhedron).
//! - [`overlap`]: exact, Monte Carlo and WorldMem-style overlap estimators.
//! - [`policy`]: rankings, packings, the [`ContextPlan`] and brute-force selection.
//! - [`covisibility`]: occlusion-aware selection from coarse depth (frustum top-K, then
//!   the share of the target's expected surface each frame saw unoccluded).
//! - [`index`]: [`FrameMemory`], the R-tree-indexed store whose selection
//!   equals brute force but skips frames that provably cannot enter, and
//!   [`Stack`], memories read as one (a fork's shared history and its own frames).
//! - [`selection`]: [`FrameMemory::plan`], the one way a policy's plan is chosen
//!   (the index, then co-visibility when the policy carries it).

pub mod camera;
pub mod covisibility;
pub mod error;
pub mod frustum;
pub mod index;
pub mod input;
pub mod overlap;
pub mod policy;
pub mod pose;
pub mod rng;
pub mod selection;
pub mod stability;
pub mod workload;
pub mod variants;

pub use camera::Intrinsics;
pub use error::InputError;
pub use frustum::Frustum;
pub use index::{FrameMemory, SelectionStats, Stack};
pub use overlap::Estimator;
pub use policy::{ContextPlan, LatentGrid, MemoryFrame, Packing, CoVisibility, Policy, PolicyKind, PolicySpec, Query, Ranking, ScoreWeights, select_by_brute_force};
pub use selection::Selection;
pub use pose::{AngleUnit, Pose, Pose5, Pose5Convention};
pub use variants::{VARIANTS, Variant, short_label, variant};
