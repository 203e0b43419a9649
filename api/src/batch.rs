//! Batching across sessions: concurrent steps' model calls with the same
//! packing and sampler are gathered, within a short bounded wait, into one
//! `Model::predict` over all of them.
//!
//! Leader and followers, no thread of its own: the first step to arrive
//! when nobody is gathering becomes the leader, waits `window` (or until
//! `max` items are queued), runs the batch and hands every item its frame;
//! later arrivals queue and wait. Each item carries its own seed, so its
//! frame does not depend on its batch-mates (`Model::predict`); a batch that
//! fails is run again item by item, so one bad item cannot fail the others.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use memory::{ContextPlan, Intrinsics, Packing, Pose};
use model::pack::ContextFrame;
use model::{Model, ModelError, Predicted, Request, Sampler, WarpSource};

use crate::history::{DepthFrame, Resampled};
use crate::refusal::EngineError;

/// A stored frame an item's plan refers to, owned so the item can cross threads.
pub struct OwnedFrame {
    pub latent: Vec<f32>,
    pub time: u64,
    pub pose: Pose,
    pub generated: bool,
}

/// A warp source, owned.
pub struct OwnedWarp {
    pub rgb: Vec<u8>,
    pub depth_mm: Vec<u16>,
    pub pose: Pose,
    pub intrinsics: Intrinsics,
}

impl OwnedWarp {
    /// Observed frame `d` (at `pose`, the session's camera `k`) at the model's
    /// frame size: resampled (`model::warp::resampled`) once and kept with the
    /// frame when the session's size is another, copied when it is the model's.
    pub fn at_model_size(d: &DepthFrame, pose: &Pose, k: &Intrinsics, m: &Model) -> Result<OwnedWarp, ModelError> {
        let image = &m.manifest().image;
        let (width, height) = (image.width as u32, image.height as u32);
        if (k.width, k.height) == (width, height) {
            return Ok(OwnedWarp { rgb: d.rgb.clone(), depth_mm: d.depth_mm.clone(), pose: *pose, intrinsics: *k });
        }
        if d.at_model_size.get().is_none() {
            let (rgb, depth_mm, intrinsics) = model::warp::resampled(&WarpSource { rgb: &d.rgb, depth_mm: &d.depth_mm, pose, intrinsics: k }, width, height)?;
            let _ = d.at_model_size.set(Resampled { rgb, depth_mm, intrinsics }); // a concurrent step may have set it: the same pixels
        }
        let r = d.at_model_size.get().expect("set above");
        Ok(OwnedWarp { rgb: r.rgb.clone(), depth_mm: r.depth_mm.clone(), pose: *pose, intrinsics: r.intrinsics })
    }
}

/// One step's model call.
pub struct Item {
    pub plan: ContextPlan,
    pub target_time: u64,
    pub target_pose: Pose,
    pub action: Vec<f32>,
    pub seed: u64,
    pub warp: Vec<OwnedWarp>,
    pub frames: HashMap<u64, OwnedFrame>,
}

/// An item's frame and the times of the call it was part of.
pub struct Outcome {
    pub frame: Predicted,
    pub layout: String,
    pub warp_ms: f64,
    pub sample_ms: f64,
    pub decode_ms: f64,
    /// Items in that call.
    pub batch: usize,
}

struct Job {
    packing: Packing,
    sampler: Sampler,
    item: Item,
    reply: mpsc::Sender<Result<Outcome, ModelError>>,
}

impl Job {
    /// Jobs that may share a call: the same layout and the same sampler.
    fn fits(&self, other: &Job) -> bool {
        self.packing == other.packing
            && self.sampler.timesteps == other.sampler.timesteps
            && self.sampler.method == other.sampler.method
            && self.sampler.eta == other.sampler.eta
    }
}

pub struct Batcher {
    window: Duration,
    max: usize,
    queue: Mutex<Vec<Job>>,
    leading: AtomicBool,
    /// Calls run and items served, for `/metrics`.
    pub calls: AtomicU64,
    pub items: AtomicU64,
}

impl Batcher {
    pub fn new(window: Duration, max: usize) -> Batcher {
        Batcher { window, max: max.max(1), queue: Mutex::new(Vec::new()), leading: AtomicBool::new(false), calls: AtomicU64::new(0), items: AtomicU64::new(0) }
    }

    /// Predicts `item`'s frame, possibly in one call with other sessions' items.
    pub fn predict(&self, model: &Model, packing: &Packing, sampler: &Sampler, item: Item) -> Result<Outcome, EngineError> {
        let (reply, answer) = mpsc::channel();
        self.queue.lock().expect("batch queue").push(Job { packing: packing.clone(), sampler: sampler.clone(), item, reply });
        if !self.leading.swap(true, Ordering::AcqRel) {
            self.lead(model);
        }
        let outcome = answer.recv().map_err(|_| EngineError::internal("the model call this step was batched into was lost"))?;
        Ok(outcome?)
    }

    /// Gathers for one window, then runs batches until the queue is empty.
    fn lead(&self, model: &Model) {
        // Should a model call panic, the next step to arrive must be able to lead.
        let _unwinding = StepDown(&self.leading);
        let deadline = Instant::now() + self.window;
        while Instant::now() < deadline && self.queue.lock().expect("batch queue").len() < self.max {
            std::thread::sleep(Duration::from_micros(200));
        }
        loop {
            let batch = {
                let mut queue = self.queue.lock().expect("batch queue");
                if queue.is_empty() {
                    self.leading.store(false, Ordering::Release);
                    drop(queue);
                    // A job queued after the check above and before the flag fell would wait forever.
                    if !self.queue.lock().expect("batch queue").is_empty() && !self.leading.swap(true, Ordering::AcqRel) {
                        continue;
                    }
                    return;
                }
                let first = queue.remove(0);
                let mut batch = vec![first];
                let mut i = 0;
                while i < queue.len() && batch.len() < self.max {
                    if batch[0].fits(&queue[i]) { batch.push(queue.remove(i)) } else { i += 1 }
                }
                batch
            };
            self.run(model, batch);
        }
    }

    fn run(&self, model: &Model, batch: Vec<Job>) {
        let (packing, sampler) = (batch[0].packing.clone(), batch[0].sampler.clone());
        let items: Vec<&Item> = batch.iter().map(|j| &j.item).collect();
        match call(model, &packing, &sampler, &items) {
            Ok(outcomes) => {
                self.calls.fetch_add(1, Ordering::Relaxed);
                self.items.fetch_add(batch.len() as u64, Ordering::Relaxed);
                for (job, outcome) in batch.iter().zip(outcomes) {
                    let _ = job.reply.send(Ok(outcome));
                }
            }
            Err(_) if batch.len() > 1 => {
                for job in batch {
                    let Job { packing, sampler, item, reply } = job;
                    let _ = reply.send(call(model, &packing, &sampler, &[&item]).map(|mut o| o.remove(0)));
                }
            }
            Err(e) => {
                let _ = batch[0].reply.send(Err(e));
            }
        }
    }
}

/// Gives up leadership when a leader unwinds (its batch's steps get an error; the rest wait for the next leader).
struct StepDown<'a>(&'a AtomicBool);

impl Drop for StepDown<'_> {
    fn drop(&mut self) {
        if std::thread::panicking() {
            self.0.store(false, Ordering::Release);
        }
    }
}

/// One `Model::predict` over `items`, each with its own frames and warp sources.
pub fn call(model: &Model, packing: &Packing, sampler: &Sampler, items: &[&Item]) -> Result<Vec<Outcome>, ModelError> {
    call_with(model, packing, sampler, items, true)
}

/// As [`call`], stopping at the sampled latents (`Model::predict_latents`): the frames' `rgb` is empty.
pub fn call_latents(model: &Model, packing: &Packing, sampler: &Sampler, items: &[&Item]) -> Result<Vec<Outcome>, ModelError> {
    call_with(model, packing, sampler, items, false)
}

fn call_with(model: &Model, packing: &Packing, sampler: &Sampler, items: &[&Item], decode: bool) -> Result<Vec<Outcome>, ModelError> {
    let warps: Vec<Vec<WarpSource>> = items
        .iter()
        .map(|it| it.warp.iter().map(|w| WarpSource { rgb: &w.rgb, depth_mm: &w.depth_mm, pose: &w.pose, intrinsics: &w.intrinsics }).collect())
        .collect();
    let requests: Vec<Request> = items
        .iter()
        .zip(&warps)
        .map(|(it, warp)| Request { plan: &it.plan, target_time: it.target_time, target_pose: &it.target_pose, action: &it.action, seed: it.seed, warp })
        .collect();
    let lookup = |i: usize, id: u64| {
        items[i].frames.get(&id).map(|f| ContextFrame { latent: &f.latent, time: f.time, pose: &f.pose, generated: f.generated })
    };
    let p = if decode { model.predict(packing, &requests, &lookup, sampler)? } else { model.predict_latents(packing, &requests, &lookup, sampler)? };
    let n = items.len();
    Ok(p.frames
        .into_iter()
        .map(|frame| Outcome { frame, layout: p.layout.clone(), warp_ms: p.warp_ms, sample_ms: p.sample_ms, decode_ms: p.decode_ms, batch: n })
        .collect())
}
