//! What the stores keep, whichever backend: a session's record, a frame's
//! record and its byte encoding, and the errors a store answers.

use serde::{Deserialize, Serialize};

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("store: {0}")]
    Failed(String),
    /// The database cannot be reached (PostgreSQL down or the connection lost): worth retrying.
    #[error("store unavailable: {0}")]
    Unavailable(String),
    /// The frame index is stored already: another request (or another
    /// server on the same database) wrote it first. Frames are never replaced.
    #[error("frame {index} of session {session} is already stored: the session moved on (another request or replica wrote it first)")]
    Taken { session: u64, index: u64 },
    /// A session to fork is not stored (never made, or deleted meanwhile).
    #[error("no session {0}")]
    Missing(u64),
    /// A session that forks were made from is deleted only after them: they read its frames.
    #[error("session {session} has live forks ({}); delete them first: they read its frames", list(forks))]
    HasForks { session: u64, forks: Vec<u64> },
}

fn list(ids: &[u64]) -> String {
    ids.iter().map(u64::to_string).collect::<Vec<_>>().join(", ")
}

pub(crate) fn err(e: impl std::fmt::Display) -> StoreError {
    StoreError::Failed(e.to_string())
}

/// What a session was created with; enough to rebuild it after a restart.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SessionRecord {
    /// The policy as the caller gave it (a `memory::PolicySpec`).
    pub policy: serde_json::Value,
    pub intrinsics: memory::Intrinsics,
    /// `Some(seed)` for a session in the synthetic world.
    pub world_seed: Option<u64>,
    /// The tenant that created it, when the server runs with tokens.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tenant: Option<String>,
    /// A fork's link to the session it was forked from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fork: Option<ForkOf>,
}

/// Where a fork comes from: its first `frames` frames are `parent`'s, stored
/// once, under the parent; the fork's own frames follow from index `frames` on.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ForkOf {
    pub parent: u64,
    pub frames: u64,
}

/// One stored frame. `latent` is the model's scaled latent (absent when the
/// server runs without a model); `png` the image; `depth_png16` the caller's
/// depth map when given (16-bit grayscale PNG, millimetres, 0 = unknown).
#[derive(Clone, Debug, PartialEq)]
pub struct FrameRecord {
    pub meta: FrameMeta,
    pub latent: Vec<f32>,
    pub png: Vec<u8>,
    pub depth_png16: Vec<u8>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrameMeta {
    /// Camera-to-world, OpenCV axes, row-major 4×4.
    pub c2w: [[f64; 4]; 4],
    pub time: u64,
    /// `observed` (given by the caller) or `generated` (by the model).
    pub source: String,
    pub action: Option<Vec<f32>>,
    /// Synthetic sessions: the player's feet, yaw and pitch (Minecraft degrees), for the motion model.
    pub player: Option<[f64; 5]>,
}

impl FrameRecord {
    /// `[u32 header length][header JSON][latent f32 LE][png][depth png]`, the
    /// header holding the meta, the latent's length and the image's.
    pub fn encode(&self) -> Vec<u8> {
        let header = serde_json::to_vec(&(&self.meta, self.latent.len(), self.png.len())).expect("frame meta serialises");
        let mut out = Vec::with_capacity(4 + header.len() + self.latent.len() * 4 + self.png.len());
        out.extend_from_slice(&(header.len() as u32).to_le_bytes());
        out.extend_from_slice(&header);
        for v in &self.latent {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend_from_slice(&self.png);
        out.extend_from_slice(&self.depth_png16);
        out
    }

    pub fn decode(bytes: &[u8]) -> Result<FrameRecord, StoreError> {
        let n = u32::from_le_bytes(bytes.get(..4).ok_or_else(|| err("truncated frame"))?.try_into().unwrap()) as usize;
        let header = bytes.get(4..4 + n).ok_or_else(|| err("truncated frame header"))?;
        let (meta, latent_len, png_len): (FrameMeta, usize, usize) = serde_json::from_slice(header).map_err(err)?;
        let start = 4 + n;
        let lat = bytes.get(start..start + latent_len * 4).ok_or_else(|| err("truncated latent"))?;
        let latent = lat.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect();
        let png_start = start + latent_len * 4;
        let png = bytes.get(png_start..png_start + png_len).ok_or_else(|| err("truncated image"))?.to_vec();
        Ok(FrameRecord { meta, latent, png, depth_png16: bytes[png_start + png_len..].to_vec() })
    }
}
