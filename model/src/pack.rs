//! From a memory plan to the denoiser's context inputs: per-rate latents,
//! time offsets, relative poses and masks, in the layout's slot order.
//! The graph itself compresses each rate; packing only places frames.

use memory::{ContextPlan, Pose};

use crate::error::ModelError;
use crate::tensor::Tensor;
use crate::manifest::{CONTEXT_NOISE_PREFIX, ContextNoiseSpec, LatentSpec, LayoutSpec};

/// A stored frame as the denoiser needs it: its scaled latent, time and pose,
/// and whether the model generated it (rather than a camera observing it).
#[derive(Clone, Copy, Debug)]
pub struct ContextFrame<'a> {
    pub latent: &'a [f32],
    pub time: u64,
    pub pose: &'a Pose,
    pub generated: bool,
}

/// The context inputs of one sample (batch 1), named as the graph names them.
#[derive(Clone, Debug, PartialEq)]
pub struct PackedContext {
    pub tensors: Vec<(String, Tensor)>,
    /// Frames from the newest present context frame to the target.
    pub rel_time: f32,
}

/// Places the plan's frames into `layout`'s slots: the i-th plan slot at rate
/// r goes to the next free slot of rate r. `frame(id)` looks a frame up.
pub fn pack<'a>(
    layout: &LayoutSpec,
    latent: &LatentSpec,
    noise: Option<&ContextNoiseSpec>,
    plan: &ContextPlan,
    target_time: u64,
    target_pose: &Pose,
    frame: impl Fn(u64) -> Option<ContextFrame<'a>>,
) -> Result<PackedContext, ModelError> {
    let n = latent.len();
    let noise = match (layout.takes_context_noise(), noise) {
        (false, _) => None,
        (true, Some(levels)) => Some(levels),
        (true, None) => return Err(ModelError::manifest("denoiser.context_noise", format!("layout {} takes context noise levels; the manifest gives none", layout.name))),
    };
    let mut groups: Vec<Group> = layout.slots.iter().map(|s| Group::empty(s.rate, s.count, n)).collect();
    let mut newest: Option<u64> = None;
    for (i, slot) in plan.slots.iter().enumerate() {
        let Some(g) = groups.iter().position(|g| g.rate == slot.rate) else {
            return Err(ModelError::input(format!("plan.slots[{i}].rate"), format!("layout {} has no rate {}", layout.name, slot.rate)));
        };
        let capacity = layout.slots[g].count;
        let Group { used, latents: lat, times: time, poses: pose, mask, levels, .. } = &mut groups[g];
        if *used == capacity {
            return Err(ModelError::input(
                format!("plan.slots[{i}]"),
                format!("more rate-{} slots than layout {} holds ({capacity})", slot.rate, layout.name),
            ));
        }
        let at = *used;
        *used += 1;
        let Some(chosen) = slot.frame else { continue };
        let Some(f) = frame(chosen.id) else {
            return Err(ModelError::input(format!("plan.slots[{i}].frame"), format!("frame {} is not in the store", chosen.id)));
        };
        if f.latent.len() != n {
            return Err(ModelError::input(format!("frame {}", chosen.id), format!("latent has {} values, the model needs {n}", f.latent.len())));
        }
        if f.time >= target_time {
            return Err(ModelError::input(format!("frame {}", chosen.id), format!("time {} is not before the target's {target_time}", f.time)));
        }
        lat[at * n..(at + 1) * n].copy_from_slice(f.latent);
        time[at] = (f.time as f64 - target_time as f64) as f32;
        let rel = f.pose.relative_to(target_pose).matrix_rows();
        for (r, row) in rel.iter().take(3).enumerate() {
            for (c, v) in row.iter().enumerate() {
                pose[at * 12 + r * 4 + c] = *v as f32;
            }
        }
        mask[at] = 1.0;
        if let Some(l) = noise {
            levels[at] = if f.generated { l.generated_level } else { l.observed_level };
        }
        newest = Some(newest.map_or(f.time, |t| t.max(f.time)));
    }
    let Some(newest) = newest else {
        return Err(ModelError::input("plan", "no slot holds a frame; the model needs at least one"));
    };
    let mut tensors = Vec::new();
    for (s, g) in layout.slots.iter().zip(groups) {
        let (k, rate) = (s.count, g.rate);
        tensors.push((format!("context_r{rate}"), Tensor::new(vec![1, k, latent.channels, latent.height, latent.width], g.latents)));
        tensors.push((format!("context_time_r{rate}"), Tensor::new(vec![1, k], g.times)));
        tensors.push((format!("context_pose_r{rate}"), Tensor::new(vec![1, k, 12], g.poses)));
        tensors.push((format!("context_mask_r{rate}"), Tensor::new(vec![1, k], g.mask)));
        if noise.is_some() {
            tensors.push((format!("{CONTEXT_NOISE_PREFIX}{rate}"), Tensor::new(vec![1, k], g.levels)));
        }
    }
    Ok(PackedContext { tensors, rel_time: (target_time - newest) as f32 })
}

/// One rate's slots while they are filled.
struct Group {
    rate: u32,
    used: usize,
    latents: Vec<f32>,
    times: Vec<f32>,
    poses: Vec<f32>,
    mask: Vec<f32>,
    levels: Vec<f32>,
}

impl Group {
    fn empty(rate: u32, count: usize, latent_len: usize) -> Group {
        let zeros = |n: usize| vec![0.0; n];
        Group { rate, used: 0, latents: zeros(count * latent_len), times: zeros(count), poses: zeros(count * 12), mask: zeros(count), levels: zeros(count) }
    }
}

/// Concatenates samples along the batch axis (every sample from one layout).
pub fn stack(samples: &[&[(String, Tensor)]]) -> Vec<(String, Tensor)> {
    let Some(first) = samples.first() else { return Vec::new() };
    first
        .iter()
        .enumerate()
        .map(|(i, (name, t))| {
            let mut shape = t.shape.clone();
            shape[0] = samples.iter().map(|s| s[i].1.shape[0]).sum();
            let data = samples.iter().flat_map(|s| s[i].1.data.iter().copied()).collect();
            (name.clone(), Tensor::new(shape, data))
        })
        .collect()
}
