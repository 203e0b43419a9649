//! Criterion benches for the selection hot paths: building a frustum, one
//! exact overlap, inserting into the index, and a full indexed WorldPack
//! selection on the loop and walk workloads. `cargo bench -p memory`.

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use memory::overlap::exact_overlap;
use memory::workload::{Workload, frusta};
use memory::{FrameMemory, Frustum, Intrinsics, MemoryFrame, Policy, PolicyKind};

fn camera() -> Intrinsics {
    Intrinsics::from_fov(70.0, None, 64, 64).unwrap()
}

fn hot_paths(c: &mut Criterion) {
    let k = camera();
    let views = frusta(Workload::Loop, 64, 1, k);
    c.bench_function("frustum_new", |b| b.iter(|| Frustum::new(*views[5].pose(), k).unwrap()));
    // Neighbouring views of the loop overlap a lot: the clipper's common case.
    c.bench_function("exact_overlap_neighbours", |b| b.iter(|| exact_overlap(&views[10], &views[11])));
    c.bench_function("exact_overlap_far_apart", |b| b.iter(|| exact_overlap(&views[10], &views[40])));
    c.bench_function("insert_10k", |b| {
        let frames = frusta(Workload::Walk, 10_000, 2, k);
        b.iter(|| {
            let mut m = FrameMemory::new();
            for (t, f) in frames.iter().enumerate() {
                m.insert(MemoryFrame { id: t as u64, time: t as u64, frustum: f.clone() }).unwrap();
            }
            m
        })
    });
}

fn selection(c: &mut Criterion) {
    let k = camera();
    let policy = Policy::preset(PolicyKind::WorldPack);
    let mut group = c.benchmark_group("select_worldpack");
    for workload in [Workload::Walk, Workload::Loop] {
        for n in [1_600usize, 10_000] {
            let views = frusta(workload, n + 1, 7, k);
            let mut m = FrameMemory::new();
            for (t, f) in views[..n].iter().enumerate() {
                m.insert(MemoryFrame { id: t as u64, time: t as u64, frustum: f.clone() }).unwrap();
            }
            let target = &views[n];
            group.bench_with_input(BenchmarkId::new(format!("{workload:?}").to_lowercase(), n), &n, |b, _| {
                b.iter(|| m.select(&policy, target, None))
            });
        }
    }
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20);
    targets = hot_paths, selection
}
criterion_main!(benches);
