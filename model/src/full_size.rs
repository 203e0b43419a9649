//! Frames at the size a session's frames were seen. The model decides every
//! frame at its own size (64×64 for the shipped models); this stage shows it
//! at the session's size: the stored frames warped into the new view at their
//! own size wherever they land and agree with the model's frame, and the
//! model's frame brought up (bicubic) where they do not: holes,
//! disocclusions, new ground, and what memory shows wrongly. The model makes
//! only what memory does not hold.

use memory::Pose;

use crate::error::ModelError;
use crate::warp::{FILL_ROUNDS, WarpSource, fused_warp};

/// How much the warp and the model's frame may differ where the warp is shown.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FullSize {
    /// Largest difference in luma (0–255) between the warp averaged over one
    /// of the model's pixels and that pixel, for the warp to be shown there.
    /// The model saw the memory too, so where the two disagree the warp is
    /// more often wrong (a moved occluder, bad depth) than the model.
    pub agree_luma: f64,
    /// The least share of a model pixel's area the warp must cover to be
    /// shown there; a cell half in a hole is the model's.
    pub min_cover: f64,
    /// The most stored frames warped, best first: at 224×224 each costs about
    /// as much as warping 12 at 64×64.
    pub frames: usize,
}

impl Default for FullSize {
    fn default() -> Self {
        FullSize { agree_luma: 48.0, min_cover: 0.75, frames: 8 }
    }
}

impl FullSize {
    /// The rule a model's manifest names (its `serving.full_size` block), else the default.
    pub fn of(serving: Option<&crate::manifest::ServingSpec>) -> FullSize {
        match serving.and_then(|s| s.full_size) {
            Some(f) => FullSize { agree_luma: f.agree_luma, frames: f.frames, min_cover: f.min_cover.unwrap_or(FullSize::default().min_cover) },
            None => FullSize::default(),
        }
    }

    /// This rule with the fields `agree_luma` and `frames` replaced where given.
    pub fn with(self, agree_luma: Option<f64>, frames: Option<usize>) -> FullSize {
        FullSize { agree_luma: agree_luma.unwrap_or(self.agree_luma), frames: frames.unwrap_or(self.frames), ..self }
    }
}

/// A frame at the session's size and how it was made.
#[derive(Clone, Debug, PartialEq)]
pub struct FullFrame {
    /// Row-major RGB at the requested size.
    pub rgb: Vec<u8>,
    /// The share of pixels shown from the warp (weights summed over pixels).
    pub warp_share: f64,
}

/// `small` (the model's `sw × sh` frame) shown at `width × height`, with the
/// `sources` (best first, each at `width × height`) warped into `target`
/// where they land and agree with it.
pub fn full_size_frame(small: &[u8], sw: u32, sh: u32, sources: &[WarpSource], target: &Pose, width: u32, height: u32, rule: &FullSize) -> Result<FullFrame, ModelError> {
    let (sw, sh, w, h) = (sw as usize, sh as usize, width as usize, height as usize);
    if small.len() != sw * sh * 3 {
        return Err(ModelError::input("frame", format!("{} bytes for a {sw}x{sh} RGB frame", small.len())));
    }
    if let Some(k) = sources.iter().map(|s| s.intrinsics).find(|k| (k.width as usize, k.height as usize) != (w, h)) {
        return Err(ModelError::input("warp.intrinsics", format!("a {}x{} source for a {w}x{h} frame", k.width, k.height)));
    }
    let up = bicubic(small, sw, sh, w, h);
    let sources = &sources[..sources.len().min(rule.frames)];
    if sources.is_empty() {
        return Ok(FullFrame { rgb: up, warp_share: 0.0 });
    }
    let mut warped = fused_warp(sources, target)?;
    warped.fill_cracks(w, h, FILL_ROUNDS);
    // Agreement is judged on the model's grid: the warp averaged over each
    // model pixel's footprint against that pixel.
    let (mean, cover) = area_mean(&warped.rgb, &warped.mask, w, h, sw, sh);
    let agree: Vec<f64> = (0..sw * sh)
        .map(|p| {
            let d = (luma(&mean[3 * p..3 * p + 3]) - luma_u8(&small[3 * p..3 * p + 3])).abs();
            f64::from(cover[p] >= rule.min_cover && d <= rule.agree_luma)
        })
        .collect();
    // Soft edges between the two: the agreement weights brought up bilinearly.
    let weight = bilinear_plane(&agree, sw, sh, w, h);
    let mut rgb = up;
    let mut shown = 0.0;
    for p in 0..w * h {
        let a = if warped.mask[p] { weight[p] } else { 0.0 };
        if a > 0.0 {
            shown += a;
            for c in 0..3 {
                let v = a * warped.rgb[3 * p + c] as f64 + (1.0 - a) * rgb[3 * p + c] as f64;
                rgb[3 * p + c] = v.round() as u8;
            }
        }
    }
    Ok(FullFrame { rgb, warp_share: shown / (w * h) as f64 })
}

fn luma(rgb: &[f64]) -> f64 {
    0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2]
}

fn luma_u8(rgb: &[u8]) -> f64 {
    luma(&[rgb[0] as f64, rgb[1] as f64, rgb[2] as f64])
}

/// The mean colour of the landed pixels over each cell of an `sw × sh` grid
/// laid on a `w × h` image (pixels assigned by their centre), and the share
/// of each cell's pixels that landed.
fn area_mean(rgb: &[u8], mask: &[bool], w: usize, h: usize, sw: usize, sh: usize) -> (Vec<f64>, Vec<f64>) {
    let mut sum = vec![0.0; sw * sh * 3];
    let mut landed = vec![0usize; sw * sh];
    let mut all = vec![0usize; sw * sh];
    for y in 0..h {
        let cy = ((y as f64 + 0.5) * sh as f64 / h as f64) as usize;
        for x in 0..w {
            let cx = ((x as f64 + 0.5) * sw as f64 / w as f64) as usize;
            let (p, c) = (y * w + x, cy.min(sh - 1) * sw + cx.min(sw - 1));
            all[c] += 1;
            if mask[p] {
                landed[c] += 1;
                for k in 0..3 {
                    sum[3 * c + k] += rgb[3 * p + k] as f64;
                }
            }
        }
    }
    for c in 0..sw * sh {
        for k in 0..3 {
            sum[3 * c + k] /= landed[c].max(1) as f64;
        }
    }
    (sum, landed.iter().zip(&all).map(|(&l, &a)| l as f64 / a.max(1) as f64).collect())
}

/// One plane of `w × h` values at `ow × oh`, bilinear, pixel centres to pixel centres.
fn bilinear_plane(plane: &[f64], w: usize, h: usize, ow: usize, oh: usize) -> Vec<f64> {
    let taps = |o: usize, n: usize, on: usize| {
        let x = ((o as f64 + 0.5) * n as f64 / on as f64 - 0.5).clamp(0.0, (n - 1) as f64);
        let x0 = x as usize;
        (x0, (x0 + 1).min(n - 1), x - x0 as f64)
    };
    let mut out = Vec::with_capacity(ow * oh);
    for v in 0..oh {
        let (y0, y1, fy) = taps(v, h, oh);
        for u in 0..ow {
            let (x0, x1, fx) = taps(u, w, ow);
            let top = plane[y0 * w + x0] * (1.0 - fx) + plane[y0 * w + x1] * fx;
            let bottom = plane[y1 * w + x0] * (1.0 - fx) + plane[y1 * w + x1] * fx;
            out.push(top * (1.0 - fy) + bottom * fy);
        }
    }
    out
}

/// Catmull-Rom weights (the cubic with a = −0.5, as OpenCV's and PIL's
/// bicubic) of the four taps around fraction `t`.
fn cubic_weights(t: f64) -> [f64; 4] {
    let a = -0.5;
    let near = |x: f64| ((a + 2.0) * x - (a + 3.0)) * x * x + 1.0;
    let far = |x: f64| ((a * x - 5.0 * a) * x + 8.0 * a) * x - 4.0 * a;
    [far(t + 1.0), near(t), near(1.0 - t), far(2.0 - t)]
}

/// Per output index: the first of its four source taps and their weights.
fn cubic_taps(n: usize, on: usize) -> Vec<([usize; 4], [f64; 4])> {
    (0..on)
        .map(|o| {
            let x = (o as f64 + 0.5) * n as f64 / on as f64 - 0.5;
            let base = x.floor();
            let at = |k: i64| (base as i64 + k).clamp(0, n as i64 - 1) as usize;
            ([at(-1), at(0), at(1), at(2)], cubic_weights(x - base))
        })
        .collect()
}

/// An RGB image of `w × h` at `ow × oh`, bicubic (Catmull-Rom), pixel
/// centres to pixel centres, edges clamped: the floor a full-size frame is
/// measured against (`upsampled_64` in `worldpack eval`).
pub fn bicubic(rgb: &[u8], w: usize, h: usize, ow: usize, oh: usize) -> Vec<u8> {
    let (xs, ys) = (cubic_taps(w, ow), cubic_taps(h, oh));
    // Rows first (h × ow), then columns.
    let mut rows = vec![0.0f32; h * ow * 3];
    for y in 0..h {
        for (u, (ix, wx)) in xs.iter().enumerate() {
            for c in 0..3 {
                let s: f64 = (0..4).map(|k| wx[k] * rgb[(y * w + ix[k]) * 3 + c] as f64).sum();
                rows[(y * ow + u) * 3 + c] = s as f32;
            }
        }
    }
    let mut out = vec![0u8; ow * oh * 3];
    for (v, (iy, wy)) in ys.iter().enumerate() {
        for u in 0..ow {
            for c in 0..3 {
                let s: f64 = (0..4).map(|k| wy[k] * rows[(iy[k] * ow + u) * 3 + c] as f64).sum();
                out[(v * ow + u) * 3 + c] = s.round().clamp(0.0, 255.0) as u8;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{DMat3, DVec3};
    use memory::Intrinsics;

    fn camera(side: u32) -> Intrinsics {
        Intrinsics::from_fov(70.0, None, side, side).unwrap()
    }

    /// A wall 2 m ahead with a fine checker on it (detail a 16×16 frame cannot hold).
    fn checker(side: usize) -> (Vec<u8>, Vec<u16>) {
        let rgb = (0..side * side).flat_map(|p| if (p % side + p / side).is_multiple_of(2) { [200, 60, 30] } else { [40, 90, 220] }).collect();
        (rgb, vec![2000; side * side])
    }

    fn box_down(rgb: &[u8], w: usize, f: usize) -> Vec<u8> {
        let sw = w / f;
        (0..sw * sw)
            .flat_map(|p| {
                let (x, y) = (p % sw, p / sw);
                (0..3).map(move |c| {
                    let s: u32 = (0..f * f).map(|q| rgb[((y * f + q / f) * w + x * f + q % f) * 3 + c] as u32).sum();
                    (s / (f * f) as u32) as u8
                })
            })
            .collect()
    }

    #[test]
    fn bicubic_keeps_flat_images_and_matches_a_constant_at_any_size() {
        let flat = vec![77u8; 5 * 3 * 3];
        assert!(bicubic(&flat, 5, 3, 17, 11).iter().all(|&v| v == 77));
        // Up and down by the same factor: a smooth ramp comes back within rounding.
        let ramp: Vec<u8> = (0..16 * 16).flat_map(|p| [(p % 16 * 8) as u8; 3]).collect();
        let there = bicubic(&ramp, 16, 16, 64, 64);
        let back = box_down(&there, 64, 4);
        let worst = ramp.iter().zip(&back).skip(3 * 16).take(3 * 16 * 14).map(|(&a, &b)| (a as i32 - b as i32).abs()).max().unwrap();
        assert!(worst <= 2, "{worst}");
    }

    #[test]
    fn where_memory_lands_and_agrees_the_stored_pixels_are_shown() {
        let (side, small) = (64, 16);
        let (rgb, depth) = checker(side);
        let k = camera(side as u32);
        let pose = Pose::from_position(DVec3::ZERO);
        let model_frame = box_down(&rgb, side, side / small);
        let src = WarpSource { rgb: &rgb, depth_mm: &depth, pose: &pose, intrinsics: &k };
        let out = full_size_frame(&model_frame, small as u32, small as u32, &[src], &pose, side as u32, side as u32, &FullSize::default()).unwrap();
        assert_eq!(out.rgb, rgb, "standing where the stored frame was taken shows it exactly");
        assert!(out.warp_share > 0.99);
        let up = bicubic(&model_frame, small, small, side, side);
        assert_ne!(up, rgb, "the model's frame alone cannot show the checker");
    }

    #[test]
    fn where_the_model_disagrees_or_memory_has_nothing_the_model_frame_is_shown() {
        let (side, small) = (64, 16);
        let (rgb, depth) = checker(side);
        let k = camera(side as u32);
        let pose = Pose::from_position(DVec3::ZERO);
        let src = WarpSource { rgb: &rgb, depth_mm: &depth, pose: &pose, intrinsics: &k };
        let grey = vec![128u8; small * small * 3];
        let up = bicubic(&grey, small, small, side, side);
        let disagree = full_size_frame(&grey, small as u32, small as u32, &[src], &pose, side as u32, side as u32, &FullSize { agree_luma: 5.0, ..FullSize::default() }).unwrap();
        assert_eq!((disagree.rgb.clone(), disagree.warp_share), (up.clone(), 0.0), "the checker's mean is far from grey");
        let none = full_size_frame(&grey, small as u32, small as u32, &[], &pose, side as u32, side as u32, &FullSize::default()).unwrap();
        assert_eq!(none.rgb, up);
        // Turned 90° away, nothing lands: all the model's.
        let turned = Pose::new(DMat3::from_rotation_y(std::f64::consts::FRAC_PI_2), DVec3::ZERO).unwrap();
        let model_frame = box_down(&rgb, side, side / small);
        let away = full_size_frame(&model_frame, small as u32, small as u32, &[src], &turned, side as u32, side as u32, &FullSize::default()).unwrap();
        assert_eq!(away.warp_share, 0.0);
    }

    #[test]
    fn a_models_serving_block_names_its_rule_and_flags_replace_fields_of_it() {
        let serving: crate::manifest::ServingSpec = serde_json::from_str(r#"{"full_size": {"agree_luma": 255, "frames": 32}}"#).unwrap();
        let rule = FullSize::of(Some(&serving));
        assert_eq!((rule.agree_luma, rule.frames, rule.min_cover), (255.0, 32, FullSize::default().min_cover));
        let any_cover: crate::manifest::ServingSpec = serde_json::from_str(r#"{"full_size": {"agree_luma": 9, "frames": 2, "min_cover": 0}}"#).unwrap();
        assert_eq!(FullSize::of(Some(&any_cover)).min_cover, 0.0);
        assert_eq!(FullSize::of(None), FullSize::default());
        assert_eq!(rule.with(None, Some(4)).frames, 4);
        assert_eq!(rule.with(Some(12.0), None), FullSize { agree_luma: 12.0, ..rule });
        assert!(serde_json::from_str::<crate::manifest::ServingSpec>(r#"{"full_size": {"agree": 1, "frames": 2}}"#).is_err(), "a misspelt field is refused");
    }

    #[test]
    fn sources_of_another_size_are_refused_by_field() {
        let (rgb, depth) = checker(32);
        let k = camera(32);
        let pose = Pose::from_position(DVec3::ZERO);
        let src = WarpSource { rgb: &rgb, depth_mm: &depth, pose: &pose, intrinsics: &k };
        let err = full_size_frame(&[0; 16 * 16 * 3], 16, 16, &[src], &pose, 64, 64, &FullSize::default()).unwrap_err();
        assert!(err.to_string().contains("warp.intrinsics"), "{err}");
        let err = full_size_frame(&[0; 10], 16, 16, &[], &pose, 64, 64, &FullSize::default()).unwrap_err();
        assert!(err.to_string().contains("frame"), "{err}");
    }
}
