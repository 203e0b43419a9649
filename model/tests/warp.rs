//! The geometry model's warp in Rust against the trainer's (the cases the
//! export wrote with PyTorch), and its warp input through the encoder.

use std::path::{Path, PathBuf};

use memory::{Intrinsics, Pose};
use model::warp::{Warped, forward_warp, forward_warp_many};
use model::{Model, Provider, RuntimeOptions, Tensor, WarpSource};

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures/variants/worldpack_geometry")
}

fn cases<T: world::npy::Element>(name: &str) -> (Vec<usize>, Vec<T>) {
    let path = fixture().join("reference/warp").join(format!("{name}.npy"));
    world::npy::read::<T>(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// A row-major 4×4 camera-to-world matrix, flattened.
fn pose(m: &[f64]) -> Pose {
    Pose::from_matrix_rows([0, 1, 2, 3].map(|i| [m[4 * i], m[4 * i + 1], m[4 * i + 2], m[4 * i + 3]])).expect("a reference pose is a proper rotation")
}

/// Frames `rgb` (N, H, W, 3) with their depth and poses, as warp sources.
fn sources<'a>(rgb: &'a [u8], depth: &'a [u16], poses: &'a [Pose], k: &'a Intrinsics) -> Vec<WarpSource<'a>> {
    let pixels = depth.len() / poses.len();
    (0..poses.len())
        .map(|i| WarpSource { rgb: &rgb[i * pixels * 3..(i + 1) * pixels * 3], depth_mm: &depth[i * pixels..(i + 1) * pixels], pose: &poses[i], intrinsics: k })
        .collect()
}

/// Pixels where our mask, and our colour, equal the reference's.
fn agreement(ours: &Warped, rgb: &[u8], mask: &[u8]) -> (usize, usize) {
    let same_mask = ours.mask.iter().zip(mask).filter(|(a, b)| **a == (**b == 1)).count();
    let same_rgb = ours.rgb.chunks(3).zip(rgb.chunks(3)).filter(|(a, b)| a == b).count();
    (same_mask, same_rgb)
}

/// The export's warp cases: source frames (N, H, W, 3) with depth, and the poses to warp between.
struct WarpCases {
    model: Model,
    k: Intrinsics,
    shape: Vec<usize>,
    rgb: Vec<u8>,
    depth: Vec<u16>,
    src: Vec<Pose>,
    dst: Vec<Pose>,
}

fn warp_cases() -> WarpCases {
    let model = Model::load(&fixture(), RuntimeOptions { provider: Provider::Cpu, threads: 1 }).expect("the geometry model loads");
    let k = model.manifest().intrinsics;
    let (shape, rgb) = cases::<u8>("rgb");
    let src = cases::<f64>("src_c2w").1.chunks(16).map(pose).collect();
    let dst = cases::<f64>("dst_c2w").1.chunks(16).map(pose).collect();
    WarpCases { model, k, shape, rgb, depth: cases::<u16>("depth_mm").1, src, dst }
}

#[test]
fn the_warp_and_its_encoding_match_the_trainer() {
    let WarpCases { model, k, shape, rgb, depth, src, dst } = warp_cases();
    let (_, warped) = cases::<u8>("warped");
    let (_, mask) = cases::<u8>("mask");
    let (n, pixels) = (shape[0], shape[1] * shape[2]);
    assert!(n >= 3, "the export writes a case per gap");
    let one_each = sources(&rgb, &depth, &src, &k);
    // Float64 in the same order on both sides: a projection landing exactly
    // on a rounding edge is the only way to disagree, and it is rare.
    for i in 0..n {
        let (m, c) = (&mask[i * pixels..(i + 1) * pixels], &warped[i * pixels * 3..(i + 1) * pixels * 3]);
        let covered = m.iter().filter(|&&v| v == 1).count();
        assert!(covered * 5 >= pixels, "case {i}: the reference warp covers too little to check ({covered} pixels)");
        let (same_mask, same_rgb) = agreement(&forward_warp(&one_each[i], &dst[i]).unwrap(), c, m);
        assert!(same_mask * 1000 >= pixels * 998 && same_rgb * 1000 >= pixels * 998, "case {i}: {same_mask} masks, {same_rgb} colours of {pixels} agree");
    }

    // Several frames behind one z-buffer, as the runtime fuses a manifest's `warp.frames`.
    let (_, frgb) = cases::<u8>("fused_rgb");
    let (_, fdepth) = cases::<u16>("fused_depth_mm");
    let fsrc: Vec<Pose> = cases::<f64>("fused_src_c2w").1.chunks(16).map(pose).collect();
    let fdst = pose(&cases::<f64>("fused_dst_c2w").1);
    let fused = sources(&frgb, &fdepth, &fsrc, &k);
    let ours = forward_warp_many(&fused, &fdst).unwrap();
    assert!(ours.coverage() > forward_warp(&fused[0], &fdst).unwrap().coverage(), "fusing covers more than the best frame alone");
    let (same_mask, same_rgb) = agreement(&ours, &cases::<u8>("fused_warped").1, &cases::<u8>("fused_mask").1);
    assert!(same_mask * 1000 >= pixels * 998 && same_rgb * 1000 >= pixels * 998, "fused: {same_mask} masks, {same_rgb} colours of {pixels} agree");

    // The encoded input: the warp through the model's encoder, then the coverage per latent cell.
    let items: Vec<_> = one_each.iter().zip(&dst).map(|(s, d)| (std::slice::from_ref(s), d)).collect();
    let ours = model.warp_input(&items).unwrap();
    let (in_shape, input) = cases::<f32>("input");
    assert_eq!(ours.shape, in_shape);
    let expected = Tensor::new(in_shape, input);
    let worst = ours.data.iter().zip(&expected.data).map(|(a, b)| (a - b).abs() - (1e-4 + 1e-3 * b.abs())).fold(f32::NEG_INFINITY, f32::max);
    assert!(worst <= 0.0, "the warp input exceeds the tolerance by {worst:e}");
    // Without a source, the input is the encoded empty image with zero coverage, as in training.
    let empty = model.warp_input(&[(&[], &dst[0])]).unwrap();
    let per = empty.data.len() / 5;
    assert!(empty.data[4 * per..].iter().all(|&c| c == 0.0));
}

/// Depth from a real sensor is noisy or partly missing. The warp must degrade
/// with it step by step, not fall apart: with multiplicative depth noise of
/// growing size, fewer and fewer pixels keep the colour the clean warp gives
/// them; with depth missing on a fifth of the pixels, most of the warp stays.
#[test]
fn noisy_or_missing_depth_degrades_the_warp_gracefully() {
    let WarpCases { k, shape, rgb, depth, src, dst, .. } = warp_cases();
    let pixels = shape[1] * shape[2];
    let mut rng = memory::rng::SplitMix64::new(7);
    for i in 0..shape[0] {
        let (frame, clean_depth) = (&rgb[i * pixels * 3..(i + 1) * pixels * 3], &depth[i * pixels..(i + 1) * pixels]);
        let warp = |d: &[u16]| forward_warp(&WarpSource { rgb: frame, depth_mm: d, pose: &src[i], intrinsics: &k }, &dst[i]).unwrap();
        let clean = warp(clean_depth);
        // Share of the clean warp's pixels that keep their colour.
        let kept = |w: &Warped| {
            let covered = clean.mask.iter().filter(|&&m| m).count().max(1);
            let same = (0..pixels).filter(|&p| clean.mask[p] && w.mask[p] && w.rgb[p * 3..p * 3 + 3] == clean.rgb[p * 3..p * 3 + 3]).count();
            same as f64 / covered as f64
        };
        let mut last = 1.0;
        for sigma in [0.01, 0.05, 0.2] {
            let noisy: Vec<u16> = clean_depth
                .iter()
                .map(|&d| if d == 0 { 0 } else { (d as f64 * (1.0 + sigma * (2.0 * rng.next_f64() - 1.0) * 1.732)).clamp(1.0, 65535.0) as u16 })
                .collect();
            let share = kept(&warp(&noisy));
            assert!(share <= last + 0.02, "case {i}: more noise ({sigma}) kept more ({share:.3} > {last:.3})");
            if sigma == 0.01 {
                // Measured: 0.78-0.98 of the clean warp over the four cases.
                assert!(share >= 0.7, "case {i}: 1% depth noise kept only {share:.3} of the clean warp");
            }
            last = share;
        }
        // A fifth of the depth missing (0 reads as nothing within range, so those
        // pixels move as if at infinity): most of the warp stays as it was.
        let holed: Vec<u16> = clean_depth.iter().map(|&d| if rng.next_f64() < 0.2 { 0 } else { d }).collect();
        let share = kept(&warp(&holed));
        assert!(share >= 0.7, "case {i}: with 20% of the depth missing only {share:.3} of the clean warp stays");
    }
}

/// One step ahead of the first reference source: its frame encoded by
/// `model` as the only context (the first full-rate slot of the WorldPack
/// layout), a forward action, and the warp cases to warp from.
struct OneStep {
    cases: WarpCases,
    first: Vec<u8>,
    latent: Vec<f32>,
    policy: memory::Policy,
    plan: memory::ContextPlan,
    action: [f32; 7],
}

/// `rgb`, a frame at the reference camera `k`, encoded by `model`.
fn encode_rgb(model: &Model, rgb: &[u8], k: &Intrinsics) -> Vec<f32> {
    model.encode(&model::generate::frame_to_tensor(rgb, k.width, k.height, k, k.width, k.height).unwrap().0).unwrap().data
}

fn one_step(model: &Model) -> OneStep {
    use memory::policy::{SelectedFrame, Slot};
    use memory::{ContextPlan, Policy, PolicyKind};

    let cases = warp_cases();
    let k = cases.k;
    let first = cases.rgb[..cases.shape[1] * cases.shape[2] * 3].to_vec();
    let latent = encode_rgb(model, &first, &k);
    let policy = Policy::preset(PolicyKind::WorldPack);
    let layout = model.layout_for(&policy.packing).unwrap();
    let mut slots: Vec<Slot> = layout.slots.iter().flat_map(|s| (0..s.count).map(move |_| Slot { rate: s.rate, frame: None })).collect();
    slots[0].frame = Some(SelectedFrame { id: 0, time: 0, overlap: 1.0, score: 1.0 });
    OneStep { cases, first, latent, policy, plan: ContextPlan { slots }, action: [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0] }
}

/// With a fusion head, a frame still does not depend on its batch: a request
/// with warp sources is blended and its latent is the blend re-encoded, one
/// without sources keeps its decoded frame and sampled latent, alone or
/// beside the other.
#[test]
fn a_fused_frame_does_not_depend_on_its_batch() {
    use model::pack::ContextFrame;
    use model::{Method, Request, Sampler};

    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures/variants/worldpack_geometry_fused");
    let mut model = Model::load(&dir, RuntimeOptions { provider: Provider::Cpu, threads: 1 }).expect("the fused model loads");
    let OneStep { cases: WarpCases { k, rgb, depth, src, dst, .. }, first, latent, policy, plan, action } = one_step(&model);
    let frame = |_: usize, id: u64| (id == 0).then(|| ContextFrame { latent: &latent, time: 0, pose: &src[0], generated: false });
    let sampler = Sampler::new(&model.manifest().diffusion, 3, Method::Ddim, 0.0).unwrap();
    let warp = sources(&rgb, &depth, &src, &k);
    let with = Request { plan: &plan, target_time: 1, target_pose: &dst[0], action: &action, seed: 5, warp: &warp[..1] };
    let without = Request { warp: &[], seed: 6, ..with };
    let both = model.predict(&policy.packing, &[with, without], &frame, &sampler).unwrap().frames;
    for (i, r) in [with, without].into_iter().enumerate() {
        let alone = model.predict(&policy.packing, &[r], &frame, &sampler).unwrap().frames.remove(0);
        let worst_px = alone.rgb.iter().zip(&both[i].rgb).map(|(a, b)| a.abs_diff(*b)).max().unwrap();
        let worst_latent = alone.latent.iter().zip(&both[i].latent).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
        assert!(worst_px <= 1 && worst_latent < 1e-3, "request {i}: batched and alone differ by {worst_px}/255 and {worst_latent} in the latent");
    }
    // The blended frame's latent is the blend re-encoded.
    let again = encode_rgb(&model, &both[0].rgb, &k);
    let worst = again.iter().zip(&both[0].latent).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
    assert!(worst < 0.05, "the stored latent is not the shown frame's: {worst}");
    // A request whose best source stands at its target's pose shows that source exactly.
    let revisit = Request { target_pose: &src[0], ..with };
    let seen = model.predict(&policy.packing, &[revisit, without], &frame, &sampler).unwrap().frames.remove(0);
    assert!(seen.rgb == first, "a view seen from where it was observed is not shown as observed");
    // With sampled latents kept, the same frame is shown, and its latent is the
    // one the request without a warp would keep: what the sampler made, not the blend.
    model.keep_sampled_latents(true);
    let kept = model.predict(&policy.packing, &[with], &frame, &sampler).unwrap().frames.remove(0);
    assert_eq!(kept.rgb, both[0].rgb, "the frame shown does not depend on what the memory keeps");
    let moved = kept.latent.iter().zip(&both[0].latent).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
    assert!(moved > 0.05, "the kept latent is still the re-encoded blend (largest difference {moved})");
    let resampled = kept.latent.iter().zip(&again).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
    assert!(resampled > 0.05, "the kept latent equals the blend's encoding");
}

/// The served student's head pair through `Model::predict`: the memory keeps
/// another frame than the one shown (its `kept` output re-encoded), and with
/// sampled latents kept it keeps neither, but the same frame is shown.
#[test]
fn a_head_pair_shows_one_frame_and_keeps_another() {
    use model::pack::ContextFrame;
    use model::{Method, Request, Sampler};

    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures/variants/worldpack_geometry_fused_1step");
    let mut model = Model::load(&dir, RuntimeOptions { provider: Provider::Cpu, threads: 1 }).expect("the student loads");
    let OneStep { cases: WarpCases { k, rgb, depth, src, dst, .. }, latent, policy, plan, action, .. } = one_step(&model);
    let frame = |_: usize, id: u64| (id == 0).then(|| ContextFrame { latent: &latent, time: 0, pose: &src[0], generated: false });
    let sampler = Sampler::new(&model.manifest().diffusion, 1, Method::Ddim, 0.0).unwrap();
    let warp = sources(&rgb, &depth, &src, &k);
    let request = Request { plan: &plan, target_time: 1, target_pose: &dst[0], action: &action, seed: 5, warp: &warp[..1] };
    let got = model.predict(&policy.packing, &[request], &frame, &sampler).unwrap().frames.remove(0);
    let apart = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0f32, f32::max);
    let shown_again = encode_rgb(&model, &got.rgb, &k);
    assert!(apart(&got.latent, &shown_again) > 0.05, "the memory keeps the frame shown");
    model.keep_sampled_latents(true);
    let sampled = model.predict(&policy.packing, &[request], &frame, &sampler).unwrap().frames.remove(0);
    assert_eq!(sampled.rgb, got.rgb, "the frame shown does not depend on what the memory keeps");
    assert!(apart(&sampled.latent, &got.latent) > 0.05, "with sampled latents kept, the latent is still the re-encoded kept frame");
}
