//! `worldpack geometry`: JSON in, JSON out, for the memory crate's geometry.
//!
//! One request object (or an array of them) on stdin; one response (or an
//! array) on stdout. The OpenCV convention tests and the Python training code
//! call the Rust implementation through this, so there is one source of truth.

use memory::overlap::exact_overlap;
use memory::policy::{LatentGrid, PolicySpec};
use memory::{AngleUnit, Estimator, Frustum, InputError, Intrinsics, MemoryFrame, Pose, Pose5, Pose5Convention, select};
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
    /// A context plan for a target view over stored frames.
    Select {
        policy: PolicySpec,
        target: ViewInput,
        frames: Vec<FrameInput>,
        #[serde(default)]
        latent: Option<LatentGrid>,
    },
}

/// A pose in any supported convention (exactly one key).
#[derive(Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum PoseInput {
    /// Canonical: OpenCV camera-to-world, row-major rotation.
    C2w { rotation: [[f64; 3]; 3], position: [f64; 3] },
    /// OpenCV extrinsics (world-to-camera), as `cv2.solvePnP` returns.
    Opencv { rvec: [f64; 3], tvec: [f64; 3] },
    /// OpenGL/Blender camera-to-world 4×4, row-major.
    Opengl([[f64; 4]; 4]),
    /// A 5-D pose in a named convention and unit.
    Pose5 {
        x: f64,
        y: f64,
        z: f64,
        pitch: f64,
        yaw: f64,
        convention: Pose5Convention,
        unit: AngleUnit,
    },
}

impl PoseInput {
    fn resolve(&self) -> Result<Pose, InputError> {
        match self {
            PoseInput::C2w { rotation, position } => Pose::from_rows(*rotation, *position),
            PoseInput::Opencv { rvec, tvec } => Pose::from_opencv_extrinsics(*rvec, *tvec),
            PoseInput::Opengl(m) => Pose::from_opengl(*m),
            PoseInput::Pose5 { x, y, z, pitch, yaw, convention, unit } => {
                Pose::from_pose5(&Pose5 { x: *x, y: *y, z: *z, pitch: *pitch, yaw: *yaw }, *convention, *unit)
            }
        }
    }
}

/// Intrinsics as focal lengths (`fx`, optional `fy`, `cx`, `cy`) or as
/// field-of-view angles (`hfov_deg`, optional `vfov_deg`); principal point
/// defaults to the image centre and `near`/`far` to 0.1/30.
#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct IntrinsicsInput {
    fx: Option<f64>,
    fy: Option<f64>,
    cx: Option<f64>,
    cy: Option<f64>,
    hfov_deg: Option<f64>,
    vfov_deg: Option<f64>,
    width: u32,
    height: u32,
    near: Option<f64>,
    far: Option<f64>,
}

impl IntrinsicsInput {
    fn resolve(&self) -> Result<Intrinsics, InputError> {
        let base = match (self.fx, self.hfov_deg) {
            (Some(_), Some(_)) => return Err(InputError::Invalid { field: "hfov_deg".into(), reason: "give either fx or hfov_deg, not both".into() }),
            (None, None) => return Err(InputError::Invalid { field: "fx".into(), reason: "give fx (focal length in pixels) or hfov_deg".into() }),
            (Some(fx), None) => {
                if self.vfov_deg.is_some() {
                    return Err(InputError::Invalid { field: "vfov_deg".into(), reason: "only valid together with hfov_deg".into() });
                }
                let centre = |n: u32| (n as f64 - 1.0) / 2.0;
                Intrinsics::new(
                    fx,
                    self.fy.unwrap_or(fx),
                    self.cx.unwrap_or(centre(self.width)),
                    self.cy.unwrap_or(centre(self.height)),
                    self.width,
                    self.height,
                )?
            }
            (None, Some(h)) => {
                for (field, v) in [("fy", self.fy), ("cx", self.cx), ("cy", self.cy)] {
                    if v.is_some() {
                        return Err(InputError::Invalid { field: field.into(), reason: "only valid together with fx".into() });
                    }
                }
                Intrinsics::from_fov(h, self.vfov_deg, self.width, self.height)?
            }
        };
        base.with_range(self.near.unwrap_or(base.near), self.far.unwrap_or(base.far))
    }
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
        Request::Select { policy, target, frames, latent } => {
            let policy = policy.clone().into_policy().map_err(|e| e.within("policy"))?;
            let target = target.frustum("target")?;
            let mut stored = Vec::with_capacity(frames.len());
            for (i, f) in frames.iter().enumerate() {
                let at = format!("frames[{i}]");
                if stored.iter().any(|s: &MemoryFrame| s.id == f.id) {
                    return Err(InputError::Invalid { field: format!("{at}.id"), reason: format!("duplicate id {}", f.id) });
                }
                let frustum = ViewInput::frustum_of(&f.pose, &f.intrinsics).map_err(|e| e.within(&at))?;
                stored.push(MemoryFrame { id: f.id, time: f.time, frustum });
            }
            let plan = select(&policy, &target, &stored);
            let mut out = json!({ "plan": plan, "empty": plan.is_empty() });
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
pub fn run(input: &str) -> Result<(Value, bool), String> {
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
