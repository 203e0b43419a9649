//! The REST server as users meet it: the real `worldpack serve` process on
//! loopback, real HTTP: sessions, steps, observes, selections, bad input, queues, the document.

mod support;

use std::process::Command;

use base64::Engine;
use base64::engine::general_purpose::STANDARD as B64;
use serde_json::{Value, json};
use support::*;

#[test]
fn a_synthetic_session_steps_observes_selects_and_reads_back() {
    let store = temp_store("flow");
    let s = Server::start(&store, &[]);
    let (code, health) = s.get("/v1/health");
    assert_eq!((code, health["provider"].as_str()), (200, Some("cpu")));

    let (code, created) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 }, "policy": { "kind": "worldpack" } }));
    assert_eq!(code, 201, "{created}");
    let id = created["session"].as_u64().unwrap();
    let mut last_pose = Value::Null;
    for i in 1..=20u64 {
        let turn = if i % 5 == 0 { 12.0 } else { 0.0 };
        let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true, "yaw_deg": turn } }));
        assert_eq!(code, 200, "{r}");
        assert_eq!(r["index"].as_u64(), Some(i));
        let png = B64.decode(r["image_png"].as_str().unwrap()).unwrap();
        assert_eq!(&png[1..4], b"PNG");
        let plan = r["selection"]["plan"]["slots"].as_array().unwrap();
        assert_eq!(plan.len(), 22, "worldpack packs 22 slots");
        let used: Vec<u64> = plan.iter().filter_map(|s| s["frame"].as_u64()).collect();
        assert_eq!(used.len() as u64, i.min(22), "every earlier frame fits until there are 22");
        assert!(used.iter().all(|&f| f < i), "only earlier frames are context");
        assert_ne!(r["pose"], last_pose, "the motion model moved the camera");
        last_pose = r["pose"].clone();
        let psnr = r["truth"]["psnr_db"].as_f64().unwrap();
        assert!(psnr.is_finite() && psnr > 5.0, "a synthetic step scores itself against the world: {}", r["truth"]);
        assert_eq!(r["truth"]["image"], format!("/v1/sessions/{id}/frames/{i}/truth"));
        assert!(r["selection"]["warp_frames"] == json!([]) && r["timings_ms"]["warp"] == 0.0, "this model takes no warp: {r}");
    }
    // The first frame is the world's own render, so its truth is the same picture.
    assert_eq!(s.bytes(&format!("/v1/sessions/{id}/frames/0/truth")), s.bytes(&format!("/v1/sessions/{id}/frames/0/image")));
    assert_ne!(s.bytes(&format!("/v1/sessions/{id}/frames/7/truth")), s.bytes(&format!("/v1/sessions/{id}/frames/7/image")));
    // Observe a real frame (the first one again), then ask what a pose would use.
    let image = B64.encode(s.bytes(&format!("/v1/sessions/{id}/frames/0/image")));
    let (code, frame0) = s.get(&format!("/v1/sessions/{id}/frames/0"));
    assert_eq!(code, 200);
    let pose = json!({ "c2w": frame0["pose"] });
    let (code, r) = s.post(&format!("/v1/sessions/{id}/observe"), &json!({ "image_png": image, "pose": pose }));
    assert_eq!((code, r["index"].as_u64()), (200, Some(21)), "{r}");
    let (code, r) = s.post(&format!("/v1/sessions/{id}/select"), &json!({ "pose": pose }));
    assert_eq!(code, 200, "{r}");
    let best = &r["plan"]["slots"][0];
    assert!(best["frame"] == 0 || best["frame"] == 21, "the frames taken from this very pose rank first: {best}");
    assert!((best["overlap"].as_f64().unwrap() - 1.0).abs() < 1e-9);

    let (code, r) = s.get(&format!("/v1/sessions/{id}"));
    assert_eq!((code, r["frames"].as_u64()), (200, Some(22)));
    let (code, r) = s.get(&format!("/v1/sessions/{id}/frames/7"));
    assert_eq!((code, r["source"].as_str()), (200, Some("generated")));
    let (code, _) = answer(HTTP.delete(&format!("{}/v1/sessions/{id}", s.url)).call());
    assert_eq!(code, 204);
    assert_eq!(s.get(&format!("/v1/sessions/{id}")).0, 404);
    let text = HTTP.get(&format!("{}/metrics", s.url)).call().unwrap().into_string().unwrap();
    assert!(text.contains("worldpack_steps_total 20") && text.contains("worldpack_observes_total 1"), "{text}");
}

#[test]
fn without_a_model_the_server_is_a_memory_store() {
    let store = temp_store("memory");
    let with_model = Server::start(&temp_store("memory-src"), &[]);
    let (_, created) = with_model.post("/v1/sessions", &json!({ "synthetic": { "seed": 5 } }));
    let png = B64.encode(with_model.bytes(&format!("/v1/sessions/{}/frames/0/image", created["session"])));
    drop(with_model);

    let s = Server::start(&store, &["--memory-only"]);
    let intrinsics = json!({ "hfov_deg": 70, "width": 64, "height": 64 });
    let (code, r) = s.post("/v1/sessions", &json!({ "frames": [{ "image_png": png, "pose": c2w([0.0, 0.0, 0.0]) }], "intrinsics": intrinsics }));
    assert_eq!(code, 201, "{r}");
    let id = r["session"].as_u64().unwrap();
    for x in 1..5 {
        let (code, r) = s.post(&format!("/v1/sessions/{id}/observe"), &json!({ "image_png": png, "pose": c2w([x as f64 * 5.0, 0.0, 0.0]) }));
        assert_eq!((code, r["has_latent"].as_bool()), (200, Some(false)), "{r}");
    }
    let (code, r) = s.post(&format!("/v1/sessions/{id}/select"), &json!({ "pose": c2w([20.0, 0.0, 1.0]) }));
    assert_eq!(code, 200);
    assert_eq!(r["plan"]["slots"][0]["frame"], 4, "the nearest view ranks first: {r}");
    assert_eq!(r["plan"]["slots"][1]["frame"], 3, "then the one five units back: {r}");
    // Depth rides along as a 16-bit PNG (millimetres) and comes back byte for byte.
    let depth = {
        let mut out = Vec::new();
        let mut enc = png::Encoder::new(&mut out, 64, 64);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Sixteen);
        let mm: Vec<u8> = (0..64 * 64u32).flat_map(|i| ((1000 + i) as u16).to_be_bytes()).collect();
        enc.write_header().unwrap().write_image_data(&mm).unwrap();
        out
    };
    let (code, r) = s.post(&format!("/v1/sessions/{id}/observe"), &json!({ "image_png": png, "pose": c2w([21.0, 0.0, 0.0]), "depth_png16": B64.encode(&depth) }));
    assert_eq!(code, 200, "{r}");
    let index = r["index"].as_u64().unwrap();
    assert_eq!(s.bytes(&format!("/v1/sessions/{id}/frames/{index}/depth")), depth);
    assert_eq!(s.get(&format!("/v1/sessions/{id}/frames/1/depth")).1["error"]["field"], "depth");
    let (code, r) = s.get(&format!("/v1/sessions/{id}/frames/1/truth"));
    assert_eq!((code, r["error"]["field"].as_str()), (404, Some("truth")), "real frames have no truth here: {r}");
    let (code, r) = s.post(&format!("/v1/sessions/{id}/observe"), &json!({ "image_png": png, "pose": c2w([0.0; 3]), "depth_png16": png }));
    assert_eq!((code, r["error"]["field"].as_str()), (400, Some("depth_png16")), "an RGB image is not a depth map: {r}");
    let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true } }));
    assert_eq!((code, r["error"]["field"].as_str()), (409, Some("model")));
}

#[test]
fn bad_requests_get_4xx_json_naming_the_field() {
    let s = Server::start(&temp_store("bad"), &[]);
    let (_, created) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 } }));
    let id = created["session"].as_u64().unwrap();
    let step = format!("/v1/sessions/{id}/step");
    let small_png = {
        // A 32x32 frame: the session camera says 64x64.
        let mut out = Vec::new();
        let mut enc = png::Encoder::new(&mut out, 32, 32);
        enc.set_color(png::ColorType::Rgb);
        enc.write_header().unwrap().write_image_data(&[90u8; 32 * 32 * 3]).unwrap();
        B64.encode(out)
    };
    let cases: Vec<(&str, String, Value, u16, &str)> = vec![
        ("unknown session", "/v1/sessions/999/step".into(), json!({ "action": {} }), 404, "session"),
        ("bad session id", "/v1/sessions/abc/step".into(), json!({ "action": {} }), 400, "session"),
        ("turn too large", step.clone(), json!({ "action": { "yaw_deg": 1000 } }), 400, "action.yaw_deg"),
        ("key not a bool", step.clone(), json!({ "action": { "jump": "yes" } }), 400, "action.jump"),
        ("no action", step.clone(), json!({}), 400, "action"),
        ("unknown field", step.clone(), json!({ "action": {}, "speed": 2 }), 400, "speed"),
        ("far-away pose", step.clone(), json!({ "action": {}, "pose": c2w([0.0, 1e308, 0.0]) }), 400, "pose.position"),
        ("not a rotation", step.clone(), json!({ "action": {}, "pose": { "c2w": { "rotation": [[2, 0, 0], [0, 1, 0], [0, 0, 1]], "position": [0, 0, 0] } } }), 400, "pose.rotation"),
        ("zero steps", step.clone(), json!({ "action": {}, "steps": 0 }), 400, "steps"),
        ("unknown policy", "/v1/sessions".into(), json!({ "synthetic": { "seed": 1 }, "policy": { "kind": "magic" } }), 400, "policy.kind"),
        ("both starts", "/v1/sessions".into(), json!({ "synthetic": { "seed": 1 }, "frames": [] }), 400, "frames"),
        ("no intrinsics", "/v1/sessions".into(), json!({ "frames": [{ "image_png": small_png, "pose": c2w([0.0; 3]) }] }), 400, "intrinsics"),
        ("wrong image size", "/v1/sessions".into(),
            json!({ "frames": [{ "image_png": small_png, "pose": c2w([0.0; 3]) }], "intrinsics": { "hfov_deg": 70, "width": 64, "height": 64 } }), 400, "frames[0].image_png"),
        ("not a png", format!("/v1/sessions/{id}/observe"), json!({ "image_png": "aGVsbG8=", "pose": c2w([0.0; 3]) }), 400, "image_png"),
        ("bad fov", "/v1/sessions".into(), json!({ "frames": [{ "image_png": small_png, "pose": c2w([0.0; 3]) }], "intrinsics": { "hfov_deg": 200, "width": 32, "height": 32 } }), 400, "intrinsics.hfov_deg"),
    ];
    for (what, path, body, status, field) in cases {
        let (code, r) = s.post(&path, &body);
        assert_eq!(code, status, "{what}: {r}");
        assert_eq!(r["error"]["field"].as_str(), Some(field), "{what}: {r}");
        assert!(!r["error"]["message"].as_str().unwrap().is_empty(), "{what}");
    }
    // JSON has no NaN; an overflowing number is the closest a client can send.
    let (code, r) = answer(HTTP.post(&format!("{}{step}", s.url)).set("Content-Type", "application/json")
        .send_string(r#"{"action": {}, "pose": {"c2w": {"rotation": [[1,0,0],[0,1,0],[0,0,1]], "position": [0, 1e999, 0]}}}"#));
    assert_eq!((code, r["error"]["field"].as_str()), (400, Some("pose.c2w.position[1]")), "{r}");
    let (code, r) = answer(HTTP.post(&format!("{}{step}", s.url)).set("Content-Type", "text/plain").send_string("{}"));
    assert_eq!((code, r["error"]["field"].as_str()), (415, Some("content-type")));
    // A body over the limit is refused once the server has read past it. Sent by hand: a
    // client still writing when the server answers and closes sees a broken pipe, and the
    // answer is already waiting in the socket.
    let (code, r) = oversized_post(&s.url, &step, 17 << 20);
    assert_eq!((code, r["error"]["field"].as_str()), (413, Some("body")), "{r}");
    let (code, r) = s.get("/v1/nowhere");
    assert_eq!((code, r["error"]["field"].as_str()), (404, Some("path")));
    // The session is untouched by all of it.
    let (_, r) = s.get(&format!("/v1/sessions/{id}"));
    assert_eq!(r["frames"], 1);
}

#[test]
fn sixteen_sessions_step_concurrently() {
    let s = Server::start(&temp_store("concurrent"), &[]);
    let ids: Vec<u64> = (0..16).map(|i| s.post("/v1/sessions", &json!({ "synthetic": { "seed": i % 4 } })).1["session"].as_u64().unwrap()).collect();
    std::thread::scope(|scope| {
        for &id in &ids {
            let s = &s;
            scope.spawn(move || {
                for i in 1..=3u64 {
                    let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true } }));
                    assert_eq!(code, 200, "session {id}: {r}");
                    assert_eq!(r["index"].as_u64(), Some(i), "steps within a session are ordered");
                }
            });
        }
    });
    for id in ids {
        assert_eq!(s.get(&format!("/v1/sessions/{id}")).1["frames"], 4);
    }
}

#[test]
fn the_openapi_document_describes_the_routes_and_docs_are_served_offline() {
    let s = Server::start(&temp_store("openapi"), &["--memory-only"]);
    let (code, doc) = s.get("/openapi.json");
    assert_eq!(code, 200);
    let paths = doc["paths"].as_object().unwrap();
    assert!(paths.len() >= 9);
    for (path, item) in paths {
        let concrete = path.replace("{id}", "999999").replace("{index}", "0");
        for method in item.as_object().unwrap().keys().filter(|m| ["get", "post", "delete"].contains(&m.as_str())) {
            let url = format!("{}{concrete}", s.url);
            let resp = match method.as_str() {
                "get" => HTTP.get(&url).call(),
                "delete" => HTTP.delete(&url).call(),
                _ => HTTP.post(&url).set("Content-Type", "application/json").send_string("{}"),
            };
            let (code, body) = answer(resp);
            assert_ne!(body["error"]["field"], "path", "{method} {path} is documented but not routed ({code})");
        }
    }
    let html = HTTP.get(&format!("{}/docs/", s.url)).call().unwrap().into_string().unwrap();
    assert!(html.contains("swagger-ui"), "the docs page is Swagger UI, served from the binary");
}

#[test]
fn full_queues_answer_429_and_503_and_lose_nothing() {
    let s = Server::start(&temp_store("queues"), &["--max-queue", "1", "--max-inflight", "1"]);
    let ids: Vec<u64> = (0..2).map(|_| s.post("/v1/sessions", &json!({ "synthetic": { "seed": 1 } })).1["session"].as_u64().unwrap()).collect();
    // Many slow steps at once: on one session they queue (429 past one waiting),
    // across sessions they compete for the one model slot (503).
    let codes: Vec<u16> = std::thread::scope(|scope| {
        let workers: Vec<_> = (0..8)
            .map(|i| {
                let (s, id) = (&s, ids[i % 2]);
                scope.spawn(move || s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true }, "steps": 40 })))
            })
            .collect();
        workers.into_iter().map(|w| w.join().unwrap()).map(|(code, r)| {
            if code != 200 {
                assert!(r["error"]["message"].as_str().is_some(), "{r}");
            }
            code
        }).collect()
    });
    assert!(codes.iter().all(|c| [200, 429, 503].contains(c)), "{codes:?}");
    assert!(codes.contains(&200), "{codes:?}");
    assert!(codes.iter().any(|&c| c == 429 || c == 503), "8 concurrent slow steps against queue 1 / in-flight 1: {codes:?}");
    // Exactly the accepted steps were stored.
    let stored: u64 = ids.iter().map(|id| s.get(&format!("/v1/sessions/{id}")).1["frames"].as_u64().unwrap() - 1).sum();
    assert_eq!(stored, codes.iter().filter(|&&c| c == 200).count() as u64);
}

#[test]
fn overlay_warp_needs_a_geometry_model() {
    let out = Command::new(env!("CARGO_BIN_EXE_worldpack"))
        .args(["serve", "--model", "fixtures/small", "--addr", "127.0.0.1:0", "--store", temp_store("overlay").to_str().unwrap(), "--overlay-warp"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--overlay-warp"), "{}", String::from_utf8_lossy(&out.stderr));
}

/// The paper's token geometry end to end (fixtures/paper_tokens: 224x224
/// frames, 28x28 latents, random weights): a synthetic session steps until
/// its memory fills the 22 packed slots, and every answer is a 224x224 frame.
#[test]
fn the_paper_token_geometry_serves_a_synthetic_session() {
    let store = temp_store("paper-tokens");
    let model = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/paper_tokens");
    let s = Server::start(&store, &["--model", model]);
    let (code, created) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 }, "policy": { "kind": "worldpack" } }));
    assert_eq!(code, 201, "{created}");
    let id = created["session"].as_u64().unwrap();
    for i in 1..=24u64 {
        let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true, "yaw_deg": 15 } }));
        assert_eq!(code, 200, "{r}");
        let png = B64.decode(r["image_png"].as_str().unwrap()).unwrap();
        let side = |at: usize| u32::from_be_bytes(png[at..at + 4].try_into().unwrap());
        assert_eq!((&png[12..16], side(16), side(20)), (&b"IHDR"[..], 224, 224), "step {i}: the frame is 224x224");
        let slots = r["selection"]["plan"]["slots"].as_array().unwrap();
        let used_at = |rate: u64| slots.iter().filter(|s| s["rate"] == rate && s["frame"].is_u64()).count() as u64;
        let used = used_at(1) + used_at(4) + used_at(16);
        assert_eq!(used, i.min(22), "step {i}: every earlier frame fits until there are 22");
        if i > 22 {
            assert_eq!((used_at(1), used_at(4), used_at(16)), (2, 4, 16), "step {i}: the paper's 2 + 4 + 16 slots");
        }
    }
}
