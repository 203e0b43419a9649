//! The reprojection reference against the world renderer: warping a
//! rendered frame into a nearby pose must look more like the frame rendered
//! there than the unwarped frame does. This fails if a pose, pixel or depth
//! convention disagrees between the renderer and `eval::reproject`.

use eval::metrics::psnr;
use eval::reproject::reproject;
use memory::{AngleUnit, Pose, Pose5, Pose5Convention};
use world::suite::{default_intrinsics, depth_to_mm};
use world::{RenderSettings, World, render};

fn pose(x: f64, z: f64, yaw: f64, pitch: f64, eye: f64) -> Pose {
    Pose::from_pose5(&Pose5 { x, y: eye, z, pitch, yaw }, Pose5Convention::Minecraft, AngleUnit::Degrees).unwrap()
}

#[test]
fn warping_beats_copying_for_steps_and_turns() {
    let world = World::generate(11);
    let k = default_intrinsics(96, 96).unwrap();
    let settings = RenderSettings::default();
    let spawn = world::agent::spawn_point(&world, None).expect("a place to stand");
    let eye = spawn[1] as f64 + 1.62;
    let (x, z) = (spawn[0] as f64 + 0.5, spawn[2] as f64 + 0.5);
    let mut margins = Vec::new();
    for yaw in [0.0, 90.0, 200.0] {
        let src = pose(x, z, yaw, 15.0, eye);
        let a = render(&world, &src, &k, &settings);
        let depth: Vec<u16> = a.depth.iter().map(|&d| if d.is_finite() { depth_to_mm(d) } else { 0 }).collect();
        let (s, c) = (yaw.to_radians().sin(), yaw.to_radians().cos());
        // A step forward (yaw 0 faces +z), a step sideways, a 10° turn.
        for dst in [pose(x - 0.4 * s, z + 0.4 * c, yaw, 15.0, eye), pose(x + 0.3 * c, z + 0.3 * s, yaw, 15.0, eye), pose(x, z, yaw + 10.0, 15.0, eye)] {
            let b = render(&world, &dst, &k, &settings);
            let (warped, hit) = reproject(&a.rgb, &depth, &k, &src, &dst);
            let (copy, warp) = (psnr(&a.rgb, &b.rgb), psnr(&warped, &b.rgb));
            assert!(hit > 0.2, "yaw {yaw}: only {hit:.2} of the view was warped");
            margins.push(warp - copy);
        }
    }
    let worst = margins.iter().copied().fold(f64::INFINITY, f64::min);
    assert!(worst > 1.0, "warping gained only {worst:.2} dB over copying somewhere: {margins:?}");
}
