//! The depth warp a geometry model is conditioned on: a stored frame, with
//! its depth, splatted into the target camera. The trainer has the same warp
//! (`train/worldpack_train/core/warp.py`); the parity test checks the two
//! against the cases the export wrote. Float64 throughout, computed in the
//! same order as the trainer, so both round the same way.

use glam::{DMat3, DVec3};
use memory::{Intrinsics, Pose};

use crate::error::ModelError;

/// Depth maps hold millimetres along the optical axis; 0 where nothing lies within range.
pub const DEPTH_UNIT_M: f64 = 1e-3;
/// The z-buffer key of a direction at infinity (plus its pixel index): behind every surface.
const SKY_KEY: f64 = 1e12;

/// A stored frame a warp is made from.
#[derive(Clone, Copy, Debug)]
pub struct WarpSource<'a> {
    /// Row-major RGB, 3 bytes a pixel, at the intrinsics' size.
    pub rgb: &'a [u8],
    /// Millimetres, one per pixel; 0 = nothing within range (sky).
    pub depth_mm: &'a [u16],
    pub pose: &'a Pose,
    pub intrinsics: &'a Intrinsics,
}

/// A warped frame: RGB (0 in holes), which pixels something landed on, and
/// the depth of what landed (metres along the target's optical axis;
/// infinity for sky, 0 in holes): a generated view's depth, made from the
/// observed frames' own.
#[derive(Clone, Debug, PartialEq)]
pub struct Warped {
    pub rgb: Vec<u8>,
    pub mask: Vec<bool>,
    pub depth: Vec<f64>,
}

impl Warped {
    /// The share of pixels the warp covers.
    pub fn coverage(&self) -> f64 {
        self.mask.iter().filter(|&&m| m).count() as f64 / self.mask.len().max(1) as f64
    }

    /// `image` (RGB, the warp's size) with the warp's pixels wherever something landed.
    pub fn overlay(&self, mut image: Vec<u8>) -> Vec<u8> {
        for (p, &m) in self.mask.iter().enumerate() {
            if m {
                image[3 * p..3 * p + 3].copy_from_slice(&self.rgb[3 * p..3 * p + 3]);
            }
        }
        image
    }

    /// The warp's RGB with what nothing landed on taken from `src` (same size).
    pub fn or_source(mut self, src: &[u8]) -> Vec<u8> {
        for (p, &m) in self.mask.iter().enumerate() {
            if !m {
                self.rgb[3 * p..3 * p + 3].copy_from_slice(&src[3 * p..3 * p + 3]);
            }
        }
        self.rgb
    }

    /// [`fused_reference`] from the warp of its sources, `best` the first of
    /// them: the image, and where the warp itself landed.
    pub fn into_reference(mut self, best: &WarpSource) -> (Vec<u8>, Vec<bool>) {
        let landed = self.mask.clone();
        self.fill_cracks(best.intrinsics.width as usize, best.intrinsics.height as usize, FILL_ROUNDS);
        (self.or_source(best.rgb), landed)
    }

    /// Each hole with at least two landed 4-neighbours takes their mean and
    /// counts as landed; repeated `rounds` times.
    pub(crate) fn fill_cracks(&mut self, w: usize, h: usize, rounds: usize) {
        for _ in 0..rounds {
            let before = self.clone();
            for y in 0..h {
                for x in 0..w {
                    let p = y * w + x;
                    if before.mask[p] {
                        continue;
                    }
                    let near = [(x > 0).then(|| p - 1), (x + 1 < w).then(|| p + 1), (y > 0).then(|| p - w), (y + 1 < h).then(|| p + w)];
                    let valid: Vec<usize> = near.into_iter().flatten().filter(|&q| before.mask[q]).collect();
                    if valid.len() < 2 {
                        continue;
                    }
                    for c in 0..3 {
                        let sum: u32 = valid.iter().map(|&q| before.rgb[3 * q + c] as u32).sum();
                        self.rgb[3 * p + c] = ((sum + valid.len() as u32 / 2) / valid.len() as u32) as u8;
                    }
                    self.mask[p] = true;
                }
            }
        }
    }
}

/// Rounds of crack filling in [`fused_reference`]: splatting at the same
/// resolution leaves one- and two-pixel cracks, which two rounds close.
pub const FILL_ROUNDS: usize = 2;

/// In [`fused_warp`], a source takes a pixel an earlier (better) one landed
/// on only when it is nearer by more than this share of the depth. The same
/// surface seen from two frames lands at nearly the same depth, and a plain
/// z-buffer then picks between them by rounding: where depth is coarse (Doom's
/// 8-bit buffer has 22 cm steps) the worse views win part of the surface, and
/// the best frame's view is spoilt even where it is exact. On the held-out
/// Doom walks the fused warp went from 25.64 to 28.76 dB (0.05: 26.65, 0.3:
/// 28.77); a true occluder is nearer by far more than 15%.
pub const REFERENCE_MARGIN: f64 = 0.15;

/// A warp source moved to `width × height` (the model's frame size), owned:
/// colour sampled bilinearly as the encoder's input is, depth taken from the
/// nearest source pixel (an average across an edge would put a surface where
/// none is), the intrinsics scaled to match. Frames of any size a client
/// observes can then be warped into the model's view.
pub fn resampled(src: &WarpSource, width: u32, height: u32) -> Result<(Vec<u8>, Vec<u16>, Intrinsics), ModelError> {
    let k = src.intrinsics;
    let (w, h, ow, oh) = (k.width as usize, k.height as usize, width as usize, height as usize);
    if src.rgb.len() != w * h * 3 || src.depth_mm.len() != w * h {
        return Err(ModelError::input("warp", format!("a source's pixels do not match its {w}x{h} intrinsics")));
    }
    let k2 = k.resized(width, height).map_err(|e| ModelError::input("warp", e.to_string()))?;
    let mut rgb = vec![0u8; ow * oh * 3];
    crate::generate::bilinear(src.rgb, w, h, ow, oh, |u, v, c, value| rgb[(v * ow + u) * 3 + c] = value.round() as u8);
    let nearest = |o: usize, n: usize, on: usize| (((o as f64 + 0.5) * n as f64 / on as f64) as usize).min(n - 1);
    let depth = (0..oh).flat_map(|v| (0..ow).map(move |u| (u, v))).map(|(u, v)| src.depth_mm[nearest(v, h, oh) * w + nearest(u, w, ow)]).collect();
    Ok((rgb, depth, k2))
}

/// The fused reference: [`fused_warp`] with cracks filled from their
/// neighbours over [`FILL_ROUNDS`] rounds, what is still empty the best
/// frame's own pixel. The probe's strongest non-learned row, and what a
/// fusion head blends with the model's frame. Returns the image and where the
/// warp itself landed (before filling).
pub fn fused_reference(sources: &[WarpSource], dst: &Pose) -> Result<(Vec<u8>, Vec<bool>), ModelError> {
    Ok(fused_warp(sources, dst)?.into_reference(&sources[0]))
}

/// `sources` (best first) warped into `dst` behind one z-buffer that favours
/// earlier sources by [`REFERENCE_MARGIN`]: what the fused reference and the
/// composite (the warp where it lands, a model's frame in its holes) show.
pub fn fused_warp(sources: &[WarpSource], dst: &Pose) -> Result<Warped, ModelError> {
    warp_behind(sources, dst, REFERENCE_MARGIN)
}

/// Whether `src` stands at `dst`'s pose (within 1 mm and 0.01°): its warp
/// moves no pixel, so in a static world it is the view at `dst` exactly.
pub fn stands_at(src: &Pose, dst: &Pose) -> bool {
    let turn = (src.rotation().transpose() * dst.rotation()).to_cols_array();
    let trace = turn[0] + turn[4] + turn[8];
    (src.position() - dst.position()).length() <= 1e-3 && trace >= 1.0 + 2.0 * 0.01f64.to_radians().cos()
}

/// A depth map in this module's millimetres (0: nothing in range), pooled to
/// the coarse grid occlusion-aware selection reads (`memory::covisibility`).
pub fn coarse_depth(depth_mm: &[u16], intrinsics: &Intrinsics, cells: u32) -> Result<memory::covisibility::DepthGrid, memory::InputError> {
    let metres: Vec<f32> = depth_mm.iter().map(|&mm| (mm as f64 * DEPTH_UNIT_M) as f32).collect();
    memory::covisibility::DepthGrid::pool(&metres, intrinsics, cells)
}

/// `src` as the camera at `dst` would see it. Each source pixel lands on the
/// target pixel nearest its projection (`floor(x + 0.5)`) behind a z-buffer;
/// ties go to the earlier pixel in row-major order. A pixel with depth 0 is
/// warped as a direction at infinity (rotation only) and loses to every
/// surface. Pixels nothing lands on are holes.
pub fn forward_warp(src: &WarpSource, dst: &Pose) -> Result<Warped, ModelError> {
    forward_warp_many(std::slice::from_ref(src), dst)
}

/// Several frames warped into `dst` behind one z-buffer (ties go to the
/// earlier frame); every source must share the first one's image size.
pub fn forward_warp_many(sources: &[WarpSource], dst: &Pose) -> Result<Warped, ModelError> {
    warp_behind(sources, dst, 0.0)
}

/// [`forward_warp_many`] where a source takes a pixel an earlier (better)
/// source landed on only when nearer by more than `margin`, a share of the
/// depth; within one source the z-test is plain.
fn warp_behind(sources: &[WarpSource], dst: &Pose, margin: f64) -> Result<Warped, ModelError> {
    Ok(Landings::of(sources, dst)?.resolve(margin))
}

/// Where every pixel of some sources lands in one target view, in the order
/// the z-test takes them (source by source, row-major). Projecting is most of
/// a warp's work; the model's warp input and the fused reference of one step
/// differ only in their depth test, so they project once and resolve twice.
#[derive(Clone, Debug)]
pub struct Landings {
    width: usize,
    height: usize,
    hits: Vec<Landing>,
}

#[derive(Clone, Copy, Debug)]
struct Landing {
    /// The target pixel, row-major.
    to: u32,
    /// The source it came from, best first.
    source: u16,
    sky: bool,
    rgb: [u8; 3],
    /// The z-buffer key: depth along the target's axis, or a sky key.
    key: f64,
}

impl Landings {
    /// `sources` (best first, one image size) projected into `dst`. Each
    /// source pixel lands on the target pixel nearest its projection
    /// (`floor(x + 0.5)`); a pixel with depth 0 is a direction at infinity
    /// (rotation only).
    pub fn of(sources: &[WarpSource], dst: &Pose) -> Result<Landings, ModelError> {
        let Some(first) = sources.first() else { return Err(ModelError::input("warp", "no frame to warp")) };
        let (w, h) = (first.intrinsics.width as usize, first.intrinsics.height as usize);
        if sources.len() >= u16::MAX as usize {
            return Err(ModelError::input("warp", format!("{} frames in one warp; at most {}", sources.len(), u16::MAX - 1)));
        }
        let mut hits = Vec::with_capacity(sources.len() * w * h);
        for (n, src) in sources.iter().enumerate() {
            let k = src.intrinsics;
            if (k.width as usize, k.height as usize) != (w, h) {
                return Err(ModelError::input("warp.intrinsics", format!("frames of {}x{} and {w}x{h} in one warp", k.width, k.height)));
            }
            project(src, n as u16, dst, &mut hits)?;
        }
        Ok(Landings { width: w, height: h, hits })
    }

    /// The warp behind one z-buffer where a source takes a pixel an earlier
    /// (better) source landed on only when nearer by more than `margin`, a
    /// share of the depth; within one source the z-test is plain, and ties go
    /// to the earlier pixel.
    pub fn resolve(&self, margin: f64) -> Warped {
        let n = self.width * self.height;
        let mut zbuffer = ZBuffer { key: vec![f64::INFINITY; n], owner: vec![u16::MAX; n], margin };
        let mut out = Warped { rgb: vec![0; n * 3], mask: vec![false; n], depth: vec![0.0; n] };
        for hit in &self.hits {
            let j = hit.to as usize;
            if zbuffer.take(j, hit.key, hit.source) {
                out.rgb[3 * j..3 * j + 3].copy_from_slice(&hit.rgb);
                out.mask[j] = true;
                out.depth[j] = if hit.sky { f64::INFINITY } else { hit.key };
            }
        }
        out
    }
}

/// The depth test of a warp of several sources: each pixel's key (depth, or
/// a sky key; infinity while empty, so any source takes an empty pixel) and
/// the source that set it.
struct ZBuffer {
    key: Vec<f64>,
    owner: Vec<u16>,
    margin: f64,
}

impl ZBuffer {
    /// Whether source `n` at `key` takes pixel `j`; it does when it wins.
    fn take(&mut self, j: usize, key: f64, n: u16) -> bool {
        let wins = key < if self.owner[j] != n { self.key[j] * (1.0 - self.margin) } else { self.key[j] };
        if wins {
            self.key[j] = key;
            self.owner[j] = n;
        }
        wins
    }
}

/// Source number `n`'s pixels that land in `dst`'s view, appended to `hits`.
fn project(src: &WarpSource, n: u16, dst: &Pose, hits: &mut Vec<Landing>) -> Result<(), ModelError> {
    let k = src.intrinsics;
    let (w, h) = (k.width as usize, k.height as usize);
    if src.rgb.len() != w * h * 3 {
        return Err(ModelError::input("warp.rgb", format!("{} bytes for a {w}x{h} RGB frame", src.rgb.len())));
    }
    if src.depth_mm.len() != w * h {
        return Err(ModelError::input("warp.depth", format!("{} values for a {w}x{h} depth map", src.depth_mm.len())));
    }
    let (rs, ts) = (src.pose.rotation(), src.pose.position());
    let (rd_t, td) = (dst.rotation().transpose(), dst.position());
    for v in 0..h {
        for u in 0..w {
            let i = v * w + u;
            let ray = DVec3::new((u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy, 1.0);
            let turned = mul(&rs, ray);
            let sky = src.depth_mm[i] == 0;
            let q = if sky {
                mul(&rd_t, turned)
            } else {
                let world = turned * (src.depth_mm[i] as f64 * DEPTH_UNIT_M) + ts;
                mul(&rd_t, world - td)
            };
            let ahead = if sky { q.z > 1e-9 } else { q.z > k.near };
            if !ahead {
                continue;
            }
            // floor(x + 0.5) within [0, w) is x + 0.5 in [0, w) truncated
            // (floor is a library call on the baseline x86-64 target).
            let x = k.fx * q.x / q.z + k.cx + 0.5;
            let y = k.fy * q.y / q.z + k.cy + 0.5;
            if !(x >= 0.0 && y >= 0.0 && x < w as f64 && y < h as f64) {
                continue;
            }
            let j = y as usize * w + x as usize;
            let p = 3 * i;
            hits.push(Landing {
                to: j as u32,
                source: n,
                sky,
                rgb: [src.rgb[p], src.rgb[p + 1], src.rgb[p + 2]],
                key: if sky { SKY_KEY + i as f64 } else { q.z },
            });
        }
    }
    Ok(())
}

/// `m · v` summed left to right, as the trainer's einsum does.
fn mul(m: &DMat3, v: DVec3) -> DVec3 {
    let r = |i: usize| m.col(0)[i] * v.x + m.col(1)[i] * v.y + m.col(2)[i] * v.z;
    DVec3::new(r(0), r(1), r(2))
}

/// The image the encoder sees, (3, H, W) planar in [-1, 1] with holes 0.
pub fn warped_image(warped: &Warped) -> Vec<f32> {
    let n = warped.mask.len();
    let mut out = vec![0.0f32; 3 * n];
    for (p, &m) in warped.mask.iter().enumerate() {
        if m {
            for c in 0..3 {
                out[c * n + p] = warped.rgb[3 * p + c] as f32 / 127.5 - 1.0;
            }
        }
    }
    out
}

/// The mask's share per `factor`×`factor` cell, (H/f, W/f) row-major.
pub fn coverage_grid(mask: &[bool], width: usize, height: usize, factor: usize) -> Vec<f32> {
    let (gw, gh) = (width / factor, height / factor);
    let mut out = vec![0.0f32; gw * gh];
    for y in 0..gh * factor {
        for x in 0..gw * factor {
            if mask[y * width + x] {
                out[(y / factor) * gw + x / factor] += 1.0;
            }
        }
    }
    let cell = (factor * factor) as f32;
    out.iter_mut().for_each(|v| *v /= cell);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> Intrinsics {
        Intrinsics::from_fov(70.0, Some(70.0), 32, 32).unwrap()
    }

    /// A textured wall 5 m ahead, with sky above its top quarter.
    fn wall() -> (Vec<u8>, Vec<u16>) {
        let rgb = (0..32 * 32).flat_map(|i| [(i % 32 * 8) as u8, (i / 32 * 8) as u8, 77]).collect();
        let depth = (0..32 * 32).map(|i| if i / 32 < 8 { 0 } else { 5000 }).collect();
        (rgb, depth)
    }

    #[test]
    fn same_pose_is_the_identity_and_covers_everything() {
        let (rgb, depth) = wall();
        let k = camera();
        let pose = Pose::from_position(DVec3::ZERO);
        let src = WarpSource { rgb: &rgb, depth_mm: &depth, pose: &pose, intrinsics: &k };
        let out = forward_warp(&src, &pose).unwrap();
        assert_eq!(out.rgb, rgb);
        assert_eq!(out.coverage(), 1.0);
        assert_eq!((out.depth[0], out.depth[20 * 32]), (f64::INFINITY, 5.0), "sky at infinity, the wall where it was");
    }

    #[test]
    fn a_source_resampled_to_half_size_averages_colour_and_keeps_depth_edges() {
        let (rgb, depth) = wall();
        let k = camera();
        let pose = Pose::from_position(DVec3::ZERO);
        let src = WarpSource { rgb: &rgb, depth_mm: &depth, pose: &pose, intrinsics: &k };
        let (small, small_depth, k2) = resampled(&src, 16, 16).unwrap();
        assert_eq!((k2.width, k2.height, small.len(), small_depth.len()), (16, 16, 16 * 16 * 3, 16 * 16));
        assert!((k2.fx - k.fx / 2.0).abs() < 1e-9);
        // Output pixel (3, 5) sits between source columns 6 and 7, rows 10 and 11: their mean.
        let at = (5 * 16 + 3) * 3;
        assert_eq!(&small[at..at + 2], &[(6 * 8 + 7 * 8) / 2, (10 * 8 + 11 * 8) / 2]);
        // Depth is never a mix of the sky (0) and the wall (5000) at the wall's top edge.
        assert!(small_depth.iter().all(|&d| d == 0 || d == 5000));
        assert_eq!((small_depth[3 * 16], small_depth[4 * 16]), (0, 5000));
        // Warped to its own pose, the half-size source is itself.
        let half = WarpSource { rgb: &small, depth_mm: &small_depth, pose: &pose, intrinsics: &k2 };
        assert_eq!(forward_warp(&half, &pose).unwrap().rgb, small);
    }

    #[test]
    fn stepping_back_opens_holes_and_sideways_shifts_by_the_parallax() {
        let (rgb, depth) = wall();
        let k = camera();
        let src_pose = Pose::from_position(DVec3::ZERO);
        let src = WarpSource { rgb: &rgb, depth_mm: &depth, pose: &src_pose, intrinsics: &k };
        // 1 m to the right: the wall (5 m) moves fx/5 pixels left; the sky does not move.
        let right = Pose::from_position(DVec3::new(1.0, 0.0, 0.0));
        let out = forward_warp(&src, &right).unwrap();
        let shift = (k.fx / 5.0).round() as usize;
        let row = 20 * 32;
        assert_eq!(out.rgb[3 * (row + 10)], rgb[3 * (row + 10 + shift)]);
        assert_eq!(out.rgb[3 * (2 * 32 + 10)], rgb[3 * (2 * 32 + 10)], "sky is at infinity");
        assert!(!out.mask[row + 31], "the right edge was never seen");
        // Moving forward magnifies the wall: splatting leaves cracks, never out-of-range pixels.
        let ahead = Pose::from_position(DVec3::new(0.0, 0.0, 2.0));
        let near = forward_warp(&src, &ahead).unwrap();
        assert!(near.coverage() < 0.9 && near.coverage() > 0.2, "coverage {}", near.coverage());
    }

    #[test]
    fn a_wrong_sized_source_is_refused_by_field() {
        let (rgb, depth) = wall();
        let k = camera();
        let pose = Pose::from_position(DVec3::ZERO);
        let src = WarpSource { rgb: &rgb[..30], depth_mm: &depth, pose: &pose, intrinsics: &k };
        assert!(forward_warp(&src, &pose).unwrap_err().to_string().contains("warp.rgb"));
    }

    #[test]
    fn coverage_pools_cells() {
        let mut mask = vec![false; 16];
        mask[0] = true;
        mask[1] = true;
        mask[15] = true;
        assert_eq!(coverage_grid(&mask, 4, 4, 2), vec![0.5, 0.0, 0.0, 0.25]);
    }

    #[test]
    fn the_reference_keeps_the_best_view_of_a_surface_but_not_of_an_occluder() {
        let k = camera();
        let pose = Pose::from_position(DVec3::ZERO);
        let (best_rgb, depth) = wall();
        let other_rgb = vec![9; best_rgb.len()];
        // The other frame sees the same wall 5% nearer (coarse depth): the best frame keeps it.
        let near: Vec<u16> = depth.iter().map(|&d| (d as u32 * 95 / 100) as u16).collect();
        let best = WarpSource { rgb: &best_rgb, depth_mm: &depth, pose: &pose, intrinsics: &k };
        let other = WarpSource { rgb: &other_rgb, depth_mm: &near, ..best };
        let (rgb, _) = fused_reference(&[best, other], &pose).unwrap();
        assert!(rgb == best_rgb, "the best frame lost pixels of the same surface");
        assert_eq!(forward_warp_many(&[best, other], &pose).unwrap().rgb[3 * 20 * 32], 9, "a plain z-buffer takes the nearer");
        // An occluder at half the depth is nearer by far more than the margin: it wins.
        let occluder: Vec<u16> = depth.iter().map(|&d| d / 2).collect();
        let (rgb, _) = fused_reference(&[best, WarpSource { depth_mm: &occluder, ..other }], &pose).unwrap();
        assert_eq!(rgb[3 * 20 * 32], 9);
    }

    #[test]
    fn standing_at_a_pose_allows_a_millimetre_and_a_hundredth_of_a_degree() {
        let at = Pose::from_position(DVec3::new(1.0, 2.0, 3.0));
        assert!(stands_at(&at, &Pose::from_position(DVec3::new(1.0005, 2.0, 3.0))));
        assert!(!stands_at(&at, &Pose::from_position(DVec3::new(1.002, 2.0, 3.0))));
        let turned = |deg: f64| Pose::new(DMat3::from_rotation_y(deg.to_radians()), at.position()).unwrap();
        assert!(stands_at(&at, &turned(0.005)));
        assert!(!stands_at(&at, &turned(0.02)));
    }

    #[test]
    fn cracks_are_filled_from_their_neighbours() {
        let mut w = Warped { rgb: vec![100; 3 * 9], mask: vec![true; 9], depth: vec![1.0; 9] };
        w.mask[4] = false;
        w.rgb[12..15].copy_from_slice(&[0, 0, 0]);
        w.fill_cracks(3, 3, 1);
        assert!(w.mask[4]);
        assert_eq!(&w.rgb[12..15], &[100, 100, 100]);
    }
}
