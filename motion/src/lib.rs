//! The action space and the motion-model interface. The server needs a
//! motion model for every step (the next camera pose), the synthetic world
//! implements one with physics (`world::agent::Physics`), and sessions of
//! real frames use the kinematic one here; neither needs the other, so this
//! crate is what both share: the action type, the interface and the
//! kinematic model, with no world and no renderer.

use glam::{DMat3, DQuat, DVec3};
use memory::Pose;
use serde::{Deserialize, Serialize};

/// Blocks per step when walking (Minecraft walks 4.317 blocks/s; at 20 Hz
/// that is 0.216 per tick).
pub const WALK_SPEED: f64 = 0.216;

/// One step's controls, LoopNav's action space: movement keys, jump, and
/// camera deltas in degrees (yaw in Minecraft's sense: positive turns right;
/// positive pitch looks down).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Action {
    #[serde(default)]
    pub forward: bool,
    #[serde(default)]
    pub back: bool,
    #[serde(default)]
    pub left: bool,
    #[serde(default)]
    pub right: bool,
    #[serde(default)]
    pub jump: bool,
    #[serde(default)]
    pub yaw_deg: f64,
    #[serde(default)]
    pub pitch_deg: f64,
}

impl Action {
    /// The 7 numbers stored per frame and given to the model: forward, back,
    /// left, right, jump (0/1), yaw delta, pitch delta (degrees).
    pub fn to_vector(&self) -> [f32; 7] {
        let b = |v: bool| if v { 1.0 } else { 0.0 };
        [b(self.forward), b(self.back), b(self.left), b(self.right), b(self.jump), self.yaw_deg as f32, self.pitch_deg as f32]
    }

    pub fn turn(yaw_deg: f64, pitch_deg: f64) -> Action {
        Action { yaw_deg, pitch_deg, ..Action::default() }
    }
}

/// How an agent moves under an action: a state (as little as a camera pose,
/// or a player with feet and a view), one step of it, and the camera it gives.
pub trait MotionModel {
    type State: Copy;
    fn step(&self, state: &Self::State, action: &Action) -> Self::State;
    fn camera(&self, state: &Self::State) -> Pose;
}

/// The motion model for worlds nobody simulates: turn about the world's
/// vertical (−y in OpenCV world terms: the camera's "up" is −y), then move
/// [`WALK_SPEED`] along the pressed keys in the horizontal plane. No
/// collisions, no gravity; jump is ignored. On open flat ground it is the
/// synthetic world's physics exactly (tested in `world`).
#[derive(Clone, Copy, Debug, Default)]
pub struct Kinematic;

impl MotionModel for Kinematic {
    type State = Pose;

    fn step(&self, pose: &Pose, a: &Action) -> Pose {
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
        let rotation = DMat3::from_quat(DQuat::from_mat3(&rotation).normalize());
        Pose::new(rotation, pose.position() + step).unwrap_or(*pose)
    }

    fn camera(&self, pose: &Pose) -> Pose {
        *pose
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_action_vector_is_keys_then_turns() {
        let a = Action { forward: true, jump: true, yaw_deg: 6.0, pitch_deg: -2.5, ..Action::default() };
        assert_eq!(a.to_vector(), [1.0, 0.0, 0.0, 0.0, 1.0, 6.0, -2.5]);
        let typo: Result<Action, _> = serde_json::from_str(r#"{"forwards": true}"#);
        assert!(typo.unwrap_err().to_string().contains("forwards"), "unknown keys are refused by name");
    }

    #[test]
    fn kinematic_steps_walk_and_turn_without_drift() {
        let mut pose = Pose::from_position(DVec3::ZERO);
        let walk = Action { forward: true, ..Action::default() };
        pose = Kinematic.step(&pose, &walk);
        assert!((pose.position() - DVec3::new(0.0, 0.0, WALK_SPEED)).length() < 1e-12, "forward is +z");
        // 30 turns of 12° come back to the start heading; 1,000 more steps stay a valid rotation.
        let start = pose.rotation();
        for _ in 0..30 {
            pose = Kinematic.step(&pose, &Action::turn(12.0, 0.0));
        }
        assert!(pose.rotation().abs_diff_eq(start, 1e-9));
        for i in 0..1000 {
            pose = Kinematic.step(&pose, &Action { forward: true, yaw_deg: 7.0, pitch_deg: if i % 2 == 0 { 3.0 } else { -3.0 }, ..Action::default() });
        }
        assert!(Pose::new(pose.rotation(), pose.position()).is_ok());
    }
}
