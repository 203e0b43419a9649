//! A session's frames as runs that forks share. A [`Segment`] holds a run of
//! consecutive frames with their latents, poses, depth and both indexes (all
//! frames, and the observed frames with depth). A session keeps the runs it
//! shares with its forks frozen behind an `Arc` and writes only its own
//! newest run, so a fork costs a few reference counts, never a copy of
//! frames; [`History`] reads the runs as one.

use std::collections::HashMap;
use std::sync::OnceLock;

use memory::covisibility::DepthGrid;
use memory::{FrameMemory, Frustum, MemoryFrame, Stack};
use world::agent::PlayerState;

use crate::refusal::EngineError;

pub struct Frame {
    pub pose: memory::Pose,
    pub time: u64,
    pub latent: Vec<f32>,
    pub player: Option<PlayerState>,
    /// Made by the model (a step), not observed: the model is told so when it is in context.
    pub generated: bool,
}

/// An observed frame that came with depth, at the session's camera size.
pub struct DepthFrame {
    pub rgb: Vec<u8>,
    pub depth_mm: Vec<u16>,
    /// The frame at the model's size, made the first time a step warps it
    /// (a session larger than the model's frames would resample its warp
    /// sources at every step otherwise).
    pub at_model_size: OnceLock<Resampled>,
}

/// A frame and its depth resampled to another size (`model::warp::resampled`).
pub struct Resampled {
    pub rgb: Vec<u8>,
    pub depth_mm: Vec<u16>,
    pub intrinsics: memory::Intrinsics,
}

impl DepthFrame {
    pub fn new(rgb: Vec<u8>, depth_mm: Vec<u16>) -> DepthFrame {
        DepthFrame { rgb, depth_mm, at_model_size: OnceLock::new() }
    }
}

/// Consecutive frames from session index `start` on, indexed.
#[derive(Default)]
pub struct Segment {
    start: u64,
    frames: Vec<Frame>,
    memory: FrameMemory,
    /// The observed frames with depth, indexed apart: a geometry model warps
    /// the ones of them that overlap the target view most.
    depth_memory: FrameMemory,
    depth_frames: HashMap<u64, DepthFrame>,
    /// Their depth pooled at the default co-visibility grid (memory::covisibility).
    depth_grids: HashMap<u64, DepthGrid>,
}

impl Segment {
    /// An empty run whose first frame will have index `start`.
    pub fn starting_at(start: u64) -> Segment {
        Segment { start, ..Segment::default() }
    }

    /// The index the next frame pushed gets.
    pub fn end(&self) -> u64 {
        self.start + self.frames.len() as u64
    }

    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// Appends a frame seen through `frustum`, indexed at [`Segment::end`].
    pub fn push(&mut self, frustum: Frustum, frame: Frame) -> Result<(), EngineError> {
        self.memory.insert(MemoryFrame { id: self.end(), time: frame.time, frustum })?;
        self.frames.push(frame);
        Ok(())
    }

    /// Indexes frame `index` of this run (seen through `frustum`) as a warp source.
    pub fn add_depth(&mut self, index: u64, frustum: Frustum, depth: DepthFrame, grid: DepthGrid) -> Result<(), EngineError> {
        let f = self.get(index).ok_or_else(|| EngineError::internal(format!("depth for frame {index}, which is not indexed")))?;
        self.depth_memory.insert(MemoryFrame { id: index, time: f.time, frustum })?;
        self.depth_grids.insert(index, grid);
        self.depth_frames.insert(index, depth);
        Ok(())
    }

    fn get(&self, index: u64) -> Option<&Frame> {
        self.frames.get(usize::try_from(index.checked_sub(self.start)?).ok()?)
    }
}

/// Runs read as one history, oldest first, each starting where the one before ends.
#[derive(Clone, Default)]
pub struct History<'a> {
    segments: Vec<&'a Segment>,
}

impl<'a> History<'a> {
    pub fn new(segments: Vec<&'a Segment>) -> History<'a> {
        History { segments }
    }

    /// This history with `top` after it (an imagined rollout's own frames).
    pub fn with(&self, top: &'a Segment) -> History<'a> {
        let mut segments = self.segments.clone();
        segments.push(top);
        History { segments }
    }

    pub fn len(&self) -> u64 {
        self.segments.last().map_or(0, |s| s.end())
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The run holding frame `index`.
    fn segment_of(&self, index: u64) -> Option<&'a Segment> {
        let after = self.segments.partition_point(|s| s.start <= index);
        self.segments[..after].last().copied()
    }

    pub fn frame(&self, index: u64) -> Option<&'a Frame> {
        self.segment_of(index)?.get(index)
    }

    pub fn last(&self) -> Option<&'a Frame> {
        self.segments.iter().rev().find_map(|s| s.frames.last())
    }

    pub fn first(&self) -> Option<&'a Frame> {
        self.segments.iter().find_map(|s| s.frames.first())
    }

    /// The time a new frame gets: one after the newest.
    pub fn next_time(&self) -> u64 {
        self.last().map_or(0, |f| f.time + 1)
    }

    /// Every frame's index, for selection.
    pub fn memory(&self) -> Stack<'a> {
        Stack::new(self.segments.iter().map(|s| &s.memory).collect())
    }

    /// The observed frames with depth, for the warp's sources.
    pub fn depth_memory(&self) -> Stack<'a> {
        Stack::new(self.segments.iter().map(|s| &s.depth_memory).collect())
    }

    pub fn depth_frame(&self, index: u64) -> Option<&'a DepthFrame> {
        self.segment_of(index)?.depth_frames.get(&index)
    }

    /// Frame `index`'s depth pooled at the default co-visibility grid.
    pub fn depth_grid(&self, index: u64) -> Option<&'a DepthGrid> {
        self.segment_of(index)?.depth_grids.get(&index)
    }

    /// Every observed frame with depth, by index.
    pub fn depth_frames(&self) -> impl Iterator<Item = (u64, &'a DepthFrame)> + '_ {
        self.segments.iter().flat_map(|s| s.depth_frames.iter().map(|(&i, d)| (i, d)))
    }

    /// How many runs the history reads (one per fork point with frames after it).
    pub fn segments(&self) -> usize {
        self.segments.len()
    }
}

#[cfg(test)]
mod tests {
    use memory::{Intrinsics, Pose};

    use super::*;

    fn frame(time: u64) -> (Frustum, Frame) {
        let x = time as f64;
        let pose = Pose::from_matrix_rows([[1.0, 0.0, 0.0, x], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]).unwrap();
        let k = Intrinsics::from_fov(70.0, None, 8, 8).unwrap();
        (Frustum::new(pose, k).unwrap(), Frame { pose, time, latent: vec![time as f32], player: None, generated: false })
    }

    fn run(start: u64, n: u64) -> Segment {
        let mut s = Segment::starting_at(start);
        for t in start..start + n {
            let (f, fr) = frame(t);
            s.push(f, fr).unwrap();
        }
        s
    }

    #[test]
    fn runs_read_as_one_history_by_index() {
        let (a, b, empty, c) = (run(0, 3), run(3, 2), Segment::starting_at(5), run(5, 4));
        let h = History::new(vec![&a, &b, &empty, &c]);
        assert_eq!((h.len(), h.next_time()), (9, 9));
        for i in 0..9 {
            assert_eq!(h.frame(i).map(|f| f.latent[0]), Some(i as f32), "frame {i}");
        }
        assert!(h.frame(9).is_none());
        assert_eq!(h.memory().len(), 9);
        let top = run(9, 1);
        let imagined = h.with(&top);
        assert_eq!((imagined.len(), imagined.last().map(|f| f.time), h.len()), (10, Some(9), 9));
        assert!(History::default().last().is_none() && History::default().is_empty());
    }
}
