//! Reading what `worldpack sim loopnav` writes (format in docs/world.md).

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
        let (nd, depth_mm) = array::<u16>(&dir, "depth.npy", &[h, w])?;
        let (np, poses) = read_poses(&dir, "poses.npy")?;
        let (nph, phase) = array::<u8>(&dir, "phase.npy", &[])?;
        let (na, a) = array::<f32>(&dir, "actions.npy", &[7])?;
        if [nd, np, nph, na] != [n; 4] {
            return Err(bad(&dir, format!("arrays disagree on the frame count: rgb {n}, depth {nd}, poses {np}, phase {nph}, actions {na}")));
        }
        let actions = a.chunks_exact(7).map(|c| c.try_into().expect("chunks of 7")).collect();
        Ok(Trajectory { entry: entry.clone(), intrinsics: k, rgb, depth_mm, poses, phase, actions })
    }

    pub fn len(&self) -> usize {
        self.poses.len()
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
