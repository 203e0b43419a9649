//! LoopNav's protocol on the synthetic world: look around at A, walk to goals
//! picked at ≥ 0.8·range inside a ±range square, come back to A. The frame
//! where the way back starts is the *returning point*: frames before it are
//! the context (exploration), frames from it on are evaluated.

use serde::{Deserialize, Serialize};

use crate::agent::{Action, MAX_TURN_DEG, PathFollower, PlayerState, find_path, standable, step, wrap_deg};
use crate::noise::{Rng, hash};
use crate::terrain::World;

/// The kinds of trajectories. `Aba` and `Abca` are LoopNav's evaluation
/// tasks; `Tour` (A → several goals → A, looking around on the way) and
/// `Wander` (goal to goal, glancing up and down, no return) vary the
/// training data.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, PartialOrd, Ord)]
#[serde(rename_all = "snake_case")]
pub enum Task {
    Aba,
    Abca,
    Tour,
    Wander,
    /// The occluder scene ([`generate_occluder`]): memory behind a wall.
    Occluder,
}

impl Task {
    pub fn name(self) -> &'static str {
        match self {
            Task::Aba => "aba",
            Task::Abca => "abca",
            Task::Tour => "tour",
            Task::Wander => "wander",
            Task::Occluder => "occluder",
        }
    }

    /// Outbound goals before the way back (none back for `Wander`).
    fn goals(self, rng: &mut Rng) -> usize {
        match self {
            Task::Aba => 1,
            Task::Abca => 2,
            Task::Tour => rng.range(3, 6) as usize,
            Task::Wander => rng.range(3, 7) as usize,
            Task::Occluder => 0,
        }
    }
}

/// What each frame was doing.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[repr(u8)]
pub enum Phase {
    /// Turning on the spot at A (yaw 180°, 90°, 0°, −90°, 180°).
    LookAround = 0,
    /// Walking out to the goals: the context of the evaluation.
    Outbound = 1,
    /// The way back to A, from the returning point on.
    Return = 2,
}

/// Everything that fixes one trajectory.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrajectorySpec {
    pub task: Task,
    /// Navigation range in blocks.
    pub range: i32,
    pub world_seed: u64,
    /// Seeds the choices of start and goals.
    pub seed: u64,
}

/// One recorded step: the action taken (zero for frame 0) and the state it
/// led to.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Step {
    pub action: Action,
    pub state: PlayerState,
    pub phase: Phase,
}

#[derive(Clone, Debug)]
pub struct Trajectory {
    pub spec: TrajectorySpec,
    pub steps: Vec<Step>,
    /// Index of the first frame of the way back (`steps.len()` for `Wander`).
    pub returning_point: usize,
    /// A, then each goal, as cells (feet).
    pub waypoints: Vec<[i32; 3]>,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum TrajectoryError {
    #[error("no standable start near the world centre")]
    NoStart,
    #[error("no reachable goal for leg {leg} after {tries} tries")]
    NoGoal { leg: usize, tries: usize },
    #[error("the agent got stuck on leg {leg} at step {step}")]
    Stuck { leg: usize, step: usize },
    #[error("the way back takes {0} frames, more than LoopNav's longest ({LOOPNAV_MAX_RETURN})")]
    ReturnTooLong(usize),
    #[error("the trajectory exceeds {0} steps")]
    TooLong(usize),
}

/// The yaw targets of LoopNav's look-around (mineflayer 0, π/2, π, 3π/2, 0,
/// in Minecraft's convention).
pub const LOOK_AROUND_YAWS: [f64; 5] = [180.0, 90.0, 0.0, -90.0, 180.0];
/// LoopNav's longest evaluated rollout, in frames.
pub const LOOPNAV_MAX_RETURN: usize = 630;
/// A* effort per leg.
const MAX_EXPANSIONS: usize = 400_000;
/// A leg's path may be at most this many times the straight distance (+10).
const DETOUR: f64 = 1.8;
/// Goal draws per leg before giving up.
const GOAL_TRIES: usize = 60;

/// Walks one trajectory in `world` (which must be `spec.world_seed`'s).
pub fn generate(world: &World, spec: &TrajectorySpec, max_steps: usize) -> Result<Trajectory, TrajectoryError> {
    let mut rng = Rng::new(hash(spec.seed, &[spec.task as i64, spec.range as i64]));
    let a = pick_start(world, &mut rng).ok_or(TrajectoryError::NoStart)?;
    let mut rec = Recorder { world, steps: Vec::new(), max_steps };
    let mut state = PlayerState::at_cell(a, LOOK_AROUND_YAWS[0]);
    rec.steps.push(Step { action: Action::default(), state, phase: Phase::LookAround });
    for yaw in LOOK_AROUND_YAWS {
        state = rec.turn_to(state, yaw, 0.0, Phase::LookAround)?;
    }
    let mut waypoints = vec![a];
    let goals = spec.task.goals(&mut rng);
    for leg in 0..goals {
        let from = *waypoints.last().unwrap();
        let last_leg = leg + 1 == goals && spec.task != Task::Wander;
        let (goal, path) = (0..GOAL_TRIES)
            .find_map(|_| {
                let goal = pick_goal(world, from, spec.range, &mut rng)?;
                // LoopNav draws C around B only; we also keep the way back
                // from the last goal at least half a range long.
                if last_leg && horizontal_distance(goal, a) < 0.5 * spec.range as f64 {
                    return None;
                }
                let path = find_path(world, from, goal, MAX_EXPANSIONS)?;
                // Goals behind cliffs or water would need long detours; draw again.
                (path.len() as f64 <= DETOUR * horizontal_distance(from, goal) + 10.0).then_some((goal, path))
            })
            .ok_or(TrajectoryError::NoGoal { leg, tries: GOAL_TRIES })?;
        state = rec.follow(state, path, Phase::Outbound, leg, spec.task, &mut rng)?;
        waypoints.push(goal);
        if spec.task == Task::Tour && rng.chance(0.5) {
            state = rec.look_around_here(state)?;
        }
    }
    let returning_point = rec.steps.len();
    if spec.task != Task::Wander {
        let from = *waypoints.last().unwrap();
        let path = find_path(world, from, a, MAX_EXPANSIONS)
            .filter(|p| p.len() as f64 <= DETOUR * horizontal_distance(from, a) + 10.0)
            .ok_or(TrajectoryError::NoGoal { leg: goals, tries: 1 })?;
        rec.follow(state, path, Phase::Return, goals, spec.task, &mut rng)?;
        let back = rec.steps.len() - returning_point;
        if matches!(spec.task, Task::Aba | Task::Abca) && back > LOOPNAV_MAX_RETURN {
            return Err(TrajectoryError::ReturnTooLong(back));
        }
    }
    Ok(Trajectory { spec: *spec, steps: rec.steps, returning_point, waypoints })
}

/// The occluder scene: a wall of stone bricks `range` blocks long, two
/// blocks to the side of A, parallel to A's view (yaw 0, +z). The agent first
/// looks down A's side, then walks around the wall's near end and along the
/// far side looking the same way, comes back to A and looks down A's side
/// again; the way back (the evaluated leg) then walks down A's side. Seen from
/// that leg, the far side's frames stand a few blocks away and look the same
/// way, so their frusta share much of each target's volume, but the wall hid
/// A's side from them; A's own frames saw it from further back.
/// Builds the wall into `world`.
pub fn generate_occluder(world: &mut World, spec: &TrajectorySpec, max_steps: usize) -> Result<Trajectory, TrajectoryError> {
    let mut rng = Rng::new(hash(spec.seed, &[spec.task as i64, spec.range as i64]));
    let len = spec.range.max(4);
    // Only on nearly flat ground does a wall at A's height stand on it without gaps.
    let flat = |a: [i32; 3]| (a[2] - 2..=a[2] + len + 2).all(|z| (a[0] - 1..=a[0] + 5).all(|x| world.top(x, z).is_some_and(|y| (y + 1 - a[1]).abs() <= 1)));
    let a = (0..40).find_map(|_| pick_start(world, &mut rng).filter(|&a| flat(a))).ok_or(TrajectoryError::NoStart)?;
    for z in a[2] - 1..=a[2] + len + 1 {
        for y in a[1] - 2..=a[1] + 3 {
            world.set(a[0] + 2, y, z, crate::blocks::Block::StoneBricks);
        }
    }
    let world = &*world;
    let cell = |x: i32, z: i32| -> Result<[i32; 3], TrajectoryError> {
        let y = world.top(x, z).ok_or(TrajectoryError::NoStart)? + 1;
        if standable(world, x, y, z) { Ok([x, y, z]) } else { Err(TrajectoryError::NoGoal { leg: 0, tries: 1 }) }
    };
    let (far_near, far_end, a_end) = (cell(a[0] + 4, a[2])?, cell(a[0] + 4, a[2] + len)?, cell(a[0], a[2] + len)?);
    let mut rec = Recorder { world, steps: Vec::new(), max_steps };
    let mut state = PlayerState::at_cell(a, LOOK_AROUND_YAWS[0]);
    rec.steps.push(Step { action: Action::default(), state, phase: Phase::LookAround });
    state = rec.turn_to(state, 0.0, 0.0, Phase::LookAround)?;
    let legs = [(far_near, true), (far_end, false), (a, true)];
    for (leg, (goal, turn_after)) in legs.into_iter().enumerate() {
        let from = state.cell();
        let path = find_path(world, from, goal, MAX_EXPANSIONS).ok_or(TrajectoryError::NoGoal { leg, tries: 1 })?;
        state = rec.follow(state, path, Phase::Outbound, leg, spec.task, &mut rng)?;
        if turn_after {
            state = rec.turn_to(state, 0.0, 0.0, Phase::Outbound)?;
        }
    }
    let returning_point = rec.steps.len();
    let path = find_path(world, state.cell(), a_end, MAX_EXPANSIONS).ok_or(TrajectoryError::NoGoal { leg: 3, tries: 1 })?;
    rec.follow(state, path, Phase::Return, 3, spec.task, &mut rng)?;
    Ok(Trajectory { spec: *spec, steps: rec.steps, returning_point, waypoints: vec![a, far_near, far_end, a_end] })
}

fn horizontal_distance(p: [i32; 3], q: [i32; 3]) -> f64 {
    (((p[0] - q[0]).pow(2) + (p[2] - q[2]).pow(2)) as f64).sqrt()
}

/// A standable surface cell near the world's centre, on dry land.
fn pick_start(world: &World, rng: &mut Rng) -> Option<[i32; 3]> {
    let c = world.size() / 2;
    (0..200).find_map(|_| {
        let (x, z) = (c + rng.range(-24, 25) as i32, c + rng.range(-24, 25) as i32);
        let y = world.top(x, z)? + 1;
        standable(world, x, y, z).then_some([x, y, z])
    })
}

/// LoopNav's goal rule: an offset in the ±range square at least 0.8·range
/// away, landing on a standable cell within 10 blocks of the current height.
fn pick_goal(world: &World, from: [i32; 3], range: i32, rng: &mut Rng) -> Option<[i32; 3]> {
    let (dx, dz) = (rng.range(-range as i64, range as i64) as i32, rng.range(-range as i64, range as i64) as i32);
    let min = 0.8 * range as f64;
    if ((dx * dx + dz * dz) as f64) < min * min {
        return None;
    }
    let (x, z) = (from[0] + dx, from[2] + dz);
    let y = world.top(x, z)? + 1;
    ((y - from[1]).abs() <= 10 && standable(world, x, y, z)).then_some([x, y, z])
}

struct Recorder<'w> {
    world: &'w World,
    steps: Vec<Step>,
    max_steps: usize,
}

impl Recorder<'_> {
    fn push(&mut self, state: &PlayerState, action: Action, phase: Phase) -> Result<PlayerState, TrajectoryError> {
        if self.steps.len() >= self.max_steps {
            return Err(TrajectoryError::TooLong(self.max_steps));
        }
        let next = step(self.world, state, &action);
        self.steps.push(Step { action, state: next, phase });
        Ok(next)
    }

    /// Turns on the spot toward `(yaw, pitch)` at the follower's turn rate.
    fn turn_to(&mut self, mut s: PlayerState, yaw: f64, pitch: f64, phase: Phase) -> Result<PlayerState, TrajectoryError> {
        loop {
            let (dy, dp) = (wrap_deg(yaw - s.yaw_deg), pitch - s.pitch_deg);
            if dy.abs() < 1e-9 && dp.abs() < 1e-9 {
                return Ok(s);
            }
            let turn = Action::turn(dy.clamp(-MAX_TURN_DEG, MAX_TURN_DEG), dp.clamp(-MAX_TURN_DEG, MAX_TURN_DEG));
            s = self.push(&s, turn, phase)?;
        }
    }

    fn look_around_here(&mut self, mut s: PlayerState) -> Result<PlayerState, TrajectoryError> {
        let start = s.yaw_deg;
        for quarter in 1..=4 {
            s = self.turn_to(s, wrap_deg(start + 90.0 * quarter as f64), 0.0, Phase::Outbound)?;
        }
        Ok(s)
    }

    fn follow(
        &mut self,
        mut s: PlayerState,
        path: Vec<[i32; 3]>,
        phase: Phase,
        leg: usize,
        task: Task,
        rng: &mut Rng,
    ) -> Result<PlayerState, TrajectoryError> {
        let mut follower = PathFollower::new(path);
        let (mut best, mut since_progress) = (usize::MAX, 0);
        while let Some(mut action) = follower.action(&s) {
            if task == Task::Wander && rng.chance(0.03) {
                // Glance up or down: the follower levels the camera again.
                action.pitch_deg = rng.range(-25, 26) as f64;
            }
            s = self.push(&s, action, phase)?;
            let remaining = follower.remaining();
            if remaining < best {
                (best, since_progress) = (remaining, 0);
            } else {
                since_progress += 1;
                if since_progress > 80 {
                    return Err(TrajectoryError::Stuck { leg, step: self.steps.len() });
                }
            }
        }
        Ok(s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_occluder_scene_puts_a_wall_between_the_way_back_and_the_far_side() {
        let spec = TrajectorySpec { task: Task::Occluder, range: 8, world_seed: 0, seed: 5 };
        let (world, t) = (0..20u64)
            .find_map(|seed| {
                let mut world = World::generate(seed);
                let t = generate_occluder(&mut world, &TrajectorySpec { world_seed: seed, ..spec }, 1200).ok()?;
                Some((world, t))
            })
            .expect("some world holds the scene");
        let a = t.waypoints[0];
        let wall_x = a[0] + 2;
        for z in a[2]..=a[2] + 8 {
            assert_eq!(world.get(wall_x, a[1] + 1, z), crate::blocks::Block::StoneBricks, "the wall at eye height, z {z}");
        }
        let x = |s: &Step| s.state.feet[0];
        assert!(t.steps[t.returning_point..].iter().all(|s| x(s) < wall_x as f64), "the way back stays on A's side");
        assert!(t.steps[..t.returning_point].iter().any(|s| x(s) > wall_x as f64 + 1.0), "the exploration went round to the far side");
        let last = t.steps.last().unwrap().state;
        assert!((last.feet[2] - (a[2] + 8) as f64).abs() < 1.0, "the way back ends at the wall's far end");
    }

    #[test]
    fn aba_returns_to_a_and_revisits_its_start() {
        let world = World::generate(11);
        let spec = TrajectorySpec { task: Task::Aba, range: 15, world_seed: 11, seed: 4 };
        let t = generate(&world, &spec, 5000).expect("trajectory");
        let a = t.waypoints[0];
        let last = t.steps.last().unwrap().state;
        assert!((last.feet[0] - (a[0] as f64 + 0.5)).hypot(last.feet[2] - (a[2] as f64 + 0.5)) < 0.2);
        let b = t.waypoints[1];
        let d = (((b[0] - a[0]).pow(2) + (b[2] - a[2]).pow(2)) as f64).sqrt();
        assert!(d >= 12.0 && (b[0] - a[0]).abs() <= 15 && (b[2] - a[2]).abs() <= 15, "B at {d}");
        assert!(t.returning_point > 0 && t.returning_point < t.steps.len());
        assert!(t.steps[..t.returning_point].iter().all(|s| s.phase != Phase::Return));
        assert!(t.steps[t.returning_point..].iter().all(|s| s.phase == Phase::Return));
    }
}
