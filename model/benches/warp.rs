//! Criterion benches for the geometry model's warp without ONNX Runtime: the
//! three best stored frames splatted into the target view behind one z-buffer
//! (the warp input, before its encoder call) and the fused reference the
//! fusion head blends with (the same warp, cracks filled, holes from the best
//! frame), each alone and both from one projection as a step makes them. Real
//! frames: the export's fused warp case of fixtures/variants/worldpack_geometry.
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

criterion_group!(benches, warp);
criterion_main!(benches);
