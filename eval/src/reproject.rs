//! The non-learned references that know geometry: forward-warp stored
//! frames into the target pose with their depth (`model::warp`, the same
//! warp a geometry model is given). If a model cannot beat these, it is
//! bigger than the scene needs.

use memory::{Intrinsics, Pose};
use model::warp::{Warped, forward_warp_many};
use model::WarpSource;

/// `src` (RGB) with its depth, seen from `src_pose`, as the camera at
/// `dst_pose` would see it: the warp, and what stays empty (newly revealed,
/// cracks) keeps the source pixel, so the result degrades to a copy.
/// (Filling cracks from neighbouring surfaces measured worse on the return
/// leg of aba-r30-000: 22.0 against 22.4 dB from the previous frame.)
/// Returns the image and the fraction of target pixels hit by a warped point.
pub fn reproject(src: &[u8], depth_mm: &[u16], k: &Intrinsics, src_pose: &Pose, dst_pose: &Pose) -> (Vec<u8>, f64) {
    let source = WarpSource { rgb: src, depth_mm, pose: src_pose, intrinsics: k };
    let warped = forward_warp_many(&[source], dst_pose).expect("reproject: the frame and depth match the intrinsics");
    let hit = warped.coverage();
    (keep_source_in_holes(warped, src), hit)
}

/// The fused reference: the `sources` (best first) behind one z-buffer,
/// holes filled from warped neighbours over up to [`FILL_ROUNDS`] rounds,
/// what is still empty from the best frame's own pixel.
pub fn reproject_fused(sources: &[WarpSource], dst_pose: &Pose) -> (Vec<u8>, f64) {
    let mut warped = forward_warp_many(sources, dst_pose).expect("reproject_fused: frames and depth match their intrinsics");
    let hit = warped.coverage();
    let k = sources[0].intrinsics;
    fill_from_neighbours(&mut warped, k.width as usize, k.height as usize, FILL_ROUNDS);
    (keep_source_in_holes(warped, sources[0].rgb), hit)
}

/// Rounds of neighbour filling in [`reproject_fused`]: splatting at the same
/// resolution leaves one- and two-pixel cracks, which two rounds close.
pub const FILL_ROUNDS: usize = 2;

fn keep_source_in_holes(mut warped: Warped, src: &[u8]) -> Vec<u8> {
    for (p, &m) in warped.mask.iter().enumerate() {
        if !m {
            warped.rgb[3 * p..3 * p + 3].copy_from_slice(&src[3 * p..3 * p + 3]);
        }
    }
    warped.rgb
}

/// Each hole with at least two warped 4-neighbours takes their mean; repeated `rounds` times.
fn fill_from_neighbours(warped: &mut Warped, w: usize, h: usize, rounds: usize) {
    for _ in 0..rounds {
        let before = warped.clone();
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
                    warped.rgb[3 * p + c] = ((sum + valid.len() as u32 / 2) / valid.len() as u32) as u8;
                }
                warped.mask[p] = true;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{DMat3, DVec3};

    fn camera() -> Intrinsics {
        Intrinsics::from_fov(70.0, Some(70.0), 32, 32).unwrap()
    }

    /// A textured wall 5 m in front of the source camera.
    fn wall() -> (Vec<u8>, Vec<u16>) {
        let rgb = (0..32 * 32).flat_map(|i| [(i % 32 * 8) as u8, (i / 32 * 8) as u8, 50]).collect();
        (rgb, vec![5000; 32 * 32])
    }

    #[test]
    fn same_pose_is_the_identity() {
        let (rgb, depth) = wall();
        let pose = Pose::from_position(DVec3::new(1.0, 2.0, 3.0));
        let (out, hit) = reproject(&rgb, &depth, &camera(), &pose, &pose);
        assert_eq!(out, rgb);
        assert_eq!(hit, 1.0);
    }

    #[test]
    fn a_sideways_step_shifts_the_wall_by_the_parallax() {
        let (rgb, depth) = wall();
        let k = camera();
        let src = Pose::from_position(DVec3::ZERO);
        // One metre right at 5 m: the wall moves fx/5 pixels left in the image.
        let dst = Pose::new(DMat3::IDENTITY, DVec3::new(1.0, 0.0, 0.0)).unwrap();
        let (out, hit) = reproject(&rgb, &depth, &k, &src, &dst);
        let shift = (k.fx / 5.0).round() as usize;
        for v in [0usize, 10, 31] {
            for u in 0..32 - shift {
                let (i, j) = (v * 32 + u, v * 32 + u + shift);
                assert_eq!(out[3 * i..3 * i + 3], rgb[3 * j..3 * j + 3], "pixel ({u}, {v})");
            }
        }
        // The uncovered strip on the right keeps the source pixels.
        let right = 31 * 32 + 31;
        assert_eq!(out[3 * right..3 * right + 3], rgb[3 * right..3 * right + 3]);
        assert!((hit - (32.0 - shift as f64) / 32.0).abs() < 0.05, "{hit}");
    }

    #[test]
    fn fusing_a_second_view_fills_what_the_first_never_saw() {
        let (rgb, depth) = wall();
        let k = camera();
        let (left, right) = (Pose::from_position(DVec3::new(-1.0, 0.0, 0.0)), Pose::from_position(DVec3::new(1.0, 0.0, 0.0)));
        let dst = Pose::from_position(DVec3::ZERO);
        let one = [WarpSource { rgb: &rgb, depth_mm: &depth, pose: &left, intrinsics: &k }];
        let both = [one[0], WarpSource { rgb: &rgb, depth_mm: &depth, pose: &right, intrinsics: &k }];
        let (_, hit_one) = reproject_fused(&one, &dst);
        let (_, hit_both) = reproject_fused(&both, &dst);
        assert!(hit_one < 0.9 && hit_both > 0.99, "one view covers {hit_one}, two cover {hit_both}");
    }

    #[test]
    fn cracks_are_filled_from_their_neighbours() {
        let mut w = Warped { rgb: vec![100; 3 * 9], mask: vec![true; 9], depth: vec![1.0; 9] };
        w.mask[4] = false;
        w.rgb[12..15].copy_from_slice(&[0, 0, 0]);
        fill_from_neighbours(&mut w, 3, 3, 1);
        assert!(w.mask[4]);
        assert_eq!(&w.rgb[12..15], &[100, 100, 100]);
    }
}
