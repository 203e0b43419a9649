//! The LPIPS, DreamSim-style and FVD arithmetic against NumPy on tiny
//! networks the project makes (fixtures/metrics, scripts/make_feature_nets.py),
//! and clear errors for networks that break the contract.

use std::path::{Path, PathBuf};

use eval::features::{Embedding, Lpips, VideoFeatures, frechet_distance};
use model::{Provider, RuntimeOptions};

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures/metrics")
}

const CPU: RuntimeOptions = RuntimeOptions { provider: Provider::Cpu, threads: 1 };

fn golden() -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(fixtures().join("golden.json")).unwrap()).unwrap()
}

fn array(name: &str) -> (Vec<usize>, Vec<u8>) {
    world::npy::read::<u8>(&fixtures().join(format!("{name}.npy"))).unwrap()
}

fn images(name: &str) -> Vec<Vec<u8>> {
    let (shape, data) = array(name);
    data.chunks_exact(shape[1..].iter().product()).map(<[u8]>::to_vec).collect()
}

fn assert_close(got: &[f64], want: &serde_json::Value, what: &str) {
    let want: Vec<f64> = want.as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    assert_eq!(got.len(), want.len(), "{what}");
    for (g, w) in got.iter().zip(&want) {
        assert!((g - w).abs() <= 1e-5 * w.abs().max(1e-3), "{what}: {got:?} vs NumPy {want:?}");
    }
}

#[test]
fn lpips_and_embedding_distances_match_numpy() {
    let (a, b) = (images("images_a"), images("images_b"));
    let (a, b): (Vec<&[u8]>, Vec<&[u8]>) = (a.iter().map(Vec::as_slice).collect(), b.iter().map(Vec::as_slice).collect());
    let lpips = Lpips::open(&fixtures().join("lpips_tiny.onnx"), CPU).unwrap();
    assert_close(&lpips.distances(&a, &b, 32, 32).unwrap(), &golden()["lpips"], "lpips");
    assert!(lpips.distances(&a, &a, 32, 32).unwrap().iter().all(|d| d.abs() < 1e-9), "an image is at distance 0 from itself");
    let embed = Embedding::open(&fixtures().join("embed_tiny.onnx"), CPU).unwrap();
    assert_close(&embed.distances(&a, &b, 32, 32).unwrap(), &golden()["dreamsim"], "dreamsim");
}

#[test]
fn fvd_matches_numpy() {
    let net = VideoFeatures::open(&fixtures().join("video_tiny.onnx"), CPU).unwrap();
    assert_eq!(net.clip_len(), 4);
    let clips = |name: &str| -> Vec<Vec<u8>> { images(name) };
    let (real, fake) = (clips("videos_real"), clips("videos_fake"));
    let frame = 16 * 16 * 3;
    fn split(v: &[u8], frame: usize) -> Vec<&[u8]> {
        v.chunks_exact(frame).collect()
    }
    let fr = net.features(&real.iter().map(|v| split(v, frame)).collect::<Vec<_>>(), 16, 16).unwrap();
    let ff = net.features(&fake.iter().map(|v| split(v, frame)).collect::<Vec<_>>(), 16, 16).unwrap();
    let fvd = frechet_distance(&fr, &ff);
    let want = golden()["fvd"].as_f64().unwrap();
    assert!((fvd - want).abs() <= 1e-5 * want, "FVD {fvd} vs NumPy {want}");
    assert!(frechet_distance(&fr, &fr).abs() < 1e-9);
}

#[test]
fn networks_that_break_the_contract_are_refused_by_name() {
    let wrong = |r: Result<(), eval::features::FeatureError>| r.unwrap_err().to_string();
    let e = wrong(Lpips::open(&fixtures().join("embed_tiny.onnx"), CPU).map(|_| ()));
    assert!(e.contains("feat0"), "{e}");
    let e = wrong(Embedding::open(&fixtures().join("lpips_tiny.onnx"), CPU).map(|_| ()));
    assert!(e.contains("embedding"), "{e}");
    let e = wrong(VideoFeatures::open(&fixtures().join("lpips_tiny.onnx"), CPU).map(|_| ()));
    assert!(e.contains("video"), "{e}");
    let e = wrong(Lpips::open(&fixtures().join("missing.onnx"), CPU).map(|_| ()));
    assert!(e.contains("missing.onnx"), "{e}");
}
