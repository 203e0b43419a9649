//! `worldpack sim`: the synthetic world from the command line — suites,
//! training data, single frames — and `worldpack bench render`.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use crate::cli::{bar, threads};
use memory::{AngleUnit, Intrinsics, Pose, Pose5, Pose5Convention};
use world::render::{RenderSettings, cast, render};
use world::suite::{self, Planned};
use world::{Biome, Task, World};
use clap::Subcommand;

/// `WxH`, e.g. `64x64`.
pub fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(|| format!("expected WxH such as 64x64, got {s:?}"))?;
    let parse = |v: &str, what: &str| {
        v.trim().parse::<u32>().ok().filter(|n| (8..=4096).contains(n)).ok_or_else(|| format!("{what} must be 8..=4096, got {v:?}"))
    };
    Ok((parse(w, "width")?, parse(h, "height")?))
}

/// `x,y,z,pitch,yaw` in Minecraft's convention (degrees, eye position).
pub fn parse_pose5(s: &str) -> Result<Pose5, String> {
    let v: Vec<f64> = s.split(',').map(|p| p.trim().parse::<f64>()).collect::<Result<_, _>>()
        .map_err(|_| format!("expected five numbers x,y,z,pitch,yaw, got {s:?}"))?;
    match v[..] {
        [x, y, z, ..] if [x, y, z].iter().any(|c| c.abs() > 1e6) => {
            Err(format!("x, y and z must lie within ±1e6 blocks (a world spans 384), got {s:?}"))
        }
        [x, y, z, pitch, yaw] if v.iter().all(|n| n.is_finite()) => Ok(Pose5 { x, y, z, pitch, yaw }),
        _ => Err(format!("expected five finite numbers x,y,z,pitch,yaw, got {s:?}")),
    }
}

pub fn parse_biome(s: &str) -> Result<Biome, String> {
    let all = [Biome::Plains, Biome::Forest, Biome::Desert, Biome::Snowy, Biome::Mountains, Biome::Badlands];
    all.into_iter()
        .find(|b| serde_json::to_value(b).ok().and_then(|v| v.as_str().map(|n| n == s)).unwrap_or(false))
        .ok_or_else(|| format!("unknown biome {s:?}; one of plains, forest, desert, snowy, mountains, badlands"))
}

pub fn parse_task(s: &str) -> Result<Task, String> {
    match s {
        "aba" => Ok(Task::Aba),
        "abca" => Ok(Task::Abca),
        _ => Err(format!("unknown task {s:?}; one of aba, abca")),
    }
}

fn intrinsics(size: (u32, u32)) -> Result<Intrinsics> {
    suite::default_intrinsics(size.0, size.1).map_err(|e| anyhow::anyhow!("--size: {e}"))
}

fn write_plan(out: &Path, kind: &str, seed: u64, plan: &[Planned], size: (u32, u32)) -> Result<()> {
    let k = intrinsics(size)?;
    let progress = bar(plan.len(), kind);
    let (index, frames) = suite::write_suite(out, kind, seed, plan, &k, &RenderSettings::default(), threads(), &|name| {
        progress.set_message(name.to_string());
        progress.inc(1);
    })
    .map_err(|e| anyhow::anyhow!(e))?;
    progress.finish();
    println!("wrote {} trajectories, {frames} frames at {}x{} -> {}", plan.len(), size.0, size.1, index.display());
    Ok(())
}

pub fn loopnav(out: &Path, per_cell: usize, seed: u64, size: (u32, u32), tasks: &[Task], ranges: &[i32]) -> Result<()> {
    if let Some(r) = ranges.iter().find(|r| !(1..=60).contains(*r)) {
        bail!("--ranges: each range must lie in 1..=60 blocks (the world holds ±60-block legs), got {r}");
    }
    write_plan(out, "loopnav", seed, &suite::loopnav_plan(seed, per_cell, tasks, ranges), size)
}

pub fn occluders(out: &Path, count: usize, range: i32, seed: u64, size: (u32, u32)) -> Result<()> {
    write_plan(out, "occluders", seed, &suite::occluder_plan(seed, count, range), size)
}

pub fn dataset(out: &Path, trajectories: usize, seed: u64, size: (u32, u32)) -> Result<()> {
    write_plan(out, "dataset", seed, &suite::dataset_plan(seed, trajectories), size)
}

/// One frame: `rgb.png`, `depth.png`, `depth.npy` (f32, inf = sky) and
/// `render.json` (pose, intrinsics, and the block face under `probe`).
pub fn render_one(out: &Path, seed: u64, pose: Option<Pose5>, biome: Option<Biome>, size: (u32, u32), probe: Option<(u32, u32)>) -> Result<()> {
    let world = World::generate(seed);
    let pose5 = match pose {
        Some(p) => p,
        None => {
            let cell = world::agent::spawn_point(&world, biome)
                .with_context(|| format!("--biome: world {seed} has no standable {biome:?} ground"))?;
            world::PlayerState::at_cell(cell, 0.0).pose5()
        }
    };
    let camera = Pose::from_pose5(&pose5, Pose5Convention::Minecraft, AngleUnit::Degrees).map_err(|e| anyhow::anyhow!("--pose: {e}"))?;
    let k = intrinsics(size)?;
    let settings = RenderSettings::default();
    let frame = render(&world, &camera, &k, &settings);
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    world::picture::write_png(&out.join("rgb.png"), k.width, k.height, &frame.rgb)?;
    let depth_rgb = world::picture::depth_to_rgb(&frame.depth, settings.fog_start as f32 * 2.0);
    world::picture::write_png(&out.join("depth.png"), k.width, k.height, &depth_rgb)?;
    world::npy::write(&out.join("depth.npy"), &[k.height as usize, k.width as usize], &frame.depth)?;
    let (u, v) = probe.unwrap_or((k.width / 2, k.height / 2));
    if u >= k.width || v >= k.height {
        bail!("--probe: pixel ({u}, {v}) lies outside the {}x{} image", k.width, k.height);
    }
    let probe_hit = face_under_pixel(&world, &camera, &k, &settings, u, v);
    let info = serde_json::json!({
        "world_seed": seed,
        "biome": world.biome(pose5.x.floor() as i32, pose5.z.floor() as i32),
        "pose5": pose5,
        "pose5_convention": "minecraft, degrees",
        "camera_to_world": camera.matrix_rows(),
        "intrinsics": k,
        "render": settings,
        "probe": probe_hit,
    });
    std::fs::write(out.join("render.json"), serde_json::to_string_pretty(&info)?)?;
    println!("wrote {}x{} frame of world {seed} at {:.2},{:.2},{:.2} (pitch {:.1}, yaw {:.1}) -> {}",
        k.width, k.height, pose5.x, pose5.y, pose5.z, pose5.pitch, pose5.yaw, out.display());
    Ok(())
}

/// The block face seen through pixel `(u, v)`: its cell, its four world
/// corners and where this crate's camera projects them (for checking
/// against OpenCV).
fn face_under_pixel(world: &World, camera: &Pose, k: &Intrinsics, settings: &RenderSettings, u: u32, v: u32) -> serde_json::Value {
    let dir = camera.rotation() * k.unproject(glam::DVec2::new(u as f64, v as f64), 1.0);
    let Some(hit) = cast(world, camera.position(), dir, settings.view_distance / dir.length()) else {
        return serde_json::json!({ "pixel": [u, v], "hit": false });
    };
    // The face plane is the cell boundary nearest the hit point along the
    // face's axis; its corners span the other two axes.
    let axis = match hit.face {
        world::blocks::Face::SideX => 0,
        world::blocks::Face::SideZ => 2,
        _ => 1,
    };
    let plane = hit.point.to_array()[axis].round();
    let (a, b) = match axis {
        0 => (1, 2),
        1 => (0, 2),
        _ => (0, 1),
    };
    let corners: Vec<[f64; 3]> = [(0, 0), (1, 0), (1, 1), (0, 1)]
        .iter()
        .map(|&(da, db)| {
            let mut c = [0.0; 3];
            c[axis] = plane;
            c[a] = (hit.cell[a] + da) as f64;
            c[b] = (hit.cell[b] + db) as f64;
            c
        })
        .collect();
    let projected: Vec<Option<[f64; 2]>> = corners
        .iter()
        .map(|c| k.project(camera.world_to_camera(glam::DVec3::from_array(*c))).map(|p| [p.x, p.y]))
        .collect();
    serde_json::json!({
        "pixel": [u, v],
        "hit": true,
        "cell": hit.cell,
        "block": format!("{:?}", hit.block),
        "face_axis": (["x", "y", "z"])[axis],
        "depth": hit.t,
        "corners_world": corners,
        "corners_pixels": projected,
    })
}

#[derive(Subcommand)]
pub enum Sim {
    /// Write the LoopNav evaluation suite: ABA and ABCA at ranges 5, 15, 30, 50 (test world seeds).
    Loopnav {
        #[arg(long)]
        out: PathBuf,
        /// Trajectories per (task, range); LoopNav uses 18.
        #[arg(long, default_value_t = 18, value_parser = clap::value_parser!(u32).range(1..=1000))]
        per_cell: u32,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Frame size WxH.
        #[arg(long, default_value = "64x64", value_parser = parse_size)]
        size: (u32, u32),
        /// Comma-separated tasks.
        #[arg(long, value_delimiter = ',', default_value = "aba,abca", value_parser = parse_task)]
        tasks: Vec<world::Task>,
        /// Comma-separated navigation ranges in blocks.
        #[arg(long, value_delimiter = ',', default_value = "5,15,30,50")]
        ranges: Vec<i32>,
    },
    /// Write the occluder suite: a wall beside the way back hides it from the frames that stand closest to it (test world seeds; docs/geometry.md).
    Occluders {
        #[arg(long)]
        out: PathBuf,
        /// Scenes (one trajectory each).
        #[arg(long, default_value_t = 12, value_parser = clap::value_parser!(u32).range(1..=1000))]
        count: u32,
        /// Length of the wall and of the way back, in blocks.
        #[arg(long, default_value_t = 12, value_parser = clap::value_parser!(i32).range(4..=40))]
        range: i32,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Frame size WxH.
        #[arg(long, default_value = "64x64", value_parser = parse_size)]
        size: (u32, u32),
    },
    /// Write training data: loop-style trajectories and free exploration (training world seeds).
    Dataset {
        #[arg(long, value_parser = clap::value_parser!(u32).range(1..=1_000_000))]
        trajectories: u32,
        #[arg(long)]
        out: PathBuf,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        #[arg(long, default_value = "64x64", value_parser = parse_size)]
        size: (u32, u32),
    },
    /// Render one frame: rgb.png, depth.png, depth.npy and render.json.
    Render {
        #[arg(long)]
        out: PathBuf,
        /// World seed.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Camera as x,y,z,pitch,yaw (Minecraft convention, degrees, eye position). Default: the spawn point facing +z.
        #[arg(long, value_parser = parse_pose5, allow_hyphen_values = true)]
        pose: Option<memory::Pose5>,
        /// Spawn in this biome instead (plains, forest, desert, snowy, mountains, badlands).
        #[arg(long, value_parser = parse_biome, conflicts_with = "pose")]
        biome: Option<world::Biome>,
        #[arg(long, default_value = "64x64", value_parser = parse_size)]
        size: (u32, u32),
        /// Pixel u,v whose block face is reported in render.json (default: the centre).
        #[arg(long, value_parser = parse_pixel)]
        probe: Option<(u32, u32)>,
    },
}

impl Sim {
    pub fn name(&self) -> &'static str {
        match self {
            Sim::Loopnav { .. } => "sim loopnav",
            Sim::Occluders { .. } => "sim occluders",
            Sim::Dataset { .. } => "sim dataset",
            Sim::Render { .. } => "sim render",
        }
    }

    pub fn run(&self) -> Result<()> {
        match self {
            Sim::Loopnav { out, per_cell, seed, size, tasks, ranges } => loopnav(out, *per_cell as usize, *seed, *size, tasks, ranges),
            Sim::Occluders { out, count, range, seed, size } => occluders(out, *count as usize, *range, *seed, *size),
            Sim::Dataset { trajectories, out, seed, size } => dataset(out, *trajectories as usize, *seed, *size),
            Sim::Render { out, seed, pose, biome, size, probe } => render_one(out, *seed, *pose, *biome, *size, *probe),
        }
    }
}

fn parse_pixel(s: &str) -> Result<(u32, u32), String> {
    let (u, v) = s.split_once(',').ok_or_else(|| format!("expected u,v, got {s:?}"))?;
    let n = |t: &str| t.trim().parse::<u32>().map_err(|_| format!("expected whole pixel coordinates u,v, got {s:?}"));
    Ok((n(u)?, n(v)?))
}
