//! The non-learned references that know geometry: forward-warp stored
//! frames into the target pose with their depth (`model::warp`, the same
//! warp a geometry model is given). If a model cannot beat these, it is
//! bigger than the scene needs.

use memory::{Intrinsics, Pose};
use model::warp::{forward_warp_many, fused_reference};
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
    (warped.or_source(src), hit)
}

/// The fused reference (`model::warp::fused_reference`) and the fraction of
/// target pixels the warp itself covers.
pub fn reproject_fused(sources: &[WarpSource], dst_pose: &Pose) -> (Vec<u8>, f64) {
    let (rgb, mask) = fused_reference(sources, dst_pose).expect("reproject_fused: frames and depth match their intrinsics");
    (rgb, mask.iter().filter(|&&m| m).count() as f64 / mask.len().max(1) as f64)
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
}
