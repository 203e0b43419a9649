//! Frames per second of the voxel renderer (`worldpack bench render`).

use std::time::Instant;

use anyhow::{Context, Result};
use world::World;
use world::render::{RenderSettings, render};

/// Frames per second of the renderer on one core at several sizes.
pub fn run(frames: usize, seed: u64) -> Result<()> {
    let world = World::generate(seed);
    let spawn = world::agent::spawn_point(&world, None).context("no spawn point")?;
    println!("renderer, one core, world {seed}, {frames} frames per size turning on the spot at the spawn point");
    println!("{:>9} | {:>10} {:>10} | {:>8}", "size", "ms/frame", "frames/s", "sky %");
    for (w, h) in [(64, 64), (128, 128), (224, 224), (640, 360)] {
        let k = world::suite::default_intrinsics(w, h).map_err(anyhow::Error::msg)?;
        let settings = RenderSettings::default();
        let mut state = world::PlayerState::at_cell(spawn, 0.0);
        let (mut sky, start) = (0usize, Instant::now());
        for i in 0..frames {
            state.yaw_deg = (i * 360 / frames) as f64;
            let frame = render(&world, &state.camera(), &k, &settings);
            sky += frame.depth.iter().filter(|d| !d.is_finite()).count();
        }
        let ms = start.elapsed().as_secs_f64() * 1000.0 / frames as f64;
        println!("{:>9} | {:>10.2} {:>10.1} | {:>7.1}%", format!("{w}x{h}"), ms, 1000.0 / ms, 100.0 * sky as f64 / (frames * (w * h) as usize) as f64);
    }
    Ok(())
}
