//! Image metrics on 8-bit RGB frames, in LoopNav's definitions: PSNR over
//! all channels, and SSIM with an 11×11 Gaussian window (σ = 1.5) over the
//! window positions that fit inside the image, averaged over channels.

/// PSNR is capped here so a pixel-identical pair (a frame copied while the
/// agent stands still) does not turn a mean into infinity.
pub const PSNR_CAP_DB: f64 = 100.0;

const WINDOW: usize = 11;
const SIGMA: f64 = 1.5;
const C1: f64 = (0.01 * 255.0) * (0.01 * 255.0);
const C2: f64 = (0.03 * 255.0) * (0.03 * 255.0);

/// Peak signal-to-noise ratio in dB for a peak of 255.
pub fn psnr(a: &[u8], b: &[u8]) -> f64 {
    assert_eq!(a.len(), b.len(), "psnr: images differ in size");
    let se: f64 = a.iter().zip(b).map(|(&x, &y)| (x as f64 - y as f64).powi(2)).sum();
    psnr_of_mse(se / a.len().max(1) as f64)
}

/// PSNR in dB of a mean squared error on 0..255 values, capped at [`PSNR_CAP_DB`].
fn psnr_of_mse(mse: f64) -> f64 {
    if mse == 0.0 { PSNR_CAP_DB } else { (10.0 * (255.0 * 255.0 / mse).log10()).min(PSNR_CAP_DB) }
}

/// How well a depth map made by warping matches the true one, summed over
/// pixels where both see a surface (sky and holes left out), so tallies add.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DepthTally {
    /// Pixels of the true depth map that see a surface.
    pub surface_pixels: usize,
    /// Of those, where the warp put a surface too.
    pub compared: usize,
    pub abs_rel_sum: f64,
    /// Compared pixels with max(d/d*, d*/d) < 1.25.
    pub within_1_25: usize,
}

impl DepthTally {
    /// `predicted` in metres (0: nothing, infinity: sky) against `truth_mm` (0: nothing within range).
    pub fn of(predicted: &[f64], truth_mm: &[u16]) -> DepthTally {
        let mut t = DepthTally::default();
        for (&d, &g) in predicted.iter().zip(truth_mm) {
            if g == 0 {
                continue;
            }
            t.surface_pixels += 1;
            if !(d > 0.0 && d.is_finite()) {
                continue;
            }
            let g = g as f64 * 1e-3;
            t.compared += 1;
            t.abs_rel_sum += (d - g).abs() / g;
            t.within_1_25 += usize::from((d / g).max(g / d) < 1.25);
        }
        t
    }

    pub fn add(&mut self, other: &DepthTally) {
        self.surface_pixels += other.surface_pixels;
        self.compared += other.compared;
        self.abs_rel_sum += other.abs_rel_sum;
        self.within_1_25 += other.within_1_25;
    }

    /// Mean |d − d*| / d* over the compared pixels.
    pub fn abs_rel(&self) -> f64 {
        self.abs_rel_sum / self.compared.max(1) as f64
    }

    /// The share of compared pixels within a factor 1.25 of the truth.
    pub fn delta_1_25(&self) -> f64 {
        self.within_1_25 as f64 / self.compared.max(1) as f64
    }

    /// The share of the truth's surface pixels the warp gives a depth for.
    pub fn coverage(&self) -> f64 {
        self.compared as f64 / self.surface_pixels.max(1) as f64
    }
}

/// PSNR over the pixels whose `mask` entry equals `inside` (RGB images,
/// one mask entry per pixel); `None` when fewer than `min_pixels` qualify.
pub fn psnr_where(a: &[u8], b: &[u8], mask: &[bool], inside: bool, min_pixels: usize) -> Option<f64> {
    assert_eq!(a.len(), b.len(), "psnr_where: images differ in size");
    assert_eq!(a.len(), mask.len() * 3, "psnr_where: one mask entry per pixel");
    let (mut se, mut n) = (0.0, 0usize);
    for ((x, y), &m) in a.chunks_exact(3).zip(b.chunks_exact(3)).zip(mask) {
        if m == inside {
            se += x.iter().zip(y).map(|(&p, &q)| (p as f64 - q as f64).powi(2)).sum::<f64>();
            n += 1;
        }
    }
    if n < min_pixels.max(1) {
        return None;
    }
    Some(psnr_of_mse(se / (3 * n) as f64))
}

/// Mean squared difference between neighbouring pixels (right and down) of
/// an interleaved RGB image's luma: how much edge a frame carries. Blur
/// lowers it, so a prediction's energy over the truth's tells a sharp frame
/// from a smooth one that happens to score well on PSNR.
pub fn gradient_energy(rgb: &[u8], width: usize, height: usize) -> f64 {
    gradient_energy_where(rgb, width, height, &|_| true).0
}

/// [`gradient_energy`] over the neighbour pairs whose two pixels `keep`
/// (by pixel index), and how many pairs that was.
fn gradient_energy_where(rgb: &[u8], width: usize, height: usize, keep: &dyn Fn(usize) -> bool) -> (f64, usize) {
    assert_eq!(rgb.len(), width * height * 3, "gradient_energy: not an RGB image of the given size");
    let luma: Vec<f64> = rgb.chunks_exact(3).map(|p| 0.299 * p[0] as f64 + 0.587 * p[1] as f64 + 0.114 * p[2] as f64).collect();
    let (mut sum, mut n) = (0.0, 0usize);
    for y in 0..height {
        for x in 0..width {
            let i = y * width + x;
            if !keep(i) {
                continue;
            }
            let v = luma[i];
            if x + 1 < width && keep(i + 1) {
                sum += (luma[i + 1] - v).powi(2);
                n += 1;
            }
            if y + 1 < height && keep(i + width) {
                sum += (luma[i + width] - v).powi(2);
                n += 1;
            }
        }
    }
    (if n == 0 { 0.0 } else { sum / n as f64 }, n)
}

/// The prediction's gradient energy over the truth's: 1 as sharp as the
/// truth, below 1 blurrier, above 1 noisier. `None` for a flat truth.
pub fn sharpness_ratio(predicted: &[u8], truth: &[u8], width: usize, height: usize) -> Option<f64> {
    let reference = gradient_energy(truth, width, height);
    (reference > 0.0).then(|| gradient_energy(predicted, width, height) / reference)
}

/// [`sharpness_ratio`] over the neighbour pairs whose two pixels have
/// `mask == inside` (the warp's holes, say); `None` with fewer than
/// `min_pairs` such pairs or a flat truth there.
pub fn sharpness_ratio_where(predicted: &[u8], truth: &[u8], width: usize, height: usize, mask: &[bool], inside: bool, min_pairs: usize) -> Option<f64> {
    assert_eq!(mask.len(), width * height, "sharpness_ratio_where: one mask entry per pixel");
    let keep = |i: usize| mask[i] == inside;
    let (reference, n) = gradient_energy_where(truth, width, height, &keep);
    if n < min_pairs.max(1) || reference <= 0.0 {
        return None;
    }
    Some(gradient_energy_where(predicted, width, height, &keep).0 / reference)
}

fn gaussian_window() -> [f64; WINDOW] {
    let mut w = [0.0; WINDOW];
    let c = (WINDOW / 2) as f64;
    for (i, v) in w.iter_mut().enumerate() {
        *v = (-((i as f64 - c).powi(2)) / (2.0 * SIGMA * SIGMA)).exp();
    }
    let sum: f64 = w.iter().sum();
    w.map(|v| v / sum)
}

/// Separable "valid" filtering of one plane: output is (w−10)×(h−10).
fn filter_valid(plane: &[f64], w: usize, h: usize, k: &[f64; WINDOW]) -> Vec<f64> {
    let (ow, oh) = (w + 1 - WINDOW, h + 1 - WINDOW);
    let mut rows = vec![0.0; ow * h];
    for y in 0..h {
        for x in 0..ow {
            rows[y * ow + x] = (0..WINDOW).map(|i| k[i] * plane[y * w + x + i]).sum();
        }
    }
    let mut out = vec![0.0; ow * oh];
    for y in 0..oh {
        for x in 0..ow {
            out[y * ow + x] = (0..WINDOW).map(|i| k[i] * rows[(y + i) * ow + x]).sum();
        }
    }
    out
}

/// Mean SSIM of two interleaved RGB images of `width`×`height`. `None` when
/// the image is smaller than the window.
pub fn ssim(a: &[u8], b: &[u8], width: usize, height: usize) -> Option<f64> {
    assert_eq!(a.len(), b.len(), "ssim: images differ in size");
    assert_eq!(a.len(), width * height * 3, "ssim: not an RGB image of the given size");
    if width < WINDOW || height < WINDOW {
        return None;
    }
    let k = gaussian_window();
    let mut total = 0.0;
    for c in 0..3 {
        let x: Vec<f64> = a.iter().skip(c).step_by(3).map(|&v| v as f64).collect();
        let y: Vec<f64> = b.iter().skip(c).step_by(3).map(|&v| v as f64).collect();
        let prod = |p: &[f64], q: &[f64]| p.iter().zip(q).map(|(u, v)| u * v).collect::<Vec<f64>>();
        let mx = filter_valid(&x, width, height, &k);
        let my = filter_valid(&y, width, height, &k);
        let sxx = filter_valid(&prod(&x, &x), width, height, &k);
        let syy = filter_valid(&prod(&y, &y), width, height, &k);
        let sxy = filter_valid(&prod(&x, &y), width, height, &k);
        let n = mx.len();
        let mut sum = 0.0;
        for i in 0..n {
            let (mx, my) = (mx[i], my[i]);
            let (vx, vy, cxy) = (sxx[i] - mx * mx, syy[i] - my * my, sxy[i] - mx * my);
            sum += ((2.0 * mx * my + C1) * (2.0 * cxy + C2)) / ((mx * mx + my * my + C1) * (vx + vy + C2));
        }
        total += sum / n as f64;
    }
    Some(total / 3.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_tallies_leave_out_sky_and_holes_and_add_up() {
        // Truth: sky, 2 m, 4 m, 10 m. Warp: a surface where there is sky, a hole, 2.4 m (AbsRel 0.4), 10 m.
        let t = DepthTally::of(&[3.0, 0.0, 2.4, 10.0], &[0, 2000, 4000, 10000]);
        assert_eq!((t.surface_pixels, t.compared, t.within_1_25), (3, 2, 1));
        assert!((t.abs_rel() - 0.2).abs() < 1e-12 && (t.delta_1_25() - 0.5).abs() < 1e-12);
        let mut sum = t;
        sum.add(&t);
        assert_eq!((sum.compared, sum.coverage()), (4, 4.0 / 6.0));
    }

    #[test]
    fn psnr_where_scores_only_its_side_of_the_mask() {
        let truth = [10u8; 12];
        let mut pred = [10u8; 12];
        pred[9..12].copy_from_slice(&[20, 20, 20]); // the last pixel is off by 10
        let mask = [true, true, true, false];
        assert_eq!(psnr_where(&pred, &truth, &mask, true, 1), Some(PSNR_CAP_DB));
        let outside = psnr_where(&pred, &truth, &mask, false, 1).unwrap();
        assert!((outside - 10.0 * (255.0f64 * 255.0 / 100.0).log10()).abs() < 1e-9);
        assert_eq!(psnr_where(&pred, &truth, &mask, false, 2), None, "one pixel is fewer than asked for");
    }

    fn noise_image(seed: u64, n: usize) -> Vec<u8> {
        let mut rng = memory::rng::SplitMix64::new(seed);
        (0..n).map(|_| (rng.next_u64() >> 56) as u8).collect()
    }

    #[test]
    fn psnr_matches_the_definition_and_caps_identical_images() {
        let a = vec![100u8; 48];
        let mut b = a.clone();
        b[0] = 110; // one error of 10 over 48 values: mse 100/48
        let want = 10.0 * (255.0f64 * 255.0 / (100.0 / 48.0)).log10();
        assert!((psnr(&a, &b) - want).abs() < 1e-12);
        assert_eq!(psnr(&a, &a), PSNR_CAP_DB);
    }

    #[test]
    fn ssim_is_one_for_identical_images_and_falls_with_noise() {
        let (w, h) = (32, 24);
        let a = noise_image(1, w * h * 3);
        assert!((ssim(&a, &a, w, h).unwrap() - 1.0).abs() < 1e-12);
        let mut rng = memory::rng::SplitMix64::new(2);
        let slightly: Vec<u8> = a.iter().map(|&v| v.saturating_add((rng.next_u64() % 8) as u8)).collect();
        let other = noise_image(3, w * h * 3);
        let s1 = ssim(&a, &slightly, w, h).unwrap();
        let s2 = ssim(&a, &other, w, h).unwrap();
        assert!(s1 < 1.0 && s1 > 0.8, "{s1}");
        assert!(s2 < 0.1, "{s2}");
        assert!(ssim(&a[..10 * 10 * 3], &a[..10 * 10 * 3], 10, 10).is_none());
    }

    #[test]
    fn window_sums_to_one_and_is_symmetric() {
        let k = gaussian_window();
        assert!((k.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        assert!((0..WINDOW).all(|i| (k[i] - k[WINDOW - 1 - i]).abs() < 1e-15));
    }

    #[test]
    fn the_sharpness_ratio_in_a_mask_sees_only_the_pairs_inside_it() {
        let (w, h) = (8, 8);
        // Stripes in the left half, flat in the right; the prediction flattens the left half.
        let truth: Vec<u8> = (0..w * h).flat_map(|i| if i % w < 4 && (i % w) % 2 == 0 { [255u8; 3] } else { [0u8; 3] }).collect();
        let mut predicted = truth.clone();
        for i in 0..w * h {
            if i % w < 4 {
                predicted[3 * i..3 * i + 3].copy_from_slice(&[128; 3]);
            }
        }
        let left: Vec<bool> = (0..w * h).map(|i| i % w < 4).collect();
        assert_eq!(sharpness_ratio_where(&predicted, &truth, w, h, &left, true, 1), Some(0.0), "the flattened stripes keep no edge");
        assert_eq!(sharpness_ratio_where(&truth, &truth, w, h, &left, true, 1), Some(1.0));
        assert_eq!(sharpness_ratio_where(&predicted, &truth, w, h, &left, false, 1), None, "the right half is flat in the truth");
        assert_eq!(sharpness_ratio_where(&truth, &truth, w, h, &left, true, 1000), None, "too few pairs");
    }

    #[test]
    fn blur_lowers_the_sharpness_ratio_and_a_flat_truth_has_none() {
        let (w, h) = (16, 8);
        // Vertical stripes of 0 and 200: every horizontal step is 200 in every channel.
        let stripes: Vec<u8> = (0..w * h).flat_map(|i| [if i % 2 == 0 { 0 } else { 200 }; 3]).collect();
        assert!((gradient_energy(&stripes, w, h) - 200.0f64.powi(2) * (h * (w - 1)) as f64 / (h * (w - 1) + w * (h - 1)) as f64).abs() < 1e-9);
        // A 2-pixel box blur halves nothing but the contrast: steps of 100 where there were 200.
        let blurred: Vec<u8> = (0..w * h).flat_map(|i| [if i % 2 == 0 { 50 } else { 150 }; 3]).collect();
        let r = sharpness_ratio(&blurred, &stripes, w, h).unwrap();
        assert!((r - 0.25).abs() < 1e-9, "{r}");
        assert_eq!(sharpness_ratio(&stripes, &stripes, w, h), Some(1.0));
        assert_eq!(sharpness_ratio(&stripes, &vec![7u8; w * h * 3], w, h), None);
    }
}
