//! From a memory plan to the denoiser's context inputs: per-rate latents,
//! time offsets, relative poses and masks, in the layout's slot order.
//! The graph itself compresses each rate; packing only places frames.

use memory::{ContextPlan, Pose};

use crate::error::ModelError;
use crate::graph::Tensor;
use crate::manifest::{LatentSpec, LayoutSpec};

/// A stored frame as the denoiser needs it: its scaled latent, time and pose.
#[derive(Clone, Copy, Debug)]
pub struct ContextFrame<'a> {
    pub latent: &'a [f32],
    pub time: u64,
    pub pose: &'a Pose,
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
    plan: &ContextPlan,
    target_time: u64,
    target_pose: &Pose,
    frame: impl Fn(u64) -> Option<ContextFrame<'a>>,
) -> Result<PackedContext, ModelError> {
    let n = latent.len();
    let mut groups: Vec<(u32, usize, Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>)> = layout
        .slots
        .iter()
        .map(|s| (s.rate, 0, vec![0.0; s.count * n], vec![0.0; s.count], vec![0.0; s.count * 12], vec![0.0; s.count]))
        .collect();
    let mut newest: Option<u64> = None;
    for (i, slot) in plan.slots.iter().enumerate() {
        let Some(g) = groups.iter_mut().position(|g| g.0 == slot.rate) else {
            return Err(ModelError::input(format!("plan.slots[{i}].rate"), format!("layout {} has no rate {}", layout.name, slot.rate)));
        };
        let capacity = layout.slots[g].count;
        let (_, used, lat, time, pose, mask) = &mut groups[g];
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
        newest = Some(newest.map_or(f.time, |t| t.max(f.time)));
    }
    let Some(newest) = newest else {
        return Err(ModelError::input("plan", "no slot holds a frame; the model needs at least one"));
    };
    let mut tensors = Vec::new();
    for (s, (rate, _, lat, time, pose, mask)) in layout.slots.iter().zip(groups) {
        let k = s.count;
        tensors.push((format!("context_r{rate}"), Tensor::new(vec![1, k, latent.channels, latent.height, latent.width], lat)));
        tensors.push((format!("context_time_r{rate}"), Tensor::new(vec![1, k], time)));
        tensors.push((format!("context_pose_r{rate}"), Tensor::new(vec![1, k, 12], pose)));
        tensors.push((format!("context_mask_r{rate}"), Tensor::new(vec![1, k], mask)));
    }
    Ok(PackedContext { tensors, rel_time: (target_time - newest) as f32 })
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
