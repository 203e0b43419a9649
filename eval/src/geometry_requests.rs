//! Geometry requests, JSON in and JSON out: a pose in every convention, projections,
//! resized intrinsics, frusta, overlaps, context plans and the depth warp, answered by
//! the memory and model crates' own code. `worldpack geometry` reads them from stdin; the
//! OpenCV convention tests and the Python tools call the Rust implementation through it,
//! so there is one source of truth.

use std::collections::HashMap;

use memory::overlap::exact_overlap;
use memory::policy::{LatentGrid, PolicySpec};
use memory::input::{IntrinsicsInput, PoseInput};
use memory::covisibility::{self, CoVisibility, DepthGrid};
use memory::{AngleUnit, Estimator, FrameMemory, Frustum, InputError, MemoryFrame, Pose, Pose5Convention, select_by_brute_force};
use serde::Deserialize;
use serde_json::{Value, json};

#[derive(Deserialize)]
#[serde(tag = "op", rename_all = "snake_case", deny_unknown_fields)]
pub enum Request {
    /// A pose in every supported convention.
    Convert { pose: PoseInput },
    /// Pixel coordinates and depths of world points.
    Project { pose: PoseInput, intrinsics: IntrinsicsInput, points: Vec<[f64; 3]> },
    /// Intrinsics after resizing the image.
    Resize { intrinsics: IntrinsicsInput, width: u32, height: u32 },
    /// Corners, planes, volume and bounding box of a view frustum.
    Frustum { pose: PoseInput, intrinsics: IntrinsicsInput },
    /// Overlap of each candidate view with the query view.
    Overlap {
        #[serde(default)]
        estimator: Estimator,
        query: ViewInput,
        candidates: Vec<ViewInput>,
    },
    /// A context plan for a target view over stored frames; with
    /// `covisibility`, occlusion-aware (memory::covisibility) from the frames' `depth`.
    Select {
        policy: PolicySpec,
        target: ViewInput,
        frames: Vec<FrameInput>,
        #[serde(default)]
        latent: Option<LatentGrid>,
        #[serde(default)]
        covisibility: Option<CoVisibility>,
    },
    /// A frame with depth splatted into another camera by the geometry
    /// models' warp (`model::warp::forward_warp`).
    Warp { source: WarpInput, target: PoseInput },
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WarpInput {
    /// Row-major RGB, 3 bytes a pixel, at the intrinsics' size.
    rgb: Vec<u8>,
    /// Millimetres along the optical axis, one per pixel; 0 = nothing in range.
    depth_mm: Vec<u16>,
    pose: PoseInput,
    intrinsics: IntrinsicsInput,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ViewInput {
    pose: PoseInput,
    intrinsics: IntrinsicsInput,
}

impl ViewInput {
    fn frustum(&self, at: &str) -> Result<Frustum, InputError> {
        Self::frustum_of(&self.pose, &self.intrinsics).map_err(|e| e.within(at))
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FrameInput {
    id: u64,
    time: u64,
    pose: PoseInput,
    intrinsics: IntrinsicsInput,
    /// Depth along the optical axis per pixel, row-major at the intrinsics'
    /// size (world units; 0: nothing in range). Used by `covisibility`.
    #[serde(default)]
    depth: Option<Vec<f32>>,
}

/// Answers one request; errors name the offending field.
pub fn answer(request: &Request) -> Result<Value, InputError> {
    match request {
        Request::Convert { pose } => {
            let p = pose.resolve().map_err(|e| e.within("pose"))?;
            Ok(describe_pose(&p))
        }
        Request::Project { pose, intrinsics, points } => {
            let p = pose.resolve().map_err(|e| e.within("pose"))?;
            let k = intrinsics.resolve().map_err(|e| e.within("intrinsics"))?;
            let mut pixels = Vec::with_capacity(points.len());
            let mut depths = Vec::with_capacity(points.len());
            for (i, pt) in points.iter().enumerate() {
                memory::error::check_finite(&format!("points[{i}]"), pt)?;
                let cam = p.world_to_camera(glam::DVec3::from_array(*pt));
                pixels.push(k.project(cam).map(|uv| [uv.x, uv.y]));
                depths.push(cam.z);
            }
            Ok(json!({ "pixels": pixels, "depths": depths }))
        }
        Request::Warp { source, target } => {
            let pose = source.pose.resolve().map_err(|e| e.within("source.pose"))?;
            let k = source.intrinsics.resolve().map_err(|e| e.within("source.intrinsics"))?;
            let dst = target.resolve().map_err(|e| e.within("target"))?;
            let src = model::warp::WarpSource { rgb: &source.rgb, depth_mm: &source.depth_mm, pose: &pose, intrinsics: &k };
            let warped = model::warp::forward_warp(&src, &dst).map_err(|e| match e {
                model::ModelError::Input { field, message } => {
                    InputError::Invalid { field: format!("source.{}", field.trim_start_matches("warp.")), reason: message }
                }
                other => InputError::Invalid { field: "source".into(), reason: other.to_string() },
            })?;
            Ok(json!({ "rgb": warped.rgb, "mask": warped.mask }))
        }
        Request::Resize { intrinsics, width, height } => {
            let k = intrinsics.resolve().map_err(|e| e.within("intrinsics"))?;
            Ok(serde_json::to_value(k.resized(*width, *height)?).expect("intrinsics serialise"))
        }
        Request::Frustum { pose, intrinsics } => {
            let f = ViewInput::frustum_of(pose, intrinsics)?;
            Ok(json!({
                "corners": f.corners().map(|c| c.to_array()),
                "planes": f.planes().map(|p| json!({ "normal": p.normal.to_array(), "offset": p.offset })),
                "volume": f.volume(),
                "aabb": { "min": f.aabb().min.to_array(), "max": f.aabb().max.to_array() },
            }))
        }
        Request::Overlap { estimator, query, candidates } => {
            let estimator = estimator.validated()?;
            let q = query.frustum("query")?;
            let cs = candidates
                .iter()
                .enumerate()
                .map(|(i, c)| c.frustum(&format!("candidates[{i}]")))
                .collect::<Result<Vec<_>, _>>()?;
            let overlaps = estimator.overlaps(&q, cs.iter());
            // The exact value rides along so a caller can see an estimator's error.
            let exact: Vec<f64> = cs.iter().map(|c| exact_overlap(&q, c)).collect();
            Ok(json!({ "overlaps": overlaps, "exact": exact }))
        }
        Request::Select { policy, target, frames, latent, covisibility } => {
            let policy = policy.clone().into_policy().map_err(|e| e.within("policy"))?;
            let target = target.frustum("target")?;
            let settings = covisibility.map(|c| c.validated()).transpose()?;
            let mut stored = Vec::with_capacity(frames.len());
            let mut depth = HashMap::new();
            for (i, f) in frames.iter().enumerate() {
                let at = format!("frames[{i}]");
                if stored.iter().any(|s: &MemoryFrame| s.id == f.id) {
                    return Err(InputError::Invalid { field: format!("{at}.id"), reason: format!("duplicate id {}", f.id) });
                }
                let frustum = ViewInput::frustum_of(&f.pose, &f.intrinsics).map_err(|e| e.within(&at))?;
                if let (Some(c), Some(d)) = (&settings, &f.depth) {
                    depth.insert(f.id, DepthGrid::pool(d, frustum.intrinsics(), c.cells).map_err(|e| e.within(&at))?);
                }
                stored.push(MemoryFrame { id: f.id, time: f.time, frustum });
            }
            let (plan, covisibility) = match settings {
                None => (select_by_brute_force(&policy, &target, &stored), None),
                Some(c) => {
                    let mut memory = FrameMemory::new();
                    for f in stored {
                        memory.insert(f).expect("ids checked unique above");
                    }
                    let (plan, stats) = covisibility::rerank(&memory, &policy, &target, &c, None, |id| depth.get(&id))?;
                    (plan, Some(stats))
                }
            };
            let mut out = json!({ "plan": plan, "empty": plan.is_empty() });
            if let Some(stats) = covisibility {
                out["covisibility"] = json!(stats);
            }
            if let Some(grid) = latent {
                let grid = grid.validated()?;
                let (used, capacity) = plan.tokens(&grid);
                out["tokens"] = json!({ "used": used, "capacity": capacity });
            }
            Ok(out)
        }
    }
}

impl ViewInput {
    fn frustum_of(pose: &PoseInput, intrinsics: &IntrinsicsInput) -> Result<Frustum, InputError> {
        let p = pose.resolve().map_err(|e| e.within("pose"))?;
        let k = intrinsics.resolve().map_err(|e| e.within("intrinsics"))?;
        Frustum::new(p, k)
    }
}

fn describe_pose(p: &Pose) -> Value {
    let (rvec, tvec) = p.to_opencv_extrinsics();
    let mut out = json!({
        "c2w": { "rotation": p.rotation_rows(), "position": p.position().to_array() },
        "opencv": { "rvec": rvec, "tvec": tvec },
        "opengl": p.to_opengl(),
    });
    for (key, convention, unit) in [
        ("minecraft", Pose5Convention::Minecraft, AngleUnit::Degrees),
        ("mineflayer", Pose5Convention::Mineflayer, AngleUnit::Radians),
        ("worldmem", Pose5Convention::WorldMem, AngleUnit::Degrees),
    ] {
        out[key] = match p.to_pose5(convention, unit) {
            Ok(p5) => serde_json::to_value(p5).expect("pose serialises"),
            Err(e) => json!({ "error": e.to_string() }),
        };
    }
    out
}

/// Runs every request in `input` (one object or an array); returns the JSON
/// to print and whether all succeeded.
pub fn answer_all(input: &str) -> Result<(Value, bool), String> {
    let value: Value = serde_json::from_str(input).map_err(|e| format!("input is not valid JSON: {e}"))?;
    let (items, batch) = match value {
        Value::Array(items) => (items, true),
        other => (vec![other], false),
    };
    let mut ok = true;
    let answers: Vec<Value> = items
        .into_iter()
        .map(|item| {
            let result = serde_json::from_value::<Request>(item)
                .map_err(|e| json!({ "field": "request", "message": e.to_string() }))
                .and_then(|r| answer(&r).map_err(|e| json!({ "field": e.field(), "message": e.to_string() })));
            result.unwrap_or_else(|error| {
                ok = false;
                json!({ "error": error })
            })
        })
        .collect();
    let out = if batch { Value::Array(answers) } else { answers.into_iter().next().unwrap_or(Value::Null) };
    Ok((out, ok))
}
