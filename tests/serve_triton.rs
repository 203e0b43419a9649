//! The model on Triton Inference Server (PyPI's tritonserver via pytriton):
//! the same frames as the local backend, a stopped Triton answered 503, a bad backend refused.

mod support;

use std::path::Path;
use std::process::Command;

use serde_json::json;
use support::*;

/// The graphs on Triton compute what they compute in this process (float
/// tolerance), and a served session makes the same frames, byte for byte,
/// with the same seeds.
#[test]
fn triton_runs_the_graphs_as_the_local_backend_does() {
    let _alone = triton_alone();
    let triton = TritonHost::start("fixtures/small", None);
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/small");
    let local = model::Model::load(&dir, model::RuntimeOptions::default()).unwrap();
    let manifest = local.manifest().clone();
    let remote = model::Model::with_backend(&dir, manifest.clone(), Box::new(kserve::KServeBackend::connect(&triton.backend(), &manifest).unwrap()));
    assert_eq!(remote.provider(), "triton");
    // Every graph on a batch of 3 pseudo-random inputs of its declared shapes.
    let mut state = 7u64;
    let mut noise = move || {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((state >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
    };
    let mut graphs = vec![(model::GraphRole::Encoder, manifest.autoencoder.encoder.clone()), (model::GraphRole::Decoder, manifest.autoencoder.decoder.clone())];
    graphs.extend(manifest.denoiser.layouts.iter().map(|l| (model::GraphRole::Denoiser(&l.name), l.graph())));
    for (role, spec) in graphs {
        let inputs: Vec<(String, model::Tensor)> = spec
            .inputs
            .iter()
            .map(|t| {
                let shape: Vec<usize> = t.dims().iter().map(|&d| if d < 0 { 3 } else { d as usize }).collect();
                let mut data: Vec<f32> = (0..shape.iter().product()).map(|_| noise()).collect();
                if t.name.starts_with("context_mask") {
                    data.iter_mut().for_each(|v| *v = 1.0);
                } else if t.name == "timestep" || t.name == "rel_time" {
                    data.iter_mut().for_each(|v| *v = (v.abs() * 10.0).round().max(1.0));
                }
                (t.name.clone(), model::Tensor::new(shape, data))
            })
            .collect();
        let named: Vec<(&str, &model::Tensor)> = inputs.iter().map(|(n, t)| (n.as_str(), t)).collect();
        let (want, got) = (local.run(role, &named).unwrap(), remote.run(role, &named).unwrap());
        for (w, g) in want.iter().zip(&got) {
            assert_eq!(w.shape, g.shape, "{role:?}");
            let worst = w.data.iter().zip(&g.data).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
            assert!(worst <= 1e-5, "{role:?}: Triton differs from the local backend by {worst}");
        }
    }
    // The same session served both ways.
    let frames = |extra: &[&str]| -> Vec<Vec<u8>> {
        let s = Server::start(&temp_store(&format!("triton-parity{}", extra.len())), extra);
        let (_, c) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 5 } }));
        let id = c["session"].as_u64().unwrap();
        (1..=3u64)
            .map(|k| {
                let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true, "yaw_deg": 6 }, "seed": k }));
                assert_eq!(code, 200, "{r}");
                s.bytes(&format!("/v1/sessions/{id}/frames/{k}/image"))
            })
            .collect()
    };
    assert_eq!(frames(&[]), frames(&["--model-backend", &triton.backend()]), "frames served through Triton differ");
    // Stopped, the host leaves none of the shared memory its calls used (the client goes
    // first, as at the end of a test, the order in which pytriton left its segments).
    let prefix = format!("pytrtion{}-", triton.pid());
    drop(remote);
    drop(triton);
    let left: Vec<String> = std::fs::read_dir("/dev/shm").unwrap().filter_map(|e| e.ok()?.file_name().into_string().ok()).filter(|n| n.starts_with(&prefix)).collect();
    assert!(left.is_empty(), "the stopped Triton host left shared memory behind: {left:?}");
}

/// Triton stopped under a running server: steps answer 503 naming triton,
/// no frame is stored for them, and service resumes when Triton is back on
/// the same port.
#[test]
fn a_stopped_triton_answers_503_and_service_resumes() {
    let _alone = triton_alone();
    let mut triton = TritonHost::start("fixtures/small", None);
    let s = Server::start(&temp_store("triton-fault"), &["--model-backend", &triton.backend()]);
    let (_, c) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 } }));
    let id = c["session"].as_u64().unwrap();
    let step = || s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true } }));
    assert_eq!(step().0, 200);
    triton.stop();
    let (code, r) = step();
    assert_eq!((code, r["error"]["field"].as_str()), (503, Some("triton")), "{r}");
    assert_eq!(s.get(&format!("/v1/sessions/{id}")).1["frames"].as_u64(), Some(2), "the refused step stored nothing");
    let _back = TritonHost::start("fixtures/small", Some(triton.ports));
    let (code, r) = step();
    assert_eq!((code, r["index"].as_u64()), (200, Some(2)), "{r}");
}

/// A Triton URL that is malformed or serves no such model stops the server
/// at start with a message naming the flag.
#[test]
fn a_bad_model_backend_is_refused_at_start() {
    for (backend, says) in [("grpc://127.0.0.1:1", "triton://HOST:PORT"), ("triton://127.0.0.1:1", "triton is unavailable")] {
        let out = Command::new(env!("CARGO_BIN_EXE_worldpack"))
            .args(["serve", "--addr", "127.0.0.1:0", "--store", temp_store("bad-backend").to_str().unwrap(), "--model-backend", backend])
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && stderr.contains("--model-backend") && stderr.contains(says), "{backend}: {stderr}");
    }
}
