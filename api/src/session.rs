//! A live session: its policy, the indexed frame memory, every frame's pose
//! and latent, and (in the synthetic world) the player for the motion model.

use std::sync::Arc;

use memory::{ContextPlan, FrameMemory, Frustum, Intrinsics, MemoryFrame, Policy, PolicySpec, Pose};
use world::World;
use world::agent::{Action, PlayerState, WALK_SPEED};

use crate::error::ApiError;
use crate::store::{FrameMeta, FrameRecord, SessionRecord};

pub struct Frame {
    pub pose: Pose,
    pub time: u64,
    pub latent: Vec<f32>,
    pub player: Option<PlayerState>,
    /// Made by the model (a step), not observed: the model is told so when it is in context.
    pub generated: bool,
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
}

/// A stored frame's `source` when a step made it (else `observed`).
pub const GENERATED: &str = "generated";
pub const OBSERVED: &str = "observed";

pub fn policy_of(spec: &serde_json::Value) -> Result<Policy, ApiError> {
    let spec: PolicySpec = serde_path_to_error::deserialize(spec.clone())
        .map_err(|e| ApiError::bad(format!("policy.{}", e.path()).trim_end_matches(".").to_string(), e.inner().to_string()))?;
    Ok(spec.into_policy().map_err(|e| e.within("policy"))?)
}

pub fn pose_of(meta: &FrameMeta) -> Result<Pose, ApiError> {
    Ok(Pose::from_matrix_rows(meta.c2w)?)
}

impl Session {
    /// Rebuilds a session from its stored record and frames (server start).
    pub fn restore(id: u64, record: SessionRecord, frames: Vec<FrameRecord>, world: Option<Arc<World>>) -> Result<Session, ApiError> {
        let policy = policy_of(&record.policy)?;
        let mut s = Session { id, record, policy, memory: FrameMemory::new(), frames: Vec::new(), last_plan: None, world, deleted: false };
        for f in frames {
            let generated = f.meta.source == GENERATED;
            s.push(f.meta.time, pose_of(&f.meta)?, f.latent, f.meta.player.map(player_from), generated)?;
        }
        Ok(s)
    }

    pub fn intrinsics(&self) -> &Intrinsics {
        &self.record.intrinsics
    }

    pub fn frustum(&self, pose: Pose) -> Result<Frustum, ApiError> {
        Ok(Frustum::new(pose, self.record.intrinsics)?)
    }

    /// Adds a committed frame to the in-memory index.
    pub fn push(&mut self, time: u64, pose: Pose, latent: Vec<f32>, player: Option<PlayerState>, generated: bool) -> Result<(), ApiError> {
        let frustum = self.frustum(pose)?;
        self.memory.insert(MemoryFrame { id: self.frames.len() as u64, time, frustum })?;
        self.frames.push(Frame { pose, time, latent, player, generated });
        Ok(())
    }

    pub fn next_time(&self) -> u64 {
        self.frames.last().map_or(0, |f| f.time + 1)
    }

    /// The pose after `action`: the world's physics in a synthetic session,
    /// else the kinematic model.
    pub fn motion(&self, action: &Action) -> Result<(Pose, Option<PlayerState>), ApiError> {
        let last = self.frames.last().ok_or_else(|| ApiError::internal("session without frames"))?;
        match (&self.world, last.player) {
            (Some(world), Some(player)) => {
                let next = world::agent::step(world, &player, action);
                Ok((next.camera(), Some(next)))
            }
            _ => Ok((kinematic(&last.pose, action), None)),
        }
    }
}

pub fn player_from(p: [f64; 5]) -> PlayerState {
    PlayerState { feet: [p[0], p[1], p[2]], yaw_deg: p[3], pitch_deg: p[4] }
}

pub fn player_to(p: &PlayerState) -> [f64; 5] {
    [p.feet[0], p.feet[1], p.feet[2], p.yaw_deg, p.pitch_deg]
}

/// The motion model for worlds the server cannot simulate: turn about the
/// world's vertical (−y in OpenCV world terms: the camera's "up" is −y), then
/// move `WALK_SPEED` along the pressed keys in the horizontal plane. No
/// collisions, no gravity; jump is ignored.
pub fn kinematic(pose: &Pose, a: &Action) -> Pose {
    use glam::{DMat3, DVec3};
    let yaw = DMat3::from_rotation_y(-a.yaw_deg.to_radians());
    let rotation = yaw * pose.rotation() * DMat3::from_rotation_x(-a.pitch_deg.to_radians());
    let forward = rotation * DVec3::Z;
    let flat = DVec3::new(forward.x, 0.0, forward.z).try_normalize().unwrap_or(DVec3::Z);
    let right = DVec3::new(-flat.z, 0.0, flat.x);
    let keys = |on: bool| if on { 1.0 } else { 0.0 };
    let dir = flat * (keys(a.forward) - keys(a.back)) + right * (keys(a.right) - keys(a.left));
    let step = dir.try_normalize().map_or(DVec3::ZERO, |d| d * WALK_SPEED);
    // Re-orthonormalised so thousands of steps (or a caller's pose at the edge
    // of the tolerance) never drift out of what `Pose::new` accepts.
    let rotation = DMat3::from_quat(glam::DQuat::from_mat3(&rotation).normalize());
    Pose::new(rotation, pose.position() + step).unwrap_or(*pose)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// On open flat ground the world's physics is pure kinematics, so the
    /// kinematic model must land on the same camera pose.
    #[test]
    fn kinematic_model_matches_the_world_on_flat_ground() {
        let world = World::flat(64, 10);
        let mut player = PlayerState { feet: [32.5, 11.0, 32.5], yaw_deg: 30.0, pitch_deg: 10.0 };
        let mut pose = player.camera();
        let actions = [
            Action { forward: true, ..Action::default() },
            Action { forward: true, yaw_deg: 12.0, ..Action::default() },
            Action { left: true, pitch_deg: -5.0, ..Action::default() },
            Action { back: true, right: true, yaw_deg: -40.0, ..Action::default() },
        ];
        for a in actions.iter().cycle().take(20) {
            player = world::agent::step(&world, &player, a);
            pose = kinematic(&pose, a);
            let want = player.camera();
            assert!((pose.position() - want.position()).length() < 1e-9, "{:?} vs {:?}", pose.position(), want.position());
            assert!(pose.rotation().abs_diff_eq(want.rotation(), 1e-9), "{:?} vs {:?}", pose.rotation(), want.rotation());
        }
    }
}
