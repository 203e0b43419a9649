//! The world's contracts on scenes with known geometry: the player's
//! physics, the path finder, and the renderer's depth.

use memory::{AngleUnit, Pose, Pose5, Pose5Convention};
use world::agent::{Action, PathFollower, PlayerState, WALK_SPEED, box_is_free, find_path, step};
use world::blocks::Block;
use world::render::{RenderSettings, render};
use world::suite::default_intrinsics;
use world::World;

const GROUND: i32 = 20;

/// Flat grass at y = 20 (players stand at feet y = 21) with a stone wall at
/// z = 40 from x = 10 to 50, two blocks high, and a one-block step at z = 30
/// for x in 60..64.
fn scene() -> World {
    let mut w = World::flat(96, GROUND);
    for x in 10..=50 {
        for y in GROUND + 1..=GROUND + 2 {
            w.set(x, y, 40, Block::StoneBricks);
        }
    }
    for x in 60..64 {
        for z in 30..34 {
            w.set(x, GROUND + 1, z, Block::Planks);
        }
    }
    w
}

fn forward(jump: bool) -> Action {
    Action { forward: true, jump, ..Action::default() }
}

fn walk(world: &World, mut s: PlayerState, a: Action, steps: usize) -> PlayerState {
    for _ in 0..steps {
        s = step(world, &s, &a);
    }
    s
}

#[test]
fn walls_stop_the_player_even_when_jumping() {
    let w = scene();
    // Facing +z (yaw 0) toward the two-high wall at z = 40.
    let start = PlayerState::at_cell([30, GROUND + 1, 35], 0.0);
    for jump in [false, true] {
        let end = walk(&w, start, forward(jump), 60);
        assert!(end.feet[2] + 0.3 <= 40.0 + 1e-9, "walked into the wall: z = {}", end.feet[2]);
        assert!(end.feet[2] > 39.0, "stopped early at z = {}", end.feet[2]);
        assert_eq!(end.feet[1], (GROUND + 1) as f64);
        assert!(box_is_free(&w, end.feet));
    }
}

#[test]
fn one_block_steps_need_a_jump_and_ledges_drop() {
    let w = scene();
    let start = PlayerState::at_cell([61, GROUND + 1, 26], 0.0);
    let blocked = walk(&w, start, forward(false), 30);
    assert_eq!(blocked.feet[1], (GROUND + 1) as f64, "climbed without jumping");
    assert!(blocked.feet[2] < 30.0);
    let climbed = walk(&w, start, forward(true), 30);
    assert!(climbed.feet[2] > 30.0 && climbed.feet[2] < 34.0, "z = {}", climbed.feet[2]);
    assert_eq!(climbed.feet[1], (GROUND + 2) as f64, "did not climb the step");
    // Walking on drops back down past the far edge.
    let down = walk(&w, climbed, forward(false), 30);
    assert!(down.feet[2] > 34.3);
    assert_eq!(down.feet[1], (GROUND + 1) as f64);
}

#[test]
fn strafing_and_turning_follow_minecraft_axes() {
    let w = World::flat(64, GROUND);
    let s = PlayerState::at_cell([32, GROUND + 1, 32], 90.0); // yaw 90° faces −x
    let f = step(&w, &s, &forward(false));
    assert!((f.feet[0] - (s.feet[0] - WALK_SPEED)).abs() < 1e-12 && (f.feet[2] - s.feet[2]).abs() < 1e-12);
    // Facing −x, the right hand points to −z (north).
    let r = step(&w, &s, &Action { right: true, ..Action::default() });
    assert!((r.feet[2] - (s.feet[2] - WALK_SPEED)).abs() < 1e-12);
    let t = step(&w, &s, &Action::turn(100.0, 120.0));
    assert_eq!((t.yaw_deg, t.pitch_deg), (-170.0, 90.0));
    // The camera's forward axis agrees with the walking direction.
    let cam = s.camera();
    assert!((cam.forward() - glam::DVec3::new(-1.0, 0.0, 0.0)).length() < 1e-12);
}

#[test]
fn paths_go_around_walls_and_the_follower_reaches_the_goal() {
    let w = scene();
    let (a, b) = ([30, GROUND + 1, 35], [30, GROUND + 1, 45]);
    let path = find_path(&w, a, b, 200_000).expect("a path around the wall");
    assert!(path.len() > 20, "path of {} cells cannot get round a 41-block wall", path.len());
    for c in &path {
        assert!(w.get(c[0], c[1], c[2]) == Block::Air && w.get(c[0], c[1] + 1, c[2]) == Block::Air, "path through {c:?}");
    }
    let mut s = PlayerState::at_cell(a, 0.0);
    let mut follower = PathFollower::new(path);
    let mut steps = 0;
    while let Some(action) = follower.action(&s) {
        s = step(&w, &s, &action);
        steps += 1;
        assert!(steps < 2000, "follower did not arrive");
        assert!(box_is_free(&w, s.feet));
    }
    assert!((s.feet[0] - 30.5).hypot(s.feet[2] - 45.5) < 0.2, "ended at {:?}", s.feet);
}

#[test]
fn depth_is_camera_z_of_the_ground_plane() {
    let w = World::flat(128, GROUND);
    let k = default_intrinsics(48, 32).unwrap();
    let eye = GROUND as f64 + 1.0 + 1.62;
    let pose = Pose::from_pose5(&Pose5 { x: 64.3, y: eye, z: 64.7, pitch: 40.0, yaw: 25.0 }, Pose5Convention::Minecraft, AngleUnit::Degrees)
        .unwrap();
    let frame = render(&w, &pose, &k, &RenderSettings::default());
    let (r, c) = (pose.rotation(), pose.position());
    let mut checked = 0;
    for v in 0..k.height {
        for u in 0..k.width {
            let d = r * glam::DVec3::new((u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy, 1.0);
            // The grass top is the plane y = GROUND + 1.
            let t = (GROUND as f64 + 1.0 - c.y) / d.y;
            let got = frame.depth[(v * k.width + u) as usize];
            if d.y < 0.0 && t * d.length() < 40.0 {
                assert!((got as f64 - t).abs() < 1e-4 * t.max(1.0), "pixel ({u}, {v}): depth {got}, plane {t}");
                checked += 1;
            }
        }
    }
    assert!(checked > 500, "only {checked} ground pixels");
}

#[test]
fn rendering_is_deterministic_and_depends_on_the_seed() {
    let k = default_intrinsics(32, 32).unwrap();
    let frame = |seed| {
        let w = World::generate(seed);
        let spawn = world::agent::spawn_point(&w, None).unwrap();
        render(&w, &PlayerState::at_cell(spawn, 30.0).camera(), &k, &RenderSettings::default())
    };
    assert_eq!(frame(8), frame(8));
    assert_ne!(frame(8).rgb, frame(9).rgb);
}
