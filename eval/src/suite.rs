//! Reading and checking suites in the `worldpack-suite/1` format
//! (docs/dataset.md): what `worldpack sim` and the Doom tool write, and what
//! anyone's own frames can be written as.

use std::path::{Path, PathBuf};

use memory::{Frustum, Intrinsics, Pose};
use serde::Deserialize;
use world::npy;

#[derive(Debug, thiserror::Error)]
pub enum SuiteError {
    #[error("{path}: {message}")]
    File { path: PathBuf, message: String },
}

fn bad(path: &Path, message: impl std::fmt::Display) -> SuiteError {
    SuiteError::File { path: path.to_path_buf(), message: message.to_string() }
}

#[derive(Clone, Debug, Deserialize)]
pub struct Entry {
    pub dir: String,
    pub task: String,
    pub range: i32,
    pub frames: usize,
    pub returning_point: usize,
}

/// The format versions this reader understands.
pub const SUITE_FORMAT: &str = "worldpack-suite/1";
pub const TRAJECTORY_FORMAT: &str = "worldpack-trajectory/1";

#[derive(Deserialize)]
struct Index {
    trajectories: Vec<Entry>,
}

/// The trajectories a suite lists, in its order.
pub fn entries(suite: &Path) -> Result<Vec<Entry>, SuiteError> {
    let path = suite.join("index.json");
    let text = std::fs::read_to_string(&path).map_err(|e| bad(&path, format!("{e} (make a suite with `worldpack sim loopnav`)")))?;
    let index: Index = serde_json::from_str(&text).map_err(|e| bad(&path, format!("not a suite index: {e}")))?;
    Ok(index.trajectories)
}

/// The first `limit` trajectories of a suite (all without a limit), loaded;
/// an error when there are none.
pub fn load(suite: &Path, limit: Option<usize>) -> Result<Vec<Trajectory>, SuiteError> {
    let mut list = entries(suite)?;
    list.truncate(limit.unwrap_or(usize::MAX));
    if list.is_empty() {
        return Err(bad(&suite.join("index.json"), "lists no trajectories"));
    }
    list.iter().map(|e| Trajectory::load(suite, e)).collect()
}

/// One trajectory, every frame in memory.
#[derive(Clone)]
pub struct Trajectory {
    pub entry: Entry,
    pub intrinsics: Intrinsics,
    /// (T, H, W, 3) interleaved RGB.
    pub rgb: Vec<u8>,
    /// (T, H, W) millimetres along the optical axis, 0 for nothing.
    pub depth_mm: Vec<u16>,
    /// Whether the suite gave depth (`depth.npy` is optional; without it every pixel reads 0).
    pub has_depth: bool,
    pub poses: Vec<Pose>,
    /// `world::Phase` as u8: 0 look-around, 1 outbound, 2 return.
    pub phase: Vec<u8>,
    /// (T, 7): the action that led to each frame.
    pub actions: Vec<[f32; 7]>,
}

pub const RETURN_PHASE: u8 = 2;

#[derive(Deserialize)]
struct Meta {
    intrinsics: Intrinsics,
}

/// What [`check`] found in a suite that passed.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Checked {
    pub trajectories: usize,
    pub frames: usize,
    pub returning_frames: usize,
    /// Trajectories without `depth.npy` (loaded as all-unknown depth).
    pub without_depth: usize,
    pub width: u32,
    pub height: u32,
}

/// Checks a suite folder against the format, field by field, and loads every
/// trajectory as `eval`, `plan` and training read it. The first fault is
/// returned naming its file and field.
pub fn check(suite: &Path) -> Result<Checked, SuiteError> {
    let index_path = suite.join("index.json");
    let text = std::fs::read_to_string(&index_path).map_err(|e| bad(&index_path, e))?;
    let index: serde_json::Value = serde_json::from_str(&text).map_err(|e| bad(&index_path, format!("not JSON: {e}")))?;
    expect_format(&index_path, &index, SUITE_FORMAT)?;
    let list = index
        .get("trajectories")
        .and_then(|t| t.as_array())
        .ok_or_else(|| bad(&index_path, "field `trajectories`: missing or not a list"))?;
    if list.is_empty() {
        return Err(bad(&index_path, "field `trajectories`: lists no trajectories"));
    }
    let mut checked = Checked { trajectories: 0, frames: 0, returning_frames: 0, without_depth: 0, width: 0, height: 0 };
    for (i, value) in list.iter().enumerate() {
        let entry: Entry = serde_json::from_value(value.clone())
            .map_err(|e| bad(&index_path, format!("field `trajectories[{i}]`: {e}")))?;
        let dir = suite.join(&entry.dir);
        if !dir.is_dir() {
            return Err(bad(&index_path, format!("field `trajectories[{i}].dir`: no folder {}", dir.display())));
        }
        let meta_path = dir.join("meta.json");
        let meta: serde_json::Value = std::fs::read_to_string(&meta_path)
            .map_err(|e| bad(&meta_path, e))
            .and_then(|t| serde_json::from_str(&t).map_err(|e| bad(&meta_path, format!("not JSON: {e}"))))?;
        expect_format(&meta_path, &meta, TRAJECTORY_FORMAT)?;
        let k: Intrinsics = meta
            .get("intrinsics")
            .ok_or_else(|| bad(&meta_path, "field `intrinsics`: missing"))
            .and_then(|v| serde_json::from_value(v.clone()).map_err(|e| bad(&meta_path, format!("field `intrinsics`: {e}"))))?;
        k.validated().map_err(|e| bad(&meta_path, format!("field `intrinsics`: {e}")))?;
        if checked.trajectories > 0 && (k.width, k.height) != (checked.width, checked.height) {
            return Err(bad(&meta_path, format!("field `intrinsics`: {}x{} frames, the suite's first trajectory has {}x{}",
                k.width, k.height, checked.width, checked.height)));
        }
        let t = Trajectory::load(suite, &entry)?;
        if t.len() != entry.frames {
            return Err(bad(&index_path, format!("field `trajectories[{i}].frames`: says {}, the arrays hold {}", entry.frames, t.len())));
        }
        if entry.returning_point == 0 || entry.returning_point >= t.len() {
            return Err(bad(&index_path, format!("field `trajectories[{i}].returning_point`: {} is not a frame after the first (1..{})",
                entry.returning_point, t.len())));
        }
        for (field, value) in [("frames", entry.frames), ("returning_point", entry.returning_point)] {
            if let Some(m) = meta.get(field).and_then(|v| v.as_u64()) && m as usize != value {
                return Err(bad(&meta_path, format!("field `{field}`: {m}, index.json says {value}")));
            }
        }
        if let Some(f) = t.phase.iter().position(|&p| p > RETURN_PHASE) {
            return Err(bad(&dir.join("phase.npy"), format!("frame {f}: phase {} is not 0, 1 or 2", t.phase[f])));
        }
        if let Some(f) = t.actions.iter().position(|a| a.iter().any(|v| !v.is_finite())) {
            return Err(bad(&dir.join("actions.npy"), format!("frame {f}: not finite")));
        }
        checked.trajectories += 1;
        checked.frames += t.len();
        checked.returning_frames += t.len() - entry.returning_point;
        checked.without_depth += usize::from(!t.has_depth);
        (checked.width, checked.height) = (k.width, k.height);
    }
    Ok(checked)
}

fn expect_format(path: &Path, value: &serde_json::Value, want: &str) -> Result<(), SuiteError> {
    match value.get("format").and_then(|f| f.as_str()) {
        Some(f) if f == want => Ok(()),
        Some(f) => Err(bad(path, format!("field `format`: {f:?}, this reader knows {want:?}"))),
        None => Err(bad(path, format!("field `format`: missing (expected {want:?})"))),
    }
}

fn array<T: npy::Element>(dir: &Path, name: &str, tail: &[usize]) -> Result<(usize, Vec<T>), SuiteError> {
    let path = dir.join(name);
    let (shape, data) = npy::read::<T>(&path).map_err(|e| bad(&path, e))?;
    if shape.len() != tail.len() + 1 || shape[1..] != *tail {
        return Err(bad(&path, format!("expected shape (T, {tail:?}), got {shape:?}")));
    }
    Ok((shape[0], data))
}

/// (T, 4, 4) camera-to-world matrices (OpenCV axes) from `dir/name`.
fn read_poses(dir: &Path, name: &str) -> Result<(usize, Vec<Pose>), SuiteError> {
    let (n, m) = array::<f64>(dir, name, &[4, 4])?;
    let poses = m
        .chunks_exact(16)
        .enumerate()
        .map(|(t, m)| {
            let rows = [0, 1, 2, 3].map(|i| [m[4 * i], m[4 * i + 1], m[4 * i + 2], m[4 * i + 3]]);
            Pose::from_matrix_rows(rows).map_err(|e| bad(&dir.join(name), format!("frame {t}: {e}")))
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok((n, poses))
}

impl Trajectory {
    /// Other poses for this trajectory's frames, e.g. estimated by visual
    /// odometry (`scripts/visual_odometry.py` writes `poses-vo.npy`).
    pub fn believed_poses(&self, suite: &Path, name: &str) -> Result<Vec<Pose>, SuiteError> {
        let dir = suite.join(&self.entry.dir);
        let (n, poses) = read_poses(&dir, name)?;
        if n != self.len() {
            return Err(bad(&dir.join(name), format!("has {n} poses but the trajectory has {} frames", self.len())));
        }
        Ok(poses)
    }


    pub fn load(suite: &Path, entry: &Entry) -> Result<Trajectory, SuiteError> {
        let dir = suite.join(&entry.dir);
        let meta_path = dir.join("meta.json");
        let meta: Meta = std::fs::read_to_string(&meta_path)
            .map_err(|e| bad(&meta_path, e))
            .and_then(|t| serde_json::from_str(&t).map_err(|e| bad(&meta_path, e)))?;
        let k = meta.intrinsics;
        let (w, h) = (k.width as usize, k.height as usize);
        let (n, rgb) = array::<u8>(&dir, "rgb.npy", &[h, w, 3])?;
        let has_depth = dir.join("depth.npy").exists();
        let (nd, depth_mm) = if has_depth { array::<u16>(&dir, "depth.npy", &[h, w])? } else { (n, vec![0; n * h * w]) };
        let (np, poses) = read_poses(&dir, "poses.npy")?;
        let (nph, phase) = array::<u8>(&dir, "phase.npy", &[])?;
        let (na, a) = array::<f32>(&dir, "actions.npy", &[7])?;
        if [nd, np, nph, na] != [n; 4] {
            return Err(bad(&dir, format!("arrays disagree on the frame count: rgb {n}, depth {nd}, poses {np}, phase {nph}, actions {na}")));
        }
        let actions = a.chunks_exact(7).map(|c| c.try_into().expect("chunks of 7")).collect();
        Ok(Trajectory { entry: entry.clone(), intrinsics: k, rgb, depth_mm, has_depth, poses, phase, actions })
    }

    pub fn len(&self) -> usize {
        self.poses.len()
    }

    /// This trajectory at `width × height` (a model's frame size): every
    /// frame and depth map resampled as a server resamples a client's warp
    /// sources (`model::warp::resampled`), the intrinsics scaled to match.
    pub fn at_size(&self, width: u32, height: u32) -> Result<Trajectory, model::ModelError> {
        let (mut rgb, mut depth_mm) = (Vec::new(), Vec::new());
        let mut k = self.intrinsics;
        for t in 0..self.len() {
            let src = model::WarpSource { rgb: self.frame(t), depth_mm: self.depth(t), pose: &self.poses[t], intrinsics: &self.intrinsics };
            let (c, d, k2) = model::warp::resampled(&src, width, height)?;
            rgb.extend(c);
            depth_mm.extend(d);
            k = k2;
        }
        Ok(Trajectory { entry: self.entry.clone(), intrinsics: k, rgb, depth_mm, poses: self.poses.clone(), phase: self.phase.clone(), actions: self.actions.clone(), ..*self })
    }

    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    pub fn frame(&self, t: usize) -> &[u8] {
        let n = self.intrinsics.width as usize * self.intrinsics.height as usize * 3;
        &self.rgb[t * n..(t + 1) * n]
    }

    pub fn depth(&self, t: usize) -> &[u16] {
        let n = self.intrinsics.width as usize * self.intrinsics.height as usize;
        &self.depth_mm[t * n..(t + 1) * n]
    }

    /// Every frame's view frustum, in frame order.
    pub fn frusta(&self) -> Result<Vec<Frustum>, SuiteError> {
        self.poses
            .iter()
            .enumerate()
            .map(|(t, p)| Frustum::new(*p, self.intrinsics).map_err(|e| bad(Path::new(&self.entry.dir), format!("frame {t}: {e}"))))
            .collect()
    }

    /// Frames of the return leg, every `stride`-th (never frame 0).
    pub fn return_frames(&self, stride: usize) -> Vec<usize> {
        (1..self.len()).filter(|&t| self.phase[t] == RETURN_PHASE).step_by(stride.max(1)).collect()
    }
}
