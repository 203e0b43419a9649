//! Suites on disk: LoopNav-style evaluation suites and training datasets,
//! one folder per trajectory of `.npy` arrays plus `meta.json`. The format
//! is documented in `docs/world.md`.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use memory::Intrinsics;
use serde::Serialize;

use crate::noise::{Rng, hash};
use crate::npy;
use crate::picture;
use crate::render::{RenderSettings, render};
use crate::terrain::World;
use crate::trajectory::{Task, Trajectory, TrajectorySpec, generate, generate_occluder};

pub const TRAJECTORY_FORMAT: &str = "worldpack-trajectory/1";
pub const SUITE_FORMAT: &str = "worldpack-suite/1";
/// LoopNav's navigation ranges.
pub const RANGES: [i32; 4] = [5, 15, 30, 50];
/// Minecraft's default field of view is 70° vertical.
pub const DEFAULT_VFOV_DEG: f64 = 70.0;

/// Evaluation suites and training data draw world seeds from disjoint halves
/// of the 64-bit space (the top bit), so no world is in both.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Split {
    Train,
    Test,
}

impl Split {
    pub fn world_seed(self, suite_seed: u64, parts: &[i64]) -> u64 {
        let h = hash(suite_seed ^ 0x5eed0f3071d, parts);
        match self {
            Split::Train => h & !(1 << 63),
            Split::Test => h | (1 << 63),
        }
    }

    pub fn of_world_seed(seed: u64) -> Split {
        if seed >> 63 == 1 { Split::Test } else { Split::Train }
    }
}

/// The camera every suite frame uses: square pixels, 70° vertical FoV,
/// centred principal point, the memory crate's default near/far.
pub fn default_intrinsics(width: u32, height: u32) -> Result<Intrinsics, memory::InputError> {
    let half_v = (DEFAULT_VFOV_DEG / 2.0).to_radians();
    let hfov = 2.0 * (half_v.tan() * width as f64 / height.max(1) as f64).atan().to_degrees();
    Intrinsics::from_fov(hfov, Some(DEFAULT_VFOV_DEG), width, height)
}

/// One planned trajectory: where it goes on disk and what fixes it.
#[derive(Clone, Debug)]
pub struct Planned {
    pub name: String,
    pub spec: TrajectorySpec,
    pub max_steps: usize,
}

/// The LoopNav suite: `per_cell` trajectories for every (task, range).
pub fn loopnav_plan(seed: u64, per_cell: usize, tasks: &[Task], ranges: &[i32]) -> Vec<Planned> {
    let mut plan = Vec::new();
    for &task in tasks {
        for &range in ranges {
            for i in 0..per_cell {
                let parts = [task as i64, range as i64, i as i64];
                plan.push(Planned {
                    name: format!("{}-r{:02}-{:03}", task.name(), range, i),
                    spec: TrajectorySpec { task, range, world_seed: Split::Test.world_seed(seed, &parts), seed: hash(seed, &parts) },
                    max_steps: 2400,
                });
            }
        }
    }
    plan
}

/// Training data: loop-style trajectories (ABA 35%, ABCA 35%, tours that
/// return 15%) and free exploration (15%), on training world seeds.
pub fn dataset_plan(seed: u64, trajectories: usize) -> Vec<Planned> {
    (0..trajectories)
        .map(|i| {
            let mut rng = Rng::new(hash(seed ^ 0xda7a, &[i as i64]));
            let roll = rng.range(0, 100);
            let task = match roll {
                0..35 => Task::Aba,
                35..70 => Task::Abca,
                70..85 => Task::Tour,
                _ => Task::Wander,
            };
            let ranges: &[i32] = if matches!(task, Task::Tour | Task::Wander) { &RANGES[..3] } else { &RANGES };
            let range = ranges[rng.range(0, ranges.len() as i64) as usize];
            let parts = [i as i64];
            Planned {
                name: format!("{:05}-{}-r{:02}", i, task.name(), range),
                spec: TrajectorySpec { task, range, world_seed: Split::Train.world_seed(seed, &parts), seed: hash(seed, &parts) },
                max_steps: 1600,
            }
        })
        .collect()
}

/// The occluder suite: `count` occluder scenes (`trajectory::generate_occluder`)
/// with walls `range` blocks long, on test world seeds.
pub fn occluder_plan(seed: u64, count: usize, range: i32) -> Vec<Planned> {
    (0..count)
        .map(|i| {
            let parts = [Task::Occluder as i64, range as i64, i as i64];
            Planned {
                name: format!("occluder-r{range:02}-{i:03}"),
                spec: TrajectorySpec { task: Task::Occluder, range, world_seed: Split::Test.world_seed(seed, &parts), seed: hash(seed, &parts) },
                max_steps: 1200,
            }
        })
        .collect()
}

/// Generates the trajectory, moving to another world of the same split
/// (seeded by the attempt number) when one cannot hold it.
pub fn realise(planned: &Planned) -> Result<(World, Trajectory), String> {
    let mut spec = planned.spec;
    let mut last_error = String::new();
    for attempt in 0..8 {
        if attempt > 0 {
            let split = Split::of_world_seed(planned.spec.world_seed);
            spec.world_seed = split.world_seed(planned.spec.world_seed, &[attempt]);
        }
        let mut world = World::generate(spec.world_seed);
        let walked = match spec.task {
            Task::Occluder => generate_occluder(&mut world, &spec, planned.max_steps),
            _ => generate(&world, &spec, planned.max_steps),
        };
        match walked {
            Ok(t) => return Ok((world, t)),
            Err(e) => last_error = e.to_string(),
        }
    }
    Err(format!("{}: no world held this trajectory after 8 tries (last: {last_error})", planned.name))
}

#[derive(Clone, Debug, Serialize)]
pub struct TrajectoryMeta {
    pub format: &'static str,
    pub name: String,
    pub split: Split,
    pub task: Task,
    pub range: i32,
    pub world_seed: u64,
    pub seed: u64,
    pub frames: usize,
    pub returning_point: usize,
    pub waypoints: Vec<[i32; 3]>,
    pub intrinsics: Intrinsics,
    pub render: RenderSettings,
    pub pose5: &'static str,
    pub depth_unit: &'static str,
}

/// Renders every frame and writes the trajectory's folder.
pub fn write_trajectory(
    dir: &Path,
    name: &str,
    world: &World,
    t: &Trajectory,
    k: &Intrinsics,
    settings: &RenderSettings,
) -> std::io::Result<TrajectoryMeta> {
    std::fs::create_dir_all(dir)?;
    let n = t.steps.len();
    let (w, h) = (k.width as usize, k.height as usize);
    let mut rgb = Vec::with_capacity(n * w * h * 3);
    let mut depth = Vec::with_capacity(n * w * h);
    let mut poses: Vec<f64> = Vec::with_capacity(n * 16);
    let mut pose5 = Vec::with_capacity(n * 5);
    let mut actions = Vec::with_capacity(n * 7);
    for s in &t.steps {
        let camera = s.state.camera();
        let frame = render(world, &camera, k, settings);
        rgb.extend_from_slice(&frame.rgb);
        depth.extend(frame.depth.iter().map(|&d| depth_to_mm(d)));
        poses.extend(camera.matrix_rows().iter().flatten());
        let p = s.state.pose5();
        pose5.extend([p.x, p.y, p.z, p.pitch, p.yaw]);
        actions.extend(s.action.to_vector());
    }
    npy::write(&dir.join("rgb.npy"), &[n, h, w, 3], &rgb)?;
    npy::write(&dir.join("depth.npy"), &[n, h, w], &depth)?;
    npy::write(&dir.join("poses.npy"), &[n, 4, 4], &poses)?;
    npy::write(&dir.join("pose5.npy"), &[n, 5], &pose5)?;
    npy::write(&dir.join("actions.npy"), &[n, 7], &actions)?;
    npy::write(&dir.join("phase.npy"), &[n], &t.steps.iter().map(|s| s.phase as u8).collect::<Vec<_>>())?;
    let (mw, mh, map) = picture::top_down(world, t, 4);
    picture::write_png(&dir.join("topdown.png"), mw, mh, &map)?;
    let meta = TrajectoryMeta {
        format: TRAJECTORY_FORMAT,
        name: name.to_string(),
        split: Split::of_world_seed(t.spec.world_seed),
        task: t.spec.task,
        range: t.spec.range,
        world_seed: t.spec.world_seed,
        seed: t.spec.seed,
        frames: n,
        returning_point: t.returning_point,
        waypoints: t.waypoints.clone(),
        intrinsics: *k,
        render: *settings,
        pose5: "minecraft, degrees: x, y (eye), z, pitch (positive looks down), yaw (0 faces +z)",
        depth_unit: "millimetres along the optical axis; 0 = nothing within view_distance",
    };
    std::fs::write(dir.join("meta.json"), serde_json::to_string_pretty(&meta).map_err(std::io::Error::other)?)?;
    Ok(meta)
}

/// Depth in whole millimetres (u16 holds up to 65.5 m, past any view
/// distance the renderer allows); 0 for sky.
pub fn depth_to_mm(d: f32) -> u16 {
    if d.is_finite() { (d * 1000.0).round().clamp(1.0, 65535.0) as u16 } else { 0 }
}

#[derive(Clone, Debug, Serialize)]
pub struct SuiteEntry {
    pub dir: String,
    pub task: Task,
    pub range: i32,
    pub frames: usize,
    pub returning_point: usize,
}

/// Writes every planned trajectory under `out` on `threads` threads, then
/// `index.json`; returns that file's path and the total number of frames.
/// `progress` is called once per finished trajectory.
pub fn write_suite(
    out: &Path,
    kind: &str,
    seed: u64,
    plan: &[Planned],
    k: &Intrinsics,
    settings: &RenderSettings,
    threads: usize,
    progress: &(dyn Fn(&str) + Sync),
) -> Result<(PathBuf, usize), String> {
    std::fs::create_dir_all(out).map_err(|e| format!("cannot create {}: {e}", out.display()))?;
    let next = AtomicUsize::new(0);
    let results: Vec<Result<SuiteEntry, String>> = std::thread::scope(|scope| {
        let workers: Vec<_> = (0..threads.max(1))
            .map(|_| {
                scope.spawn(|| {
                    let mut done = Vec::new();
                    loop {
                        let i = next.fetch_add(1, Ordering::Relaxed);
                        let Some(p) = plan.get(i) else { break };
                        let result = realise(p).and_then(|(world, t)| {
                            let meta = write_trajectory(&out.join(&p.name), &p.name, &world, &t, k, settings)
                                .map_err(|e| format!("{}: {e}", p.name))?;
                            Ok(SuiteEntry {
                                dir: p.name.clone(),
                                task: meta.task,
                                range: meta.range,
                                frames: meta.frames,
                                returning_point: meta.returning_point,
                            })
                        });
                        progress(&p.name);
                        done.push((i, result));
                    }
                    done
                })
            })
            .collect();
        let mut all: Vec<_> = workers.into_iter().flat_map(|w| w.join().expect("suite worker panicked")).collect();
        all.sort_by_key(|(i, _)| *i);
        all.into_iter().map(|(_, r)| r).collect()
    });
    let entries = results.into_iter().collect::<Result<Vec<_>, _>>()?;
    let frames = entries.iter().map(|e| e.frames).sum::<usize>();
    let split = plan.first().map(|p| Split::of_world_seed(p.spec.world_seed)).unwrap_or(Split::Test);
    let index = serde_json::json!({
        "format": SUITE_FORMAT,
        "kind": kind,
        "split": split,
        "seed": seed,
        "width": k.width,
        "height": k.height,
        "frames": frames,
        "trajectories": entries,
    });
    let path = out.join("index.json");
    std::fs::write(&path, serde_json::to_string_pretty(&index).unwrap()).map_err(|e| format!("{}: {e}", path.display()))?;
    Ok((path, frames))
}
