//! Generation around the graphs: seeded noise, the sampling loop, and RGB
//! frames in and out with the intrinsics rescaled.

use std::path::Path;

use memory::Intrinsics;
use model::generate::{Conditioning, frame_to_tensor, gaussian, tensor_to_frame};
use model::{Method, Model, Provider, RuntimeOptions, Sampler, Tensor};

fn reference(name: &str) -> Tensor {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures/small/reference/denoiser_worldpack").join(format!("{name}.npy"));
    let (shape, data) = world::npy::read::<f32>(&path).unwrap();
    Tensor::new(shape, data)
}

/// The committed small model and the worldpack layout's reference conditioning (a batch of 2).
fn small_model_and_reference_conditioning() -> (Model, Vec<(String, Tensor)>, Tensor, Tensor) {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures/small");
    let m = Model::load(&dir, RuntimeOptions { provider: Provider::Cpu, threads: 1 }).unwrap();
    let layout = m.manifest().layout("worldpack").unwrap();
    let context = layout.inputs.iter().filter(|s| s.name.starts_with("context")).map(|s| (s.name.clone(), reference(&s.name))).collect();
    (m, context, reference("action"), reference("rel_time"))
}

#[test]
fn gaussian_noise_is_seeded_and_standard() {
    let a = gaussian(7, 100_001);
    assert_eq!(a, gaussian(7, 100_001));
    assert_ne!(a[..10], gaussian(8, 10)[..]);
    let mean = a.iter().map(|&v| v as f64).sum::<f64>() / a.len() as f64;
    let var = a.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / a.len() as f64;
    assert!(mean.abs() < 0.01 && (var - 1.0).abs() < 0.02, "mean {mean}, variance {var}");
}

#[test]
fn sampling_is_seeded_and_finite() {
    let (m, context, action, rel_time) = small_model_and_reference_conditioning();
    let cond = Conditioning { context: &context, action: &action, rel_time: &rel_time };
    let sampler = Sampler::new(&m.manifest().diffusion, 3, Method::Ancestral, 0.0).unwrap();
    let a = m.sample("worldpack", &cond, &sampler, &[1, 2]).unwrap();
    assert_eq!(a.shape, [2, 4, 16, 16]);
    assert!(a.data.iter().all(|v| v.is_finite()));
    assert_eq!(a, m.sample("worldpack", &cond, &sampler, &[1, 2]).unwrap());
    assert_ne!(a, m.sample("worldpack", &cond, &sampler, &[3, 2]).unwrap());
    let image = m.decode(&a).unwrap();
    assert_eq!(tensor_to_frame(&image, 1).unwrap().len(), 64 * 64 * 3);
    let err = m.sample("nope", &cond, &sampler, &[1, 2]).unwrap_err().to_string();
    assert!(err.starts_with("layout:"), "{err}");
    let err = m.sample("worldpack", &cond, &sampler, &[1]).unwrap_err().to_string();
    assert!(err.starts_with("seeds:"), "{err}");
}

/// DPM-Solver++(2M) needs the sampling loop to carry each step's clean
/// estimate to the next: `Model::sample` must make what a hand-written loop
/// carrying it makes, and not what the same loop makes when it drops it.
#[test]
fn the_sampling_loop_carries_the_solvers_history() {
    let (m, context, action, rel_time) = small_model_and_reference_conditioning();
    let sampler = Sampler::new(&m.manifest().diffusion, 4, Method::Dpm2m, 0.0).unwrap();
    let seeds = [5, 6];
    let got = m.sample("worldpack", &Conditioning { context: &context, action: &action, rel_time: &rel_time }, &sampler, &seeds).unwrap();
    let by_hand = |carry: bool| {
        let per = got.data.len() / 2;
        let mut x: Vec<f32> = seeds.iter().flat_map(|&s| gaussian(s, per)).collect();
        let mut history = None;
        for (i, &t) in sampler.timesteps.iter().enumerate() {
            let x_t = Tensor::new(got.shape.clone(), x.clone());
            let timestep = Tensor::new(vec![2], vec![t as f32; 2]);
            let mut inputs: Vec<(&str, &Tensor)> = context.iter().map(|(k, v)| (k.as_str(), v)).collect();
            inputs.extend([("x_t", &x_t), ("timestep", &timestep), ("action", &action), ("rel_time", &rel_time)]);
            let eps = m.run(model::GraphRole::Denoiser("worldpack"), &inputs).unwrap().remove(0);
            if !carry {
                history = None;
            }
            x = sampler.step(i, &x, &eps.data, &vec![0.0; x.len()], &mut history);
        }
        x
    };
    assert_eq!(got.data, by_hand(true));
    let first_order = by_hand(false);
    let apart = got.data.iter().zip(&first_order).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
    assert!(apart > 1e-3, "the second-order term changed nothing ({apart})");
}

/// Item `i` of a batch: its context, action and relative time alone (batch 1).
fn item(context: &[(String, Tensor)], action: &Tensor, rel_time: &Tensor, i: usize) -> (Vec<(String, Tensor)>, Tensor, Tensor) {
    let one = |t: &Tensor| {
        let per = t.data.len() / t.shape[0];
        let mut shape = t.shape.clone();
        shape[0] = 1;
        Tensor::new(shape, t.data[i * per..(i + 1) * per].to_vec())
    };
    (context.iter().map(|(n, t)| (n.clone(), one(t))).collect(), one(action), one(rel_time))
}

#[test]
fn a_frame_does_not_depend_on_its_batch() {
    let (m, context, action, rel_time) = small_model_and_reference_conditioning();
    let sampler = Sampler::new(&m.manifest().diffusion, 4, Method::Ancestral, 0.0).unwrap();
    let both = m.sample("worldpack", &Conditioning { context: &context, action: &action, rel_time: &rel_time }, &sampler, &[11, 12]).unwrap();
    let per = both.data.len() / 2;
    for (i, seed) in [(0, 11), (1, 12)] {
        let (c, a, r) = item(&context, &action, &rel_time, i);
        let alone = m.sample("worldpack", &Conditioning { context: &c, action: &a, rel_time: &r }, &sampler, &[seed]).unwrap();
        // Batched matrix products may sum in another order: equal to float rounding, far below 1/255 of a pixel.
        let worst = alone.data.iter().zip(&both.data[i * per..(i + 1) * per]).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
        assert!(worst < 1e-4, "item {i}: batched and alone differ by {worst}");
    }
}

#[test]
fn frames_round_trip_and_resize_with_their_intrinsics() {
    let (w, h) = (8u32, 6u32);
    let rgb: Vec<u8> = (0..w * h * 3).map(|i| (i * 37 % 256) as u8).collect();
    let k = Intrinsics::from_fov(70.0, None, w, h).unwrap();
    let (t, k_same) = frame_to_tensor(&rgb, w, h, &k, w, h).unwrap();
    assert_eq!(t.shape, [1, 3, 6, 8]);
    assert_eq!(tensor_to_frame(&t, 0).unwrap(), rgb, "same size is lossless");
    assert_eq!(k_same, k);
    // Halving averages 2x2 blocks exactly (bilinear at the block centre).
    let (t, k2) = frame_to_tensor(&rgb, w, h, &k, 4, 3).unwrap();
    let px = |x: usize, y: usize, c: usize| rgb[(y * 8 + x) * 3 + c] as f32;
    let want = (px(2, 2, 1) + px(3, 2, 1) + px(2, 3, 1) + px(3, 3, 1)) / 4.0 / 127.5 - 1.0;
    assert!((t.data[(3 + 1) * 4 + 1] - want).abs() < 1e-6);
    assert_eq!((k2.width, k2.height), (4, 3));
    assert!((k2.fx - k.fx / 2.0).abs() < 1e-12 && (k2.cx - ((k.cx + 0.5) / 2.0 - 0.5)).abs() < 1e-12);
    let err = frame_to_tensor(&rgb[1..], w, h, &k, 4, 3).unwrap_err().to_string();
    assert!(err.starts_with("image:"), "{err}");
}

#[test]
fn concurrent_callers_get_their_own_sessions_and_the_same_answers() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures/small");
    let m = Model::load(&dir, RuntimeOptions { provider: Provider::Cpu, threads: 1 }).unwrap();
    let layout = m.manifest().layout("worldpack").unwrap();
    let inputs: Vec<(String, Tensor)> = layout.inputs.iter().map(|s| (s.name.clone(), reference(&s.name))).collect();
    let feed: Vec<(&str, &Tensor)> = inputs.iter().map(|(n, t)| (n.as_str(), t)).collect();
    let graph = m.local().unwrap().denoiser("worldpack").unwrap();
    let alone = graph.run(&feed).unwrap();
    let results: Vec<_> = std::thread::scope(|s| {
        let workers: Vec<_> = (0..4).map(|_| s.spawn(|| (0..3).map(|_| graph.run(&feed).unwrap()).collect::<Vec<_>>())).collect();
        workers.into_iter().flat_map(|w| w.join().unwrap()).collect()
    });
    assert_eq!(results.len(), 12);
    assert!(results.iter().all(|r| *r == alone), "every concurrent call gives the sequential answer");
    assert!(graph.sessions() >= 2, "concurrent calls opened more sessions instead of queueing on one");
}
