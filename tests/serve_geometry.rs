//! Geometry models served: the depth warp of observed frames across restarts,
//! co-visible warp sources, batching across sessions, the fusion head.

mod support;

use std::path::Path;

use base64::Engine;
use base64::engine::general_purpose::STANDARD as B64;
use serde_json::{Value, json};
use support::*;

#[test]
fn a_geometry_model_warps_the_best_observed_frame_with_depth_across_restarts() {
    let store = temp_store("geometry");
    let model = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/variants/worldpack_geometry");
    let s = Server::start(&store, &["--model", model]);
    let (code, created) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 }, "policy": { "kind": "worldpack" } }));
    assert_eq!(code, 201, "{created}");
    let id = created["session"].as_u64().unwrap();
    let step = |body: Value| s.post(&format!("/v1/sessions/{id}/step"), &body);
    // A synthetic session's first frame comes with the world's depth, as a depth camera's would.
    let depth = s.bytes(&format!("/v1/sessions/{id}/frames/0/depth"));
    assert_eq!(&depth[1..4], b"PNG");
    for i in 1..=3u64 {
        let (code, r) = step(json!({ "action": { "forward": true } }));
        assert_eq!(code, 200, "{r}");
        assert_eq!(r["selection"]["warp_frames"][0].as_u64(), Some(0), "step {i}: only frame 0 has depth: {r}");
        assert!(r["timings_ms"]["warp"].as_f64().unwrap() > 0.0, "{r}");
    }
    // An observing step records the world's frame and depth: the next step warps it first.
    let (code, r) = step(json!({ "action": { "forward": true }, "observe": true }));
    assert_eq!((code, r["source"].as_str(), r["index"].as_u64()), (200, Some("observed"), Some(4)), "{r}");
    assert!(r["truth"].is_null(), "an observed frame is the truth: {r}");
    assert_eq!(s.bytes(&format!("/v1/sessions/{id}/frames/4/depth"))[1..4], *b"PNG");
    let (code, r) = step(json!({ "action": {} }));
    assert_eq!((code, r["selection"]["warp_frames"][0].as_u64()), (200, Some(4)), "{r}");
    // A frame observed through the API with depth joins the warp sources too.
    let (_, frame3) = s.get(&format!("/v1/sessions/{id}/frames/3"));
    let pose3 = json!({ "c2w": frame3["pose"] });
    let truth3 = s.bytes(&format!("/v1/sessions/{id}/frames/3/truth"));
    let (code, r) = s.post(&format!("/v1/sessions/{id}/observe"), &json!({ "image_png": B64.encode(&truth3), "pose": pose3, "depth_png16": B64.encode(&depth) }));
    assert_eq!((code, r["index"].as_u64()), (200, Some(6)), "{r}");
    let (code, r) = step(json!({ "action": {}, "pose": pose3 }));
    assert_eq!((code, r["selection"]["warp_frames"][0].as_u64()), (200, Some(6)), "{r}");
    // Wrong depth, or an observing step with a pose, is refused by name and stores nothing.
    let (code, r) = s.post(&format!("/v1/sessions/{id}/observe"), &json!({ "image_png": B64.encode(&truth3), "pose": pose3, "depth_png16": B64.encode(&truth3) }));
    assert_eq!((code, r["error"]["field"].as_str()), (400, Some("depth_png16")), "{r}");
    let (code, r) = step(json!({ "action": {}, "pose": pose3, "observe": true }));
    assert_eq!((code, r["error"]["field"].as_str()), (400, Some("observe")), "{r}");
    let (_, frame0) = s.get(&format!("/v1/sessions/{id}/frames/0"));
    let pose0 = json!({ "c2w": frame0["pose"] });
    s.kill();
    // After a restart the warp sources come back from the store.
    let s = Server::start(&store, &["--model", model]);
    let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": {}, "pose": pose0 }));
    assert_eq!((code, r["index"].as_u64()), (200, Some(8)), "{r}");
    assert_eq!(r["selection"]["warp_frames"][0].as_u64(), Some(0), "{r}");
    // Occlusion-aware selection reads the restored depth: three observed frames have it.
    let select = |body: Value| s.post(&format!("/v1/sessions/{id}/select"), &body);
    let (code, r) = select(json!({ "pose": pose0, "covisibility": {} }));
    assert_eq!(code, 200, "{r}");
    let c = &r["covisibility"];
    assert!(c["candidates"].as_u64().unwrap() >= 3 && c["with_depth"] == 3 && c["surface_points"].as_u64().unwrap() > 0, "{r}");
    let (code, r) = select(json!({ "pose": pose0 }));
    assert!(code == 200 && r.get("covisibility").is_none(), "{r}");
    for (bad, field) in [(json!({ "cells": 0 }), "covisibility.cells"), (json!({ "tolerance": -1 }), "covisibility.tolerance"), (json!({ "nope": 1 }), "covisibility")] {
        let (code, r) = select(json!({ "pose": pose0, "covisibility": bad }));
        assert_eq!(code, 400, "{r}");
        assert!(r["error"]["field"].as_str().unwrap().starts_with(field), "{field}: {r}");
    }
    s.kill();
    // With --overlay-warp what the sources show is kept as seen: in a new session, at frame 0's own
    // pose, frame 0 (the only one with depth) warps onto every pixel, so the step gives it back.
    let s = Server::start(&store, &["--model", model, "--overlay-warp"]);
    let (_, created) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 } }));
    let id = created["session"].as_u64().unwrap();
    let (_, frame0) = s.get(&format!("/v1/sessions/{id}/frames/0"));
    let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": {}, "pose": { "c2w": frame0["pose"] } }));
    assert_eq!(code, 200, "{r}");
    assert_eq!(s.bytes(&format!("/v1/sessions/{id}/frames/1/image")), s.bytes(&format!("/v1/sessions/{id}/frames/0/image")));
    assert_eq!(r["truth"]["psnr_db"].as_f64(), Some(100.0), "{r}");
}

/// A policy with `covisibility` (the default policy under `serve --covisible`):
/// each step's plan and warp sources come from co-visibility over the observed
/// frames' depth. A session's own policy decides, whatever the server's default.
#[test]
fn covisible_serving_chooses_warp_sources_among_the_observed_frames() {
    let store = temp_store("covisible");
    let model = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/variants/worldpack_geometry");
    let s = Server::start(&store, &["--model", model, "--covisible"]);
    let session = |policy: Option<Value>| {
        let (code, created) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 }, "policy": policy }));
        assert_eq!(code, 201, "{created}");
        created["session"].as_u64().unwrap()
    };
    // A session that names a policy without co-visibility selects by frustum overlap.
    let plain = session(Some(json!({ "kind": "worldpack" })));
    let (code, r) = s.post(&format!("/v1/sessions/{plain}/step"), &json!({ "action": { "forward": true } }));
    assert!(code == 200 && r["selection"]["exact_evaluations"].as_u64() > Some(0), "{r}");
    let (code, r) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 }, "policy": { "kind": "worldpack", "covisibility": { "cells": 0 } } }));
    assert_eq!((code, r["error"]["field"].as_str()), (400, Some("policy.covisibility.cells")), "{r}");
    let id = session(None);
    let (_, info) = s.get(&format!("/v1/sessions/{id}"));
    assert_eq!(info["policy"]["covisibility"]["cells"], 16, "the server's default policy, resolved: {info}");
    let step = |body: Value| s.post(&format!("/v1/sessions/{id}/step"), &body);
    for _ in 0..3 {
        let (code, r) = step(json!({ "action": { "forward": true }, "observe": true }));
        assert_eq!((code, r["source"].as_str()), (200, Some("observed")), "{r}");
    }
    for i in 4..=6u64 {
        let (code, r) = step(json!({ "action": { "forward": true } }));
        assert_eq!((code, r["index"].as_u64()), (200, Some(i)), "{r}");
        let sources: Vec<u64> = r["selection"]["warp_frames"].as_array().unwrap().iter().map(|f| f.as_u64().unwrap()).collect();
        assert!(!sources.is_empty() && sources.iter().all(|&f| f <= 3), "observed frames 0-3 have depth: {r}");
        assert_eq!(r["selection"]["exact_evaluations"], 0, "co-visibility reports no frustum evaluations: {r}");
        let used = r["selection"]["plan"]["slots"].as_array().unwrap().iter().filter(|s| s["frame"].is_u64()).count() as u64;
        assert_eq!(used, i, "every earlier frame fits: {r}");
    }
}

/// Batching across sessions: four identical sessions step at once with the
/// same seed and share model calls; each frame equals the frame a lone step
/// makes, within 1/255 per pixel (a batched call may round differently).
#[test]
fn batched_steps_make_the_frames_a_lone_step_makes() {
    let store = temp_store("batching");
    let s = Server::start(&store, &["--batch-window-ms", "200", "--batch-max", "8"]);
    let ids: Vec<u64> = (0..5)
        .map(|_| s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 } })).1["session"].as_u64().unwrap())
        .collect();
    let body = json!({ "action": { "forward": true, "yaw_deg": 5 }, "seed": 11 });
    let frames: Vec<Value> = std::thread::scope(|scope| {
        let (s, body) = (&s, &body);
        let workers: Vec<_> = ids[..4].iter().map(|&id| scope.spawn(move || s.post(&format!("/v1/sessions/{id}/step"), body))).collect();
        workers.into_iter().map(|w| w.join().unwrap()).map(|(code, r)| { assert_eq!(code, 200, "{r}"); r }).collect()
    });
    let text = HTTP.get(&format!("{}/metrics", s.url)).call().unwrap().into_string().unwrap();
    let counter = |name: &str| text.lines().find(|l| l.starts_with(name)).and_then(|l| l.split_whitespace().nth(1)).unwrap().parse::<u64>().unwrap();
    let (calls, items) = (counter("worldpack_batched_calls_total"), counter("worldpack_batched_items_total"));
    assert_eq!(items, 4, "{text}");
    assert!(calls < items, "concurrent steps shared a call: {calls} calls for {items} steps");
    // The fifth session steps alone, in a call of its own.
    let (code, alone) = s.post(&format!("/v1/sessions/{}/step", ids[4]), &body);
    assert_eq!(code, 200, "{alone}");
    let pixels = |r: &Value| world::picture::decode_rgb(&B64.decode(r["image_png"].as_str().unwrap()).unwrap()).unwrap().0;
    let lone = pixels(&alone);
    for r in &frames {
        let worst = pixels(r).iter().zip(&lone).map(|(a, b)| a.abs_diff(*b)).max().unwrap();
        assert!(worst <= 1, "a batched frame differs from the lone one by {worst}/255");
    }
}

/// A geometry model with a fusion head serves its blend through the same
/// step: walking out with observing steps and back without them, the frames
/// it shows are closer to the world than those of the same model without the
/// head, and the step still reports the warp's cost.
#[test]
fn a_fusion_head_serves_frames_closer_to_the_world() {
    let walk = |name: &str| -> f64 {
        let model = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/variants").join(name);
        let s = Server::start(&temp_store(&format!("fusion-{name}")), &["--model", model.to_str().unwrap()]);
        let (_, c) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 4 }, "policy": { "kind": "worldpack" } }));
        let id = c["session"].as_u64().unwrap();
        let step = |body: Value| {
            let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &body);
            assert_eq!(code, 200, "{name}: {r}");
            r
        };
        for _ in 0..4 {
            step(json!({ "action": { "forward": true }, "observe": true }));
        }
        let turn = step(json!({ "action": { "yaw_deg": 90 }, "observe": true }));
        assert!(turn["truth"].is_null());
        step(json!({ "action": { "yaw_deg": 90 }, "observe": true }));
        let back: Vec<Value> = (0..4).map(|k| step(json!({ "action": { "forward": true }, "seed": k }))).collect();
        for r in &back {
            assert!(r["timings_ms"]["warp"].as_f64().unwrap() > 0.0 && !r["selection"]["warp_frames"].as_array().unwrap().is_empty(), "{name}: {r}");
        }
        back.iter().map(|r| r["truth"]["psnr_db"].as_f64().unwrap()).sum::<f64>() / back.len() as f64
    };
    let (fused, alone) = (walk("worldpack_geometry_fused"), walk("worldpack_geometry"));
    eprintln!("the way back: {fused:.2} dB with the fusion head, {alone:.2} without");
    assert!(fused > alone, "mean PSNR on the way back: {fused:.2} dB with the head, {alone:.2} without");
}

/// The served model fuses up to its manifest's `warp.frames` (32) observed
/// frames into the warp, not the 3 it was trained with: after six observed
/// steps ahead, a generated step warps more than three of them.
#[test]
fn the_served_model_warps_more_frames_than_it_was_trained_with() {
    let model = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/variants/worldpack_geometry_fused_1step");
    let s = Server::start(&temp_store("served-warp"), &["--model", model, "--covisible"]);
    let (_, c) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 } }));
    let id = c["session"].as_u64().unwrap();
    for _ in 0..5 {
        let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true }, "observe": true }));
        assert_eq!(code, 200, "{r}");
    }
    let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true } }));
    assert_eq!(code, 200, "{r}");
    let sources = r["selection"]["warp_frames"].as_array().unwrap();
    assert!(sources.len() > 3 && sources.len() <= 6, "frames 0-5 have depth and face this view: {r}");
}
