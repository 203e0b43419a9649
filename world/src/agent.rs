//! A Minecraft-like player: LoopNav's actions, a kinematic motion model with
//! ground following, one-block steps and collisions, an A* path finder over
//! standable cells, and a path follower that turns paths into actions.

use std::cmp::Ordering;
use std::collections::{BinaryHeap, HashMap};

use glam::DVec3;
use memory::{AngleUnit, Pose, Pose5, Pose5Convention};
use serde::{Deserialize, Serialize};

use crate::terrain::{HEIGHT, World};

/// Eye height above the feet, as in Minecraft.
pub const EYE_HEIGHT: f64 = 1.62;
/// Half the player's width: the collision box is 0.6 × 1.8 × 0.6.
pub const HALF_WIDTH: f64 = 0.3;
pub use motion::{Action, MotionModel, WALK_SPEED};
/// The path follower's largest yaw change per step, degrees.
pub const MAX_TURN_DEG: f64 = 12.0;

/// Where the player stands and looks. `feet` is the centre of the bottom of
/// the collision box; yaw and pitch follow Minecraft (degrees, yaw 0 faces
/// +z, 90° faces −x, positive pitch looks down).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PlayerState {
    pub feet: [f64; 3],
    pub yaw_deg: f64,
    pub pitch_deg: f64,
}

impl PlayerState {
    /// Standing at the centre of cell `(x, y, z)` (feet on the block below).
    pub fn at_cell(cell: [i32; 3], yaw_deg: f64) -> Self {
        PlayerState { feet: [cell[0] as f64 + 0.5, cell[1] as f64, cell[2] as f64 + 0.5], yaw_deg, pitch_deg: 0.0 }
    }

    /// The camera's 5-D pose (eye position) in Minecraft's convention, degrees.
    pub fn pose5(&self) -> Pose5 {
        Pose5 { x: self.feet[0], y: self.feet[1] + EYE_HEIGHT, z: self.feet[2], pitch: self.pitch_deg, yaw: self.yaw_deg }
    }

    /// The camera pose (OpenCV camera-to-world).
    pub fn camera(&self) -> Pose {
        Pose::from_pose5(&self.pose5(), Pose5Convention::Minecraft, AngleUnit::Degrees)
            .expect("player angles are finite by construction")
    }

    /// The cell the feet are in.
    pub fn cell(&self) -> [i32; 3] {
        [self.feet[0].floor() as i32, self.feet[1].round() as i32, self.feet[2].floor() as i32]
    }
}

/// The synthetic world's physics as a [`MotionModel`]: [`step`] in `world`.
#[derive(Clone, Copy)]
pub struct Physics<'a> {
    pub world: &'a World,
}

impl MotionModel for Physics<'_> {
    type State = PlayerState;

    fn step(&self, state: &PlayerState, action: &Action) -> PlayerState {
        step(self.world, state, action)
    }

    fn camera(&self, state: &PlayerState) -> Pose {
        state.camera()
    }
}

/// The motion model: the state after `action` from `state`. Kinematic (no
/// momentum): the camera turns, then the player moves `WALK_SPEED` along the
/// pressed keys, sliding along walls axis by axis; with `jump` held it climbs
/// a one-block step it walks into; it drops onto whatever is below.
pub fn step(world: &World, state: &PlayerState, action: &Action) -> PlayerState {
    let mut next = *state;
    next.yaw_deg = wrap_deg(state.yaw_deg + action.yaw_deg);
    next.pitch_deg = (state.pitch_deg + action.pitch_deg).clamp(-90.0, 90.0);
    let yaw = next.yaw_deg.to_radians();
    let forward = DVec3::new(-yaw.sin(), 0.0, yaw.cos());
    let right = DVec3::new(-yaw.cos(), 0.0, -yaw.sin());
    let axis = |on: bool, off: bool| f64::from(on as u8) - f64::from(off as u8);
    let wish = forward * axis(action.forward, action.back) + right * axis(action.right, action.left);
    if wish.length_squared() > 0.0 {
        let delta = wish.normalize() * WALK_SPEED;
        for (a, d) in [(0usize, delta.x), (2usize, delta.z)] {
            let mut moved = next.feet;
            moved[a] += d;
            if box_is_free(world, moved) {
                next.feet = moved;
            } else if action.jump {
                moved[1] += 1.0;
                if box_is_free(world, moved) && box_is_free(world, [next.feet[0], next.feet[1] + 1.0, next.feet[2]]) {
                    next.feet = moved;
                }
            }
        }
    }
    // Gravity, resolved at once: fall while nothing is under the box.
    while next.feet[1] > 0.0 && box_is_free(world, [next.feet[0], next.feet[1] - 1.0, next.feet[2]]) {
        next.feet[1] -= 1.0;
    }
    next
}

/// Whether the 0.6 × 1.8 × 0.6 box standing at `feet` touches no solid
/// block (feet heights are whole numbers, so it spans two cells in y).
pub fn box_is_free(world: &World, feet: [f64; 3]) -> bool {
    let y0 = feet[1].round() as i32;
    let (x0, x1) = ((feet[0] - HALF_WIDTH).floor() as i32, (feet[0] + HALF_WIDTH).floor() as i32);
    let (z0, z1) = ((feet[2] - HALF_WIDTH).floor() as i32, (feet[2] + HALF_WIDTH).floor() as i32);
    if x0 < 0 || z0 < 0 || x1 >= world.size() || z1 >= world.size() || y0 < 0 || y0 + 1 >= HEIGHT {
        return false;
    }
    for z in z0..=z1 {
        for x in x0..=x1 {
            if world.get(x, y0, z).is_solid() || world.get(x, y0 + 1, z).is_solid() {
                return false;
            }
        }
    }
    true
}

/// Whether a player can stand in cell `(x, y, z)`: two free cells on a
/// standable block.
pub fn standable(world: &World, x: i32, y: i32, z: i32) -> bool {
    y >= 1
        && y + 1 < HEIGHT
        && x >= 1
        && z >= 1
        && x + 1 < world.size()
        && z + 1 < world.size()
        && !world.get(x, y, z).is_solid()
        && !world.get(x, y + 1, z).is_solid()
        && world.get(x, y - 1, z).is_standable()
}

/// The standable surface cell nearest the world's centre (optionally in
/// `biome`), searching outward ring by ring.
pub fn spawn_point(world: &World, biome: Option<crate::terrain::Biome>) -> Option<[i32; 3]> {
    let c = world.size() / 2;
    for r in 0..c - 1 {
        for dz in -r..=r {
            for dx in -r..=r {
                if dx.abs() != r && dz.abs() != r {
                    continue;
                }
                let (x, z) = (c + dx, c + dz);
                if biome.is_some_and(|b| world.biome(x, z) != b) {
                    continue;
                }
                if let Some(y) = world.top(x, z).map(|y| y + 1)
                    && standable(world, x, y, z)
                {
                    return Some([x, y, z]);
                }
            }
        }
    }
    None
}

/// A* over standable cells with 8-neighbour moves: up one block (a jump),
/// level, or down one; diagonals only where both sides are open.
/// Returns the cells from `start` to `goal` inclusive, or `None` if the goal
/// is unreachable within `max_expansions`.
pub fn find_path(world: &World, start: [i32; 3], goal: [i32; 3], max_expansions: usize) -> Option<Vec<[i32; 3]>> {
    #[derive(PartialEq)]
    struct Open(f64, [i32; 3]);
    impl Eq for Open {}
    impl Ord for Open {
        fn cmp(&self, other: &Self) -> Ordering {
            other.0.total_cmp(&self.0).then_with(|| other.1.cmp(&self.1))
        }
    }
    impl PartialOrd for Open {
        fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
            Some(self.cmp(other))
        }
    }
    let heuristic = |c: [i32; 3]| (((c[0] - goal[0]).pow(2) + (c[2] - goal[2]).pow(2)) as f64).sqrt();
    let mut came_from: HashMap<[i32; 3], [i32; 3]> = HashMap::new();
    let mut cost: HashMap<[i32; 3], f64> = HashMap::from([(start, 0.0)]);
    let mut open = BinaryHeap::from([Open(heuristic(start), start)]);
    let mut expansions = 0;
    while let Some(Open(_, cell)) = open.pop() {
        if cell == goal {
            let mut path = vec![cell];
            let mut c = cell;
            while let Some(&p) = came_from.get(&c) {
                path.push(p);
                c = p;
            }
            path.reverse();
            return Some(path);
        }
        expansions += 1;
        if expansions > max_expansions {
            return None;
        }
        let here = cost[&cell];
        for (next, step_cost) in neighbours(world, cell) {
            let c = here + step_cost;
            if cost.get(&next).is_none_or(|&old| c < old) {
                cost.insert(next, c);
                came_from.insert(next, cell);
                open.push(Open(c + heuristic(next), next));
            }
        }
    }
    None
}

fn neighbours(world: &World, [x, y, z]: [i32; 3]) -> Vec<([i32; 3], f64)> {
    let mut out = Vec::with_capacity(8);
    let level = |dx: i32, dz: i32| standable(world, x + dx, y, z + dz);
    for (dx, dz) in [(1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (1, -1), (-1, 1), (-1, -1)] {
        let diagonal = dx != 0 && dz != 0;
        if diagonal {
            // Only level diagonal moves between two open sides: no corner cutting.
            if level(dx, dz) && level(dx, 0) && level(0, dz) {
                out.push(([x + dx, y, z + dz], std::f64::consts::SQRT_2));
            }
            continue;
        }
        let (nx, nz) = (x + dx, z + dz);
        if standable(world, nx, y, nz) {
            out.push(([nx, y, nz], 1.0));
        } else if standable(world, nx, y + 1, nz) && !world.get(x, y + 2, z).is_solid() {
            out.push(([nx, y + 1, nz], 1.5));
        } else if standable(world, nx, y - 1, nz) && !world.get(nx, y + 1, nz).is_solid() {
            // Down one block. Deeper drops are left out so that every move
            // can be undone: the way back is never longer than the way out.
            out.push(([nx, y - 1, nz], 1.2));
        }
    }
    out
}

/// Turns a path of cells into actions: turn toward the next waypoint at up to
/// `MAX_TURN_DEG` per step, walk forward once roughly facing it, jump when
/// the next cell is higher.
pub struct PathFollower {
    path: Vec<[i32; 3]>,
    next: usize,
}

impl PathFollower {
    pub fn new(path: Vec<[i32; 3]>) -> Self {
        PathFollower { path, next: 1 }
    }

    /// Waypoints not yet reached: the progress measure for stuck detection.
    pub fn remaining(&self) -> usize {
        self.path.len().saturating_sub(self.next)
    }

    /// The action for this step, or `None` once the last cell is reached.
    pub fn action(&mut self, state: &PlayerState) -> Option<Action> {
        while let Some(&target) = self.path.get(self.next) {
            let (dx, dz) = (target[0] as f64 + 0.5 - state.feet[0], target[2] as f64 + 0.5 - state.feet[2]);
            let close = if self.next + 1 == self.path.len() { 0.15 } else { 0.45 };
            if dx.hypot(dz) < close && (state.feet[1] - target[1] as f64).abs() < 0.5 {
                self.next += 1;
                continue;
            }
            let desired = (-dx).atan2(dz).to_degrees();
            let error = wrap_deg(desired - state.yaw_deg);
            let turn = error.clamp(-MAX_TURN_DEG, MAX_TURN_DEG);
            let facing = (error - turn).abs() < 40.0;
            return Some(Action {
                forward: facing,
                jump: target[1] as f64 > state.feet[1] + 0.5,
                yaw_deg: turn,
                pitch_deg: -state.pitch_deg.clamp(-MAX_TURN_DEG, MAX_TURN_DEG),
                ..Action::default()
            });
        }
        None
    }
}

/// Wraps an angle in degrees into (−180, 180].
pub fn wrap_deg(a: f64) -> f64 {
    let w = (a + 180.0).rem_euclid(360.0) - 180.0;
    if w <= -180.0 { w + 360.0 } else { w }
}

#[cfg(test)]
mod tests {
    use motion::Kinematic;

    /// On open flat ground the world's physics is pure kinematics, so the
    /// kinematic model must land on the same camera pose.
    #[test]
    fn kinematic_model_matches_the_world_on_flat_ground() {
        let world = World::flat(64, 10);
        let physics = Physics { world: &world };
        let mut player = PlayerState { feet: [32.5, 11.0, 32.5], yaw_deg: 30.0, pitch_deg: 10.0 };
        let mut pose = player.camera();
        let actions = [
            Action { forward: true, ..Action::default() },
            Action { forward: true, yaw_deg: 12.0, ..Action::default() },
            Action { left: true, pitch_deg: -5.0, ..Action::default() },
            Action { back: true, right: true, yaw_deg: -40.0, ..Action::default() },
        ];
        for a in actions.iter().cycle().take(20) {
            player = physics.step(&player, a);
            pose = Kinematic.step(&pose, a);
            let want = physics.camera(&player);
            assert!((pose.position() - want.position()).length() < 1e-9, "{:?} vs {:?}", pose.position(), want.position());
            assert!(pose.rotation().abs_diff_eq(want.rotation(), 1e-9), "{:?} vs {:?}", pose.rotation(), want.rotation());
        }
    }

    use super::*;

    fn walk(world: &World, from: PlayerState, action: Action, steps: usize) -> PlayerState {
        (0..steps).fold(from, |s, _| step(world, &s, &action))
    }

    #[test]
    fn forward_walks_at_walk_speed_along_yaw() {
        let world = World::generate_sized(3, 64);
        // Find a flat, open run along +z to walk on.
        for x in 8..56 {
            for z in 8..40 {
                let Some(y) = world.top(x, z).map(|y| y + 1) else { continue };
                if (0..8).all(|d| standable(&world, x, y, z + d)) {
                    let s = PlayerState::at_cell([x, y, z], 0.0);
                    let after = walk(&world, s, Action { forward: true, ..Action::default() }, 10);
                    assert!((after.feet[2] - s.feet[2] - 10.0 * WALK_SPEED).abs() < 1e-9);
                    assert_eq!(after.feet[0], s.feet[0]);
                    return;
                }
            }
        }
        panic!("no flat run found");
    }

    #[test]
    fn wrap_deg_range() {
        for a in [-540.0, -180.0, -179.0, 0.0, 180.0, 181.0, 725.0] {
            let w = wrap_deg(a);
            assert!(w > -180.0 && w <= 180.0, "{a} -> {w}");
            assert!(((a - w) / 360.0 - ((a - w) / 360.0).round()).abs() < 1e-12);
        }
    }
}
