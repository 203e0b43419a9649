//! Criterion benches for the geometry model's warp without ONNX Runtime: the
//! three best stored frames splatted into the target view behind one z-buffer
//! (the warp input, before its encoder call) and the fused reference the
//! fusion head blends with (the same warp, cracks filled, holes from the best
//! frame), each alone and both from one projection as a step makes them. Real
//! frames: the export's fused warp case of fixtures/variants/worldpack_geometry.
//! And the full-size stage (`model::full_size`) at 224×224: 4 and 8 of the voxel
//! world's frames, rendered at that size, shown over a 64×64 frame.
//! `cargo bench -p model`.

use std::path::{Path, PathBuf};

use criterion::{Criterion, criterion_group, criterion_main};
use memory::Pose;
use model::warp::{Landings, REFERENCE_MARGIN, forward_warp_many, fused_reference};
use model::{Manifest, WarpSource};

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures/variants/worldpack_geometry")
}

fn case<T: world::npy::Element>(name: &str) -> Vec<T> {
    let path = fixture().join("reference/warp").join(format!("{name}.npy"));
    world::npy::read::<T>(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display())).1
}

/// A row-major 4×4 camera-to-world matrix, flattened.
fn pose(m: &[f64]) -> Pose {
    Pose::from_matrix_rows([0, 1, 2, 3].map(|i| [m[4 * i], m[4 * i + 1], m[4 * i + 2], m[4 * i + 3]])).expect("a reference pose is a proper rotation")
}

fn warp(c: &mut Criterion) {
    let k = Manifest::load(&fixture()).expect("the fixture's manifest").intrinsics;
    let (rgb, depth) = (case::<u8>("fused_rgb"), case::<u16>("fused_depth_mm"));
    let poses: Vec<Pose> = case::<f64>("fused_src_c2w").chunks(16).map(pose).collect();
    let target = pose(&case::<f64>("fused_dst_c2w"));
    let pixels = (k.width * k.height) as usize;
    let sources: Vec<WarpSource> = (0..3)
        .map(|i| WarpSource { rgb: &rgb[i * pixels * 3..(i + 1) * pixels * 3], depth_mm: &depth[i * pixels..(i + 1) * pixels], pose: &poses[i], intrinsics: &k })
        .collect();
    c.bench_function("warp_3_sources_64x64", |b| b.iter(|| forward_warp_many(&sources, &target).unwrap()));
    c.bench_function("fused_reference_3_sources_64x64", |b| b.iter(|| fused_reference(&sources, &target).unwrap()));
    // What a fused model's step does: both warps from one projection.
    c.bench_function("warp_and_reference_one_projection_3_sources_64x64", |b| {
        b.iter(|| {
            let landings = Landings::of(&sources, &target).unwrap();
            (landings.resolve(0.0), landings.resolve(REFERENCE_MARGIN).into_reference(&sources[0]))
        })
    });
}

/// A rendered frame: colour, depth in millimetres, and where it was taken.
type Shot = (Vec<u8>, Vec<u16>, Pose);

/// Frames of the voxel world at `side` pixels: a slow turn on the spot, and the pose after it.
fn voxel_walk(side: u32, frames: usize) -> (Vec<Shot>, Pose, memory::Intrinsics) {
    let world = world::World::generate(3);
    let k = world::suite::default_intrinsics(side, side).unwrap();
    let start = world::agent::PlayerState::at_cell(world::agent::spawn_point(&world, None).unwrap(), 0.0);
    let at = |i: usize| world::agent::PlayerState { yaw_deg: start.yaw_deg + 3.0 * i as f64, ..start }.camera();
    let shot = |i: usize| {
        let f = world::render::render(&world, &at(i), &k, &world::render::RenderSettings::default());
        (f.rgb, f.depth.iter().map(|&d| world::suite::depth_to_mm(d)).collect(), at(i))
    };
    ((0..frames).map(shot).collect(), at(frames), k)
}

fn full_size(c: &mut Criterion) {
    use model::full_size::{FullSize, bicubic, full_size_frame};
    let (shots, target, k) = voxel_walk(224, 8);
    let sources: Vec<WarpSource> = shots.iter().rev().map(|(rgb, depth, pose)| WarpSource { rgb, depth_mm: depth, pose, intrinsics: &k }).collect();
    let small = vec![128u8; 64 * 64 * 3];
    c.bench_function("bicubic_64_to_224", |b| b.iter(|| bicubic(&small, 64, 64, 224, 224)));
    for frames in [4, 8] {
        let rule = FullSize { frames, ..FullSize::default() };
        c.bench_function(&format!("full_size_{frames}_sources_224x224"), |b| b.iter(|| full_size_frame(&small, 64, 64, &sources, &target, 224, 224, &rule).unwrap()));
    }
}

criterion_group!(benches, warp, full_size);
criterion_main!(benches);
