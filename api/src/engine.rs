//! What a request does, without HTTP: create a session, step it through the
//! model, observe a frame. The server's handlers and `worldpack bench serve`
//! call the same functions, so the benchmark's "library call" is the step
//! the server makes.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use memory::{ContextPlan, Intrinsics, Pose};
use model::full_size::{FullSize, full_size_frame};
use model::generate::frame_to_tensor;
use model::{Model, Sampler};
use world::World;
use motion::Action;
use world::agent::PlayerState;
use world::picture::{encode_depth_png16, encode_png};
use world::render::{RenderSettings, render};

use crate::batch::{self, Batcher, Item, OwnedFrame, OwnedWarp};
use crate::refusal::EngineError;
use crate::session::{GENERATED, OBSERVED, Session, Timeline, player_to};
use crate::store::{ForkOf, FrameMeta, FrameRecord, SessionRecord, Store};

pub struct Engine {
    pub store: Store,
    pub model: Option<Model>,
    /// Gathers concurrent sessions' model calls into one (`Config::batch_window`); None: each step calls alone.
    pub batcher: Option<Batcher>,
    /// The largest side of a session's frames (`serve --max-frame-side`):
    /// frames are kept and answered at their own size up to it.
    pub max_frame_side: u32,
    /// How a frame larger than the model's is made (`model::full_size`): the model's serving block's rule.
    pub full_size: FullSize,
    worlds: Mutex<HashMap<u64, Arc<World>>>,
}

/// The default of `serve --max-frame-side`: Doom's 320×240 screen and a
/// 256×256 photo fit; a 512×512 frame's full-size stage is about 5× a 224×224 one's.
pub const MAX_FRAME_SIDE: u32 = 512;

/// What one step produced.
pub struct StepOutcome {
    pub index: u64,
    pub time: u64,
    pub pose: Pose,
    pub png: Vec<u8>,
    pub plan: ContextPlan,
    pub layout: String,
    pub exact_evaluations: usize,
    pub timings_ms: [f64; 7], // select, warp, sample, decode, full_size, truth, store
    /// The observed frames a geometry model warped into the new view, best
    /// first (empty for other models, or when no frame with depth sees it).
    pub warp_frames: Vec<u64>,
    /// In a synthetic session: how close the frame is to what the world shows there.
    pub truth: Option<TruthScore>,
    /// The world's own frame (an observing step), not the model's.
    pub observed: bool,
}

/// What a step may be told besides its action.
#[derive(Clone, Copy, Debug)]
pub struct StepOptions {
    /// The next camera pose (default: the motion model's, from the action).
    pub pose: Option<Pose>,
    /// The noise seed (default: derived from the frame's time).
    pub seed: Option<u64>,
    /// A synthetic session's frame scored against the world's true frame
    /// (rendering it costs as much as the model's step at 224×224).
    pub truth: bool,
}

impl Default for StepOptions {
    fn default() -> Self {
        StepOptions { pose: None, seed: None, truth: true }
    }
}

/// A generated frame against the synthetic world's true frame at its pose.
#[derive(Clone, Copy, Debug)]
pub struct TruthScore {
    pub psnr_db: f64,
    pub ssim: f64,
}

impl Engine {
    pub fn new(store: Store, model: Option<Model>) -> Engine {
        let full_size = model.as_ref().map_or_else(FullSize::default, |m| FullSize::of(m.manifest().serving.as_ref()));
        Engine { store, model, batcher: None, max_frame_side: MAX_FRAME_SIDE, full_size, worlds: Mutex::new(HashMap::new()) }
    }

    /// The synthetic world of `seed`, generated once and shared.
    pub fn world(&self, seed: u64) -> Arc<World> {
        if let Some(w) = self.worlds.lock().unwrap_or_else(|p| p.into_inner()).get(&seed) {
            return w.clone();
        }
        let w = Arc::new(World::generate(seed));
        self.worlds.lock().unwrap_or_else(|p| p.into_inner()).insert(seed, w.clone());
        w
    }

    /// The model, or the one refusal of a server that runs without one.
    pub fn model(&self) -> Result<&Model, EngineError> {
        self.model.as_ref().ok_or_else(EngineError::no_model)
    }

    /// The camera of synthetic sessions: the model's (else the world's
    /// default at 64x64), at `side` pixels wide when given, same field of view.
    pub fn synthetic_camera(&self, side: Option<u32>) -> Result<Intrinsics, EngineError> {
        let k = match &self.model {
            Some(m) => m.manifest().intrinsics,
            None => world::suite::default_intrinsics(64, 64)?,
        };
        let Some(side) = side else { return Ok(k) };
        let height = ((side as f64 * k.height as f64 / k.width as f64).round() as u32).max(1);
        self.check_frame_size("synthetic.size", side, height)?;
        k.resized(side, height).map_err(|e| EngineError::invalid("synthetic.size", e.to_string()))
    }

    /// Refuses frames larger than the server keeps, naming `field`.
    pub fn check_frame_size(&self, field: &str, width: u32, height: u32) -> Result<(), EngineError> {
        if width.max(height) > self.max_frame_side {
            return Err(EngineError::invalid(
                field,
                format!("{width}x{height} frames are larger than this server keeps ({} pixels on a side, `serve --max-frame-side`); resize them or raise the cap", self.max_frame_side),
            ));
        }
        Ok(())
    }

    /// The model's scaled latent of an RGB frame (empty without a model).
    pub fn latent_of(&self, rgb: &[u8], w: u32, h: u32, k: &Intrinsics, field: &str) -> Result<Vec<f32>, EngineError> {
        let Some(m) = &self.model else { return Ok(Vec::new()) };
        let img = &m.manifest().image;
        let (t, _) = frame_to_tensor(rgb, w, h, k, img.width as u32, img.height as u32).map_err(|e| match e {
            model::ModelError::Input { message, .. } => EngineError::invalid(field, message),
            other => EngineError::internal(other),
        })?;
        Ok(m.encode(&t)?.data)
    }

    /// A new session in the synthetic world: spawn (in `biome` if given), render, store.
    /// `side`: the session's frame width (default the model's); the model still sees its own size.
    pub fn create_synthetic(&self, policy: serde_json::Value, seed: u64, biome: Option<world::Biome>, side: Option<u32>, tenant: Option<String>) -> Result<Session, EngineError> {
        let k = self.synthetic_camera(side)?;
        let world = self.world(seed);
        let cell = world::agent::spawn_point(&world, biome)
            .ok_or_else(|| EngineError::invalid("synthetic.biome", "this world has no standable spawn in that biome"))?;
        let player = PlayerState::at_cell(cell, 0.0);
        let (first, _) = self.world_frame(&world, &k, 0, None, &player)?;
        self.create(SessionRecord { policy, intrinsics: k, world_seed: Some(seed), tenant, fork: None }, vec![first], Some(world))
    }

    /// What the synthetic world shows `player`'s camera, as an observed frame
    /// with the world's depth (as a depth camera would give it), and the depth.
    fn world_frame(&self, world: &World, k: &Intrinsics, time: u64, action: Option<&Action>, player: &PlayerState) -> Result<(FrameRecord, Vec<u16>), EngineError> {
        let frame = render(world, &player.camera(), k, &RenderSettings::default());
        let latent = self.latent_of(&frame.rgb, k.width, k.height, k, "synthetic")?;
        let depth: Vec<u16> = frame.depth.iter().map(|&d| world::suite::depth_to_mm(d)).collect();
        let record = FrameRecord {
            meta: meta(&player.camera(), time, OBSERVED, action, Some(player)),
            latent,
            png: encode_png(k.width, k.height, &frame.rgb),
            depth_png16: encode_depth_png16(k.width, k.height, &depth),
        };
        Ok((record, depth))
    }

    /// An observing step in a synthetic session: the world's physics moves
    /// the camera and the world's true frame and depth there are stored as
    /// an observed frame (exploration, as a robot's camera would record it);
    /// nothing is generated.
    pub fn step_observed(&self, s: &mut Session, action: &Action) -> Result<StepOutcome, EngineError> {
        let (Some(world), Some(_)) = (s.world.clone(), s.history().last().and_then(|f| f.player)) else {
            return Err(EngineError::invalid("observe", "only synthetic sessions have a world to observe; send real frames to /observe"));
        };
        let (pose, player) = s.timeline().motion(action)?;
        let player = player.ok_or_else(|| EngineError::internal("a synthetic session's motion without a player"))?;
        let t0 = Instant::now();
        let (time, index) = (s.history().next_time(), s.len());
        let k = *s.intrinsics();
        let (record, depth) = self.world_frame(&world, &k, time, Some(action), &player)?;
        self.store.put_frame(s.id, index, &record)?;
        s.push(time, pose, record.latent, Some(player), false)?;
        let rgb = world::picture::decode_rgb(&record.png).map_err(EngineError::internal)?.0;
        s.add_depth(index, rgb, k.width, k.height, depth)?;
        Ok(StepOutcome {
            index,
            time,
            pose,
            png: record.png,
            plan: ContextPlan { slots: Vec::new() },
            layout: String::new(),
            exact_evaluations: 0,
            timings_ms: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, ms(t0)],
            warp_frames: Vec::new(),
            truth: None,
            observed: true,
        })
    }

    /// Stores a new session with its first frames and returns it, indexed.
    pub fn create(&self, record: SessionRecord, frames: Vec<FrameRecord>, world: Option<Arc<World>>) -> Result<Session, EngineError> {
        let first = frames.first().ok_or_else(|| EngineError::invalid("frames", "give at least one frame"))?;
        let id = self.store.create_session(&record, first)?;
        for (i, f) in frames.iter().enumerate().skip(1) {
            self.store.put_frame(id, i as u64, f)?;
        }
        Session::restore(id, record, frames, world)
    }

    /// Generates the next frame of `s` and commits it before returning.
    pub fn step(&self, s: &mut Session, action: &Action, sampler: &Sampler, o: &StepOptions) -> Result<StepOutcome, EngineError> {
        let m = self.model()?;
        let next = prepare(m, &s.timeline(), action, o.pose, o.seed, s.last_plan.as_ref())?;
        let Next { pose, player, time, plan, exact_evaluations, warp_frames, select_ms, item } = next;
        let outcome = match &self.batcher {
            Some(b) => b.predict(m, &s.policy.packing, sampler, item)?,
            None => batch::call(m, &s.policy.packing, sampler, &[&item])?.remove(0),
        };
        let batch::Outcome { frame: predicted, layout, warp_ms, sample_ms, decode_ms: model_decode_ms, .. } = outcome;
        let t2 = Instant::now();
        let (rgb, width, height) = self.at_session_size(s, predicted.rgb, &pose, &warp_frames)?;
        let full_size_ms = ms(t2);
        let t_truth = Instant::now();
        let truth = if o.truth { self.truth_at(s, &pose)? } else { None }.map(|t| TruthScore {
            psnr_db: eval::metrics::psnr(&rgb, &t),
            ssim: eval::metrics::ssim(&rgb, &t, width as usize, height as usize).unwrap_or(f64::NAN),
        });
        let truth_ms = if truth.is_some() { ms(t_truth) } else { 0.0 };
        let t3 = Instant::now();
        let png = encode_png(width, height, &rgb);
        let decode_ms = model_decode_ms + ms(t3);
        let t4 = Instant::now();
        let index = s.len();
        let record = FrameRecord { meta: meta(&pose, time, GENERATED, Some(action), player.as_ref()), latent: predicted.latent, png, depth_png16: Vec::new() };
        self.store.put_frame(s.id, index, &record)?;
        let store_ms = ms(t4);
        s.push(time, pose, record.latent, player, true)?;
        s.last_plan = Some(plan.clone());
        Ok(StepOutcome {
            index,
            time,
            pose,
            png: record.png,
            plan,
            layout,
            exact_evaluations,
            timings_ms: [select_ms, warp_ms, sample_ms, decode_ms, full_size_ms, truth_ms, store_ms],
            warp_frames,
            truth,
            observed: false,
        })
    }

    /// The model's frame at `pose` shown at the session's size
    /// (`model::full_size`): as it is when the session is at the model's
    /// size, else with the stored frames (the model's warp sources, or the
    /// best-overlap ones for a model that warps none) shown where they land and agree.
    fn at_session_size(&self, s: &Session, small: Vec<u8>, pose: &Pose, warp_frames: &[u64]) -> Result<(Vec<u8>, u32, u32), EngineError> {
        let img = &self.model()?.manifest().image;
        let (sw, sh) = (img.width as u32, img.height as u32);
        let k = *s.intrinsics();
        if (k.width, k.height) == (sw, sh) {
            return Ok((small, sw, sh));
        }
        let timeline = s.timeline();
        let best;
        let ids = if warp_frames.is_empty() {
            best = timeline.warp_frames(&s.frustum(*pose)?, self.full_size.frames)?;
            &best
        } else {
            warp_frames
        };
        let sources = timeline.warp_sources_of(ids);
        let frame = full_size_frame(&small, sw, sh, &sources, pose, k.width, k.height, &self.full_size)?;
        Ok((frame.rgb, k.width, k.height))
    }

    /// A fork of `parent`: a new session of the same tenant, policy and
    /// world whose history is the parent's up to now, shared in memory and in
    /// the store (one record and a link; no frame is copied).
    pub fn fork(&self, parent: &mut Session) -> Result<Session, EngineError> {
        let record = SessionRecord { fork: Some(ForkOf { parent: parent.id, frames: parent.len() }), ..parent.record.clone() };
        let id = self.store.create_fork(&record)?;
        parent.fork(id, record)
    }

    /// What a synthetic session's world shows at `pose` (RGB at the session's
    /// camera); `None` for sessions of real frames, which have no truth here.
    pub fn truth_at(&self, s: &Session, pose: &Pose) -> Result<Option<Vec<u8>>, EngineError> {
        let Some(world) = &s.world else { return Ok(None) };
        let k = s.intrinsics();
        Ok(Some(render(world, pose, k, &RenderSettings::default()).rgb))
    }

    /// Appends a caller's frame (encoded when a model is loaded), with its
    /// depth PNG when given, and commits it.
    pub fn observe(&self, s: &mut Session, rgb: &[u8], w: u32, h: u32, pose: Pose, action: Option<&Action>, depth_png16: Vec<u8>) -> Result<(u64, u64), EngineError> {
        let k = *s.intrinsics();
        if (w, h) != (k.width, k.height) {
            return Err(EngineError::invalid("image_png", format!("is {w}x{h}; the session's frames are {}x{}", k.width, k.height)));
        }
        let latent = self.latent_of(rgb, w, h, &k, "image_png")?;
        s.frustum(pose)?;
        let time = s.history().next_time();
        let index = s.len();
        let depth = if depth_png16.is_empty() { None } else { Some(world::picture::decode_depth_png16(&depth_png16).map_err(|e| EngineError::invalid("depth_png16", e))?.0) };
        let record = FrameRecord { meta: meta(&pose, time, OBSERVED, action, None), latent, png: encode_png(w, h, rgb), depth_png16 };
        self.store.put_frame(s.id, index, &record)?;
        s.push(time, pose, record.latent, None, false)?;
        if let Some(depth) = depth {
            s.add_depth(index, rgb.to_vec(), w, h, depth)?;
        }
        Ok((index, time))
    }
}

/// A generated frame's inputs, chosen before the model runs.
pub(crate) struct Next {
    pub pose: Pose,
    pub player: Option<PlayerState>,
    pub time: u64,
    pub plan: ContextPlan,
    pub exact_evaluations: usize,
    pub warp_frames: Vec<u64>,
    pub select_ms: f64,
    /// The model call, owned so that it can run in a batch.
    pub item: Item,
}

/// The next frame's pose (given, or by the motion model), its plan over
/// `t`'s frames and a geometry model's warp sources: what a step and an
/// imagined step both run before the model.
pub(crate) fn prepare(m: &Model, t: &Timeline, action: &Action, pose: Option<Pose>, seed: Option<u64>, previous: Option<&ContextPlan>) -> Result<Next, EngineError> {
    let t0 = Instant::now();
    let (pose, player) = match pose {
        Some(p) => (p, None),
        None => t.motion(action)?,
    };
    let time = t.history.next_time();
    let frustum = t.session.frustum(pose)?;
    let selection = t.plan(&t.session.policy, &frustum, previous)?;
    let (plan, exact_evaluations) = (selection.plan, selection.stats.overlap_evaluations);
    let select_ms = ms(t0);
    let warp_frames = match &m.manifest().denoiser.warp {
        Some(spec) => t.warp_frames(&frustum, spec.frames)?,
        None => Vec::new(),
    };
    let k = t.session.intrinsics();
    let warp = t.depth_frames_of(&warp_frames).map(|(d, pose)| OwnedWarp::at_model_size(d, pose, k, m)).collect::<Result<_, _>>()?;
    let item = Item {
        target_time: time,
        target_pose: pose,
        action: action.to_vector().to_vec(),
        seed: seed.unwrap_or(time),
        warp,
        frames: plan
            .selected()
            .filter_map(|(_, f)| {
                let fr = t.history.frame(f.id)?;
                Some((f.id, OwnedFrame { latent: fr.latent.clone(), time: fr.time, pose: fr.pose, generated: fr.generated }))
            })
            .collect(),
        plan: plan.clone(),
    };
    Ok(Next { pose, player, time, plan, exact_evaluations, warp_frames, select_ms, item })
}

pub(crate) fn ms(since: Instant) -> f64 {
    since.elapsed().as_secs_f64() * 1e3
}

pub fn meta(pose: &Pose, time: u64, source: &str, action: Option<&Action>, player: Option<&PlayerState>) -> FrameMeta {
    FrameMeta {
        c2w: pose.matrix_rows(),
        time,
        source: source.into(),
        action: action.map(|a| a.to_vector().to_vec()),
        player: player.map(player_to),
    }
}

