//! Next-frame generation: the sampler loop over the denoiser, seeded noise,
//! and RGB frames in and out at the model's size.

use memory::Intrinsics;
use memory::rng::SplitMix64;

use crate::error::ModelError;
use crate::tensor::Tensor;
use crate::sampler::Sampler;
use crate::{GraphRole, Model};

/// `n` standard normal samples from `seed` (Box–Muller over SplitMix64).
pub fn gaussian(seed: u64, n: usize) -> Vec<f32> {
    let mut rng = SplitMix64::new(seed);
    let mut out = Vec::with_capacity(n + 1);
    while out.len() < n {
        let u1 = rng.next_f64().max(f64::MIN_POSITIVE);
        let (a, b) = SplitMix64::box_muller(u1, rng.next_f64());
        out.push(a as f32);
        out.push(b as f32);
    }
    out.truncate(n);
    out
}

/// The conditioning of a batch: packed context tensors plus action and relative time.
pub struct Conditioning<'a> {
    pub context: &'a [(String, Tensor)],
    /// (batch, action dim), raw units.
    pub action: &'a Tensor,
    /// (batch,)
    pub rel_time: &'a Tensor,
}

/// Item `item`'s noise for sampler step `step` (`None`: the start noise):
/// drawn from the item's own seed alone, so a frame does not depend on what
/// else shares its batch.
fn item_noise(seed: u64, step: Option<usize>, n: usize) -> Vec<f32> {
    gaussian(step.map_or(seed, |i| seed.wrapping_add(1 + i as u64)), n)
}

impl Model {
    /// Samples target latents (scaled) for a batch, one seed per item: the
    /// start noise and every step's noise come from that seed,
    /// `sampler.len()` denoiser calls in all.
    pub fn sample(&self, layout: &str, cond: &Conditioning, sampler: &Sampler, seeds: &[u64]) -> Result<Tensor, ModelError> {
        let l = &self.manifest().autoencoder.latent;
        let batch = cond.action.shape.first().copied().unwrap_or(0);
        if batch == 0 || cond.rel_time.shape != [batch] {
            return Err(ModelError::input("rel_time", format!("expected shape [{batch}], got {:?}", cond.rel_time.shape)));
        }
        if seeds.len() != batch {
            return Err(ModelError::input("seeds", format!("one seed per item: {batch} items, {} seeds", seeds.len())));
        }
        let shape = vec![batch, l.channels, l.height, l.width];
        let per = l.len();
        let draw = |step: Option<usize>| seeds.iter().flat_map(|&s| item_noise(s, step, per)).collect::<Vec<f32>>();
        let mut x = draw(None);
        let mut history = None;
        for (i, &t) in sampler.timesteps.iter().enumerate() {
            let x_t = Tensor::new(shape.clone(), x);
            let timestep = Tensor::new(vec![batch], vec![t as f32; batch]);
            let mut inputs: Vec<(&str, &Tensor)> = cond.context.iter().map(|(k, v)| (k.as_str(), v)).collect();
            inputs.extend([("x_t", &x_t), ("timestep", &timestep), ("action", cond.action), ("rel_time", cond.rel_time)]);
            let eps = self.run(GraphRole::Denoiser(layout), &inputs)?.remove(0);
            let z = if sampler.injects_noise(i) { draw(Some(i)) } else { vec![0.0; x_t.data.len()] };
            x = sampler.step(i, &x_t.data, &eps.data, &z, &mut history);
        }
        Ok(Tensor::new(shape, x))
    }
}

/// An RGB frame (row-major, 3 bytes a pixel) to a (1, 3, H, W) tensor in
/// [-1, 1] at the model's size, bilinearly resized when needed, with the
/// intrinsics rescaled to match.
pub fn frame_to_tensor(rgb: &[u8], width: u32, height: u32, k: &Intrinsics, out_w: u32, out_h: u32) -> Result<(Tensor, Intrinsics), ModelError> {
    if rgb.len() != width as usize * height as usize * 3 {
        return Err(ModelError::input("image", format!("{}x{} RGB needs {} bytes, got {}", width, height, width * height * 3, rgb.len())));
    }
    if (k.width, k.height) != (width, height) {
        return Err(ModelError::input("intrinsics", format!("are for {}x{}, the image is {width}x{height}", k.width, k.height)));
    }
    let k2 = k.resized(out_w, out_h).map_err(|e| ModelError::input("intrinsics", e.to_string()))?;
    let (ow, oh) = (out_w as usize, out_h as usize);
    let mut data = vec![0.0f32; 3 * ow * oh];
    bilinear(rgb, width as usize, height as usize, ow, oh, |u, v, c, value| data[(c * oh + v) * ow + u] = (value / 127.5 - 1.0) as f32);
    Ok((Tensor::new(vec![1, 3, oh, ow], data), k2))
}

/// Samples an RGB image of `w × h` at `ow × oh` bilinearly, pixel centres to
/// pixel centres (OpenCV's convention, as `Intrinsics::resized`), handing each
/// output pixel's channel value (0–255) to `put(u, v, channel, value)`.
pub(crate) fn bilinear(rgb: &[u8], w: usize, h: usize, ow: usize, oh: usize, mut put: impl FnMut(usize, usize, usize, f64)) {
    let (sx, sy) = (w as f64 / ow as f64, h as f64 / oh as f64);
    for v in 0..oh {
        let y = ((v as f64 + 0.5) * sy - 0.5).clamp(0.0, (h - 1) as f64);
        let (y0, fy) = (y.floor() as usize, y - y.floor());
        let y1 = (y0 + 1).min(h - 1);
        for u in 0..ow {
            let x = ((u as f64 + 0.5) * sx - 0.5).clamp(0.0, (w - 1) as f64);
            let (x0, fx) = (x.floor() as usize, x - x.floor());
            let x1 = (x0 + 1).min(w - 1);
            for c in 0..3 {
                let p = |xx: usize, yy: usize| rgb[(yy * w + xx) * 3 + c] as f64;
                let top = p(x0, y0) * (1.0 - fx) + p(x1, y0) * fx;
                let bottom = p(x0, y1) * (1.0 - fx) + p(x1, y1) * fx;
                put(u, v, c, top * (1.0 - fy) + bottom * fy);
            }
        }
    }
}

/// One image of a (B, 3, H, W) tensor in [-1, 1] back to RGB bytes, clamped.
pub fn tensor_to_frame(t: &Tensor, index: usize) -> Result<Vec<u8>, ModelError> {
    let [b, c, h, w] = t.shape[..] else {
        return Err(ModelError::input("image", format!("expected (batch, 3, H, W), got {:?}", t.shape)));
    };
    if c != 3 || index >= b {
        return Err(ModelError::input("image", format!("no RGB image {index} in a tensor of shape {:?}", t.shape)));
    }
    let plane = h * w;
    let img = &t.data[index * 3 * plane..(index + 1) * 3 * plane];
    Ok((0..plane).flat_map(|p| (0..3).map(move |c| ((img[c * plane + p].clamp(-1.0, 1.0) + 1.0) * 127.5).round() as u8)).collect())
}
