//! Sessions at their frames' size: a synthetic session at 224×224 and a
//! session of a user's 256×256 frames answer every step at that size, keep
//! it across restarts on redb and PostgreSQL, and show stored frames at the
//! size they were seen; frames beyond the server's cap are refused by field.

mod support;

use std::path::Path;

use base64::Engine;
use base64::engine::general_purpose::STANDARD as B64;
use serde_json::{Value, json};
use support::*;

const SERVED: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/variants/worldpack_geometry_fused_1step");

/// A PNG's width and height, and its pixels as RGB.
fn decode(png_bytes: &[u8]) -> (u32, u32, Vec<u8>) {
    let mut decoder = png::Decoder::new(png_bytes);
    decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).unwrap();
    let channels = info.color_type.samples();
    let rgb = buf[..info.buffer_size()].chunks(channels).flat_map(|p| [p[0], p[1], p[2]]).collect();
    (info.width, info.height, rgb)
}

fn grey_png(w: u32, h: u32) -> Vec<u8> {
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, w, h);
    enc.set_color(png::ColorType::Rgb);
    enc.write_header().unwrap().write_image_data(&vec![128; (w * h * 3) as usize]).unwrap();
    out
}

fn answered(r: &Value) -> (u32, u32, Vec<u8>) {
    let png = B64.decode(r["image_png"].as_str().unwrap()).unwrap();
    let (w, h, rgb) = decode(&png);
    assert_eq!((r["width"].as_u64(), r["height"].as_u64()), (Some(w as u64), Some(h as u64)), "the answer states the PNG's size");
    (w, h, rgb)
}

fn psnr(a: &[u8], b: &[u8]) -> f64 {
    let mse = a.iter().zip(b).map(|(&x, &y)| (x as f64 - y as f64).powi(2)).sum::<f64>() / a.len() as f64;
    10.0 * (255.0f64 * 255.0 / mse.max(1e-12)).log10()
}

/// Observes a few steps forward at 224×224, turns back by generated steps
/// and checks every answer and stored frame is at that size; after a
/// restart the frames come back at that size and the session steps on at it.
fn a_synthetic_session_at_224_keeps_its_size(store: &Path) {
    let s = Server::start(store, &["--model", SERVED]);
    let (code, c) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3, "size": 224 } }));
    assert_eq!(code, 201, "{c}");
    let id = c["session"].as_u64().unwrap();
    let (_, info) = s.get(&format!("/v1/sessions/{id}"));
    assert_eq!((info["intrinsics"]["width"].as_u64(), info["intrinsics"]["height"].as_u64()), (Some(224), Some(224)), "{info}");
    let step = |body: Value| s.post(&format!("/v1/sessions/{id}/step"), &body);
    for _ in 0..3 {
        let (code, r) = step(json!({ "action": { "forward": true }, "observe": true }));
        assert_eq!((code, r["width"].as_u64()), (200, Some(224)), "{r}");
    }
    // Back at an observed pose, the stored frame lands everywhere: the answer
    // is that frame at full size, not a 64×64 frame brought up.
    let (_, frame1) = s.get(&format!("/v1/sessions/{id}/frames/1"));
    let (code, r) = step(json!({ "action": {}, "pose": { "c2w": frame1["pose"] } }));
    assert_eq!(code, 200, "{r}");
    let (w, h, shown) = answered(&r);
    assert_eq!((w, h), (224, 224));
    let (_, _, truth) = decode(&s.bytes(&format!("/v1/sessions/{id}/frames/1/image")));
    assert!(psnr(&shown, &truth) > 35.0, "the stored frame is shown: {:.2} dB", psnr(&shown, &truth));
    assert!(r["timings_ms"]["full_size"].as_f64().unwrap() > 0.0, "{r}");
    // Generated steps away from any stored pose answer at the session's size too.
    let (code, r) = step(json!({ "action": { "yaw_deg": 30 } }));
    assert_eq!(code, 200, "{r}");
    assert_eq!(answered(&r).0, 224);
    assert!(r["truth"]["psnr_db"].as_f64().unwrap() > 10.0, "{r}");
    // A step told not to score skips rendering the world's true frame.
    let (code, r) = step(json!({ "action": { "yaw_deg": -30 }, "truth": false }));
    assert_eq!((code, r["truth"].is_null(), r["timings_ms"]["truth"].as_f64()), (200, true, Some(0.0)), "{r}");
    let stored: Vec<Vec<u8>> = (0..7).map(|i| s.bytes(&format!("/v1/sessions/{id}/frames/{i}/image"))).collect();
    assert!(stored.iter().all(|p| decode(p).0 == 224), "every stored frame is at the session's size");
    s.kill();
    let s = Server::start(store, &["--model", SERVED]);
    for (i, png) in stored.iter().enumerate() {
        assert_eq!(&s.bytes(&format!("/v1/sessions/{id}/frames/{i}/image")), png, "frame {i} after the restart");
    }
    let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true } }));
    assert_eq!((code, r["index"].as_u64()), (200, Some(7)), "{r}");
    assert_eq!(answered(&r).0, 224);
    s.kill();
}

#[test]
fn a_synthetic_session_at_224_keeps_its_size_on_redb() {
    a_synthetic_session_at_224_keeps_its_size(&temp_store("full-size"));
}

#[test]
fn a_synthetic_session_at_224_keeps_its_size_on_postgres() {
    let pg = PgCluster::start("full-size");
    a_synthetic_session_at_224_keeps_its_size(&pg.url());
}

/// A user's own 256×256 frames with depth (here the world's, taken from a
/// synthetic session at that size) make a session whose steps answer at 256×256.
#[test]
fn a_users_256_frames_come_back_at_256() {
    let s = Server::start(&temp_store("full-size-own"), &["--model", SERVED]);
    let (_, c) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 5, "size": 256 } }));
    let world = c["session"].as_u64().unwrap();
    for _ in 0..2 {
        let (code, r) = s.post(&format!("/v1/sessions/{world}/step"), &json!({ "action": { "forward": true }, "observe": true }));
        assert_eq!(code, 200, "{r}");
    }
    let (_, info) = s.get(&format!("/v1/sessions/{world}"));
    let frame = |i: u64| (s.get(&format!("/v1/sessions/{world}/frames/{i}")).1, s.bytes(&format!("/v1/sessions/{world}/frames/{i}/image")), s.bytes(&format!("/v1/sessions/{world}/frames/{i}/depth")));
    let (meta0, png0, _) = frame(0);
    let (code, c) = s.post("/v1/sessions", &json!({
        "frames": [{ "image_png": B64.encode(&png0), "pose": { "c2w": meta0["pose"] } }],
        "intrinsics": info["intrinsics"],
    }));
    assert_eq!(code, 201, "{c}");
    let own = c["session"].as_u64().unwrap();
    for i in 1..=2 {
        let (meta, png, depth) = frame(i);
        let (code, r) = s.post(&format!("/v1/sessions/{own}/observe"), &json!({ "image_png": B64.encode(&png), "pose": { "c2w": meta["pose"] }, "depth_png16": B64.encode(&depth) }));
        assert_eq!(code, 200, "{r}");
    }
    let (meta2, png2, _) = frame(2);
    let (code, r) = s.post(&format!("/v1/sessions/{own}/step"), &json!({ "action": {}, "pose": { "c2w": meta2["pose"] } }));
    assert_eq!(code, 200, "{r}");
    let (w, h, shown) = answered(&r);
    assert_eq!((w, h), (256, 256));
    assert!(psnr(&shown, &decode(&png2).2) > 35.0, "the user's frame is shown at its size");
    // A frame of another size than the session's is refused by name.
    let (code, r) = s.post(&format!("/v1/sessions/{own}/observe"), &json!({ "image_png": B64.encode(grey_png(64, 64)), "pose": { "c2w": meta2["pose"] } }));
    assert_eq!((code, r["error"]["field"].as_str()), (400, Some("image_png")), "{r}");
    s.kill();
}

#[test]
fn frames_beyond_the_cap_are_refused_naming_the_field() {
    let s = Server::start(&temp_store("full-size-cap"), &["--model", SERVED, "--max-frame-side", "256"]);
    let (code, r) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3, "size": 320 } }));
    assert_eq!((code, r["error"]["field"].as_str()), (400, Some("synthetic.size")), "{r}");
    assert!(r["error"]["message"].as_str().unwrap().contains("--max-frame-side"), "{r}");
    let big = json!({ "width": 1024, "height": 768, "fx": 800.0, "fy": 800.0, "cx": 511.5, "cy": 383.5 });
    let (code, r) = s.post("/v1/sessions", &json!({ "frames": [{ "image_png": "AAAA", "pose": c2w([0.0, 0.0, 0.0]) }], "intrinsics": big }));
    assert_eq!((code, r["error"]["field"].as_str()), (400, Some("intrinsics.width")), "{r}");
    let (code, r) = s.get("/v1/sessions");
    assert_eq!((code, r["sessions"].as_array().map(Vec::len)), (200, Some(0)), "nothing was stored: {r}");
    s.kill();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_worldpack")).args(["serve", "--max-frame-side", "100"]).output().unwrap();
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("--max-frame-side"), "a cap under 256 is refused");
}
