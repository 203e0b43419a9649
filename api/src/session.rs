//! A live session: its policy, the indexed frame memory, every frame's pose
//! and latent, and (in the synthetic world) the player for the motion model.

use std::borrow::Cow;
use std::collections::HashMap;
use std::sync::Arc;

use memory::covisibility::{CoVisibility, DepthGrid};
use memory::{ContextPlan, FrameMemory, Frustum, Intrinsics, MemoryFrame, Policy, PolicySpec, Pose, Selection};
use model::WarpSource;
use model::warp::coarse_depth;
use world::World;
use motion::{Action, Kinematic, MotionModel};
use world::agent::PlayerState;

use crate::refusal::EngineError;
use crate::store::{FrameMeta, FrameRecord, SessionRecord};

pub struct Frame {
    pub pose: Pose,
    pub time: u64,
    pub latent: Vec<f32>,
    pub player: Option<PlayerState>,
    /// Made by the model (a step), not observed: the model is told so when it is in context.
    pub generated: bool,
}

/// An observed frame that came with depth, at the session's camera size.
pub struct DepthFrame {
    pub rgb: Vec<u8>,
    pub depth_mm: Vec<u16>,
}

pub struct Session {
    pub id: u64,
    pub record: SessionRecord,
    pub policy: Policy,
    pub memory: FrameMemory,
    pub frames: Vec<Frame>,
    pub last_plan: Option<ContextPlan>,
    pub world: Option<Arc<World>>,
    /// Set by a delete; requests that were queued on the session see it and answer 404.
    pub deleted: bool,
    /// The observed frames with depth, indexed apart: a geometry model warps
    /// the one of them that overlaps the target view most.
    pub depth_memory: FrameMemory,
    pub depth_frames: HashMap<u64, DepthFrame>,
    /// Their depth pooled at the default co-visibility grid (memory::covisibility).
    pub depth_grids: HashMap<u64, DepthGrid>,
}

/// A stored frame's `source` when a step made it (else `observed`).
pub const GENERATED: &str = "generated";
pub const OBSERVED: &str = "observed";

pub fn policy_of(spec: &serde_json::Value) -> Result<Policy, EngineError> {
    let spec: PolicySpec = serde_path_to_error::deserialize(spec.clone())
        .map_err(|e| EngineError::invalid(format!("policy.{}", e.path()).trim_end_matches(".").to_string(), e.inner().to_string()))?;
    Ok(spec.into_policy().map_err(|e| e.within("policy"))?)
}

fn pool_depth(depth_mm: &[u16], k: &Intrinsics, cells: u32) -> Result<DepthGrid, EngineError> {
    coarse_depth(depth_mm, k, cells).map_err(|e| EngineError::invalid("covisibility.cells", e.to_string()))
}

pub fn pose_of(meta: &FrameMeta) -> Result<Pose, EngineError> {
    Ok(Pose::from_matrix_rows(meta.c2w)?)
}

impl Session {
    /// Rebuilds a session from its stored record and frames (server start,
    /// or a session another server made on a shared store).
    pub fn restore(id: u64, record: SessionRecord, frames: Vec<FrameRecord>, world: Option<Arc<World>>) -> Result<Session, EngineError> {
        let policy = policy_of(&record.policy)?;
        let mut s = Session {
            id,
            record,
            policy,
            memory: FrameMemory::new(),
            frames: Vec::new(),
            last_plan: None,
            world,
            deleted: false,
            depth_memory: FrameMemory::new(),
            depth_frames: HashMap::new(),
            depth_grids: HashMap::new(),
        };
        s.append_stored(frames)?;
        Ok(s)
    }

    /// Indexes stored frames that follow the ones indexed already (frames
    /// another server wrote to a shared store, or all of them at a restore).
    pub fn append_stored(&mut self, frames: Vec<FrameRecord>) -> Result<(), EngineError> {
        for f in frames {
            let index = self.frames.len() as u64;
            let generated = f.meta.source == GENERATED;
            self.push(f.meta.time, pose_of(&f.meta)?, f.latent, f.meta.player.map(player_from), generated)?;
            if !f.depth_png16.is_empty() {
                // Both were checked when they arrived; a stored frame that no longer decodes is the store's fault.
                let (rgb, w, h) = world::picture::decode_rgb(&f.png).map_err(EngineError::internal)?;
                let (depth, _, _) = world::picture::decode_depth_png16(&f.depth_png16).map_err(EngineError::internal)?;
                self.add_depth(index, rgb, w, h, depth)?;
            }
        }
        Ok(())
    }

    pub fn intrinsics(&self) -> &Intrinsics {
        &self.record.intrinsics
    }

    pub fn frustum(&self, pose: Pose) -> Result<Frustum, EngineError> {
        Ok(Frustum::new(pose, self.record.intrinsics)?)
    }

    /// Adds a committed frame to the in-memory index.
    pub fn push(&mut self, time: u64, pose: Pose, latent: Vec<f32>, player: Option<PlayerState>, generated: bool) -> Result<(), EngineError> {
        let frustum = self.frustum(pose)?;
        self.memory.insert(MemoryFrame { id: self.frames.len() as u64, time, frustum })?;
        self.frames.push(Frame { pose, time, latent, player, generated });
        Ok(())
    }

    /// Indexes frame `index`'s depth as a warp source. Frames not at the
    /// session's camera size are left out (the warp needs its intrinsics).
    pub fn add_depth(&mut self, index: u64, rgb: Vec<u8>, width: u32, height: u32, depth_mm: Vec<u16>) -> Result<(), EngineError> {
        let k = self.record.intrinsics;
        if (width, height) != (k.width, k.height) {
            return Ok(());
        }
        let f = self.frames.get(index as usize).ok_or_else(|| EngineError::internal(format!("depth for frame {index}, which is not indexed")))?;
        let frustum = self.frustum(f.pose)?;
        self.depth_memory.insert(MemoryFrame { id: index, time: f.time, frustum })?;
        self.depth_grids.insert(index, pool_depth(&depth_mm, &k, CoVisibility::default().cells)?);
        self.depth_frames.insert(index, DepthFrame { rgb, depth_mm });
        Ok(())
    }

    /// Every observed frame's depth pooled to `cells` columns (metres;
    /// memory::covisibility), by frame index.
    pub fn depth_grids(&self, cells: u32) -> Result<Cow<'_, HashMap<u64, DepthGrid>>, EngineError> {
        if cells == CoVisibility::default().cells {
            return Ok(Cow::Borrowed(&self.depth_grids));
        }
        let k = self.intrinsics();
        Ok(Cow::Owned(self.depth_frames.iter().map(|(&id, d)| Ok((id, pool_depth(&d.depth_mm, k, cells)?))).collect::<Result<_, EngineError>>()?))
    }

    /// `policy`'s plan for `target` (memory::selection): co-visibility reads
    /// the observed frames' depth at the policy's grid.
    pub fn plan(&self, policy: &Policy, target: &Frustum, previous: Option<&ContextPlan>) -> Result<Selection, EngineError> {
        self.plan_in(&self.memory, policy, target, previous)
    }

    fn plan_in(&self, memory: &FrameMemory, policy: &Policy, target: &Frustum, previous: Option<&ContextPlan>) -> Result<Selection, EngineError> {
        let grids = match &policy.covisibility {
            Some(c) => self.depth_grids(c.cells)?,
            None => Cow::Owned(HashMap::new()),
        };
        Ok(memory.plan(policy, target, previous, |id| grids.get(&id))?)
    }

    /// The `count` observed frames with depth that overlap `target` most (or,
    /// when the session's policy asks for co-visibility, that saw most of its
    /// expected surface unoccluded), best first, ready to warp, with their
    /// indices (none when no frame with depth sees it).
    pub fn warp_sources(&self, target: &Frustum, count: usize) -> Result<(Vec<u64>, Vec<WarpSource<'_>>), EngineError> {
        let best = Policy { covisibility: self.policy.covisibility, ..Policy::best_overlap_frames(count) };
        let plan = self.plan_in(&self.depth_memory, &best, target, None)?.plan;
        Ok(plan
            .selected()
            .filter_map(|(_, f)| {
                let d = self.depth_frames.get(&f.id)?;
                Some((f.id, WarpSource { rgb: &d.rgb, depth_mm: &d.depth_mm, pose: &self.frames[f.id as usize].pose, intrinsics: self.intrinsics() }))
            })
            .unzip())
    }

    pub fn next_time(&self) -> u64 {
        self.frames.last().map_or(0, |f| f.time + 1)
    }

    /// The pose after `action`: the world's physics in a synthetic session,
    /// else the kinematic model.
    pub fn motion(&self, action: &Action) -> Result<(Pose, Option<PlayerState>), EngineError> {
        let last = self.frames.last().ok_or_else(|| EngineError::internal("session without frames"))?;
        match (&self.world, last.player) {
            (Some(world), Some(player)) => {
                let physics = world::agent::Physics { world };
                let next = physics.step(&player, action);
                Ok((physics.camera(&next), Some(next)))
            }
            _ => Ok((Kinematic.step(&last.pose, action), None)),
        }
    }
}

pub fn player_from(p: [f64; 5]) -> PlayerState {
    PlayerState { feet: [p[0], p[1], p[2]], yaw_deg: p[3], pitch_deg: p[4] }
}

pub fn player_to(p: &PlayerState) -> [f64; 5] {
    [p.feet[0], p.feet[1], p.feet[2], p.yaw_deg, p.pitch_deg]
}
