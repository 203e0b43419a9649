//! Imagine over HTTP (docs/api.md#imagine): one candidate is a fork stepped
//! H times, frame for frame; the session is left as it was; candidates share
//! model calls without changing their frames; a goal image is scored; bad
//! candidates, horizons and sizes are refused naming the field.

mod support;

use serde_json::{Value, json};
use support::*;

fn session(s: &Server, seed: u64) -> u64 {
    let (code, c) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": seed } }));
    assert_eq!(code, 201, "{c}");
    let id = c["session"].as_u64().unwrap();
    for _ in 0..2 {
        let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true }, "observe": true }));
        assert_eq!(code, 200, "{r}");
    }
    id
}

fn imagine(s: &Server, id: u64, body: Value) -> Value {
    let (code, r) = s.post(&format!("/v1/sessions/{id}/imagine"), &body);
    assert_eq!(code, 200, "{r}");
    r
}

fn actions() -> Vec<Value> {
    vec![json!({ "forward": true }), json!({ "yaw_deg": 15 }), json!({ "forward": true, "yaw_deg": -10 }), json!({ "left": true })]
}

fn rgb(b64: &Value) -> Vec<u8> {
    use base64::Engine;
    let png = base64::engine::general_purpose::STANDARD.decode(b64.as_str().unwrap()).unwrap();
    world::picture::decode_rgb(&png).unwrap().0
}

#[test]
fn one_candidate_is_a_fork_stepped_h_times() {
    let s = Server::start(&temp_store("imagine-fork"), &[]);
    let id = session(&s, 3);
    for seed in [Some(11u64), None] {
        let mut body = json!({ "candidates": [{ "actions": actions() }], "frames": "all" });
        if let Some(seed) = seed {
            body["seed"] = json!(seed);
        }
        let r = imagine(&s, id, body);
        assert_eq!((r["from"].as_u64(), r["horizon"].as_u64(), r["model_calls"].as_u64()), (Some(3), Some(4), Some(4)), "{r}");
        let imagined = &r["candidates"][0];
        let (code, f) = s.post(&format!("/v1/sessions/{id}/fork"), &json!({}));
        assert_eq!(code, 201, "{f}");
        let fork = f["session"].as_u64().unwrap();
        for (h, action) in actions().into_iter().enumerate() {
            let mut step = json!({ "action": action });
            if let Some(seed) = seed {
                step["seed"] = json!(seed + h as u64);
            }
            let (code, stepped) = s.post(&format!("/v1/sessions/{fork}/step"), &step);
            assert_eq!(code, 200, "{stepped}");
            let frame = &imagined["frames"][h];
            assert_eq!((frame["step"].as_u64(), frame["index"].as_u64()), (Some(h as u64), stepped["index"].as_u64()));
            assert_eq!(imagined["poses"][h], stepped["pose"], "seed {seed:?}, step {h}: the pose");
            assert_eq!(frame["image_png"], stepped["image_png"], "seed {seed:?}, step {h}: the frame");
        }
    }
}

#[test]
fn imagining_leaves_the_session_as_it_was() {
    let store = temp_store("imagine-unchanged");
    let s = Server::start(&store, &[]);
    let id = session(&s, 4);
    let before = s.get(&format!("/v1/sessions/{id}")).1;
    let probe = json!({ "pose": { "c2w": s.get(&format!("/v1/sessions/{id}/frames/2")).1["pose"] } });
    let plan_before = s.post(&format!("/v1/sessions/{id}/select"), &probe).1["plan"].clone();
    // A fork made now holds the session as it is, to step against afterwards.
    let witness = s.post(&format!("/v1/sessions/{id}/fork"), &json!({})).1["session"].as_u64().unwrap();

    let candidates: Vec<Value> = (0..3).map(|k| json!({ "actions": [{ "yaw_deg": 20 * k }, { "forward": true }, { "forward": true }] })).collect();
    let r = imagine(&s, id, json!({ "candidates": candidates, "frames": { "every": 2 }, "format": "latent" }));
    assert_eq!(r["latent_shape"].as_array().map(Vec::len), Some(3), "{r}");
    let c0 = &r["candidates"][0];
    assert_eq!((c0["poses"].as_array().unwrap().len(), c0["frames"].as_array().unwrap().len()), (3, 1), "every 2nd of 3 steps: step 1");
    assert!(c0["frames"][0]["latent"].is_string() && c0["frames"][0]["image_png"].is_null());

    let after = s.get(&format!("/v1/sessions/{id}")).1;
    assert_eq!(after, before, "frame count and the rest");
    assert_eq!(s.get(&format!("/v1/sessions/{id}/frames/3")).0, 404, "nothing imagined was stored");
    assert_eq!(s.post(&format!("/v1/sessions/{id}/select"), &probe).1["plan"], plan_before, "the memory chooses as before");
    let step = json!({ "action": { "forward": true }, "seed": 5 });
    let (a, b) = (s.post(&format!("/v1/sessions/{id}/step"), &step).1, s.post(&format!("/v1/sessions/{witness}/step"), &step).1);
    assert_eq!((a["index"].as_u64(), a["image_png"].clone()), (Some(3), b["image_png"].clone()), "the next step is the one it would have been");
    let metrics = String::from_utf8(s.bytes("/metrics")).unwrap();
    assert!(metrics.contains("worldpack_imagined_frames_total 9\n"), "{metrics}");
    s.kill();
    let st = api::store::Store::open(&store).unwrap();
    assert_eq!(st.frames_from(id, 0).unwrap().len(), 4, "the store holds the session's frames and the step's, none imagined");
}

/// Candidates share each step's model call; each still gets its own frames
/// (a frame does not depend on its batch, to a tolerance below one grey level).
#[test]
fn candidates_in_one_call_get_the_frames_they_would_get_alone() {
    let s = Server::start(&temp_store("imagine-batch"), &[]);
    let id = session(&s, 5);
    let alone = imagine(&s, id, json!({ "candidates": [{ "actions": actions() }], "seed": 3 }));
    let others: Vec<Value> = (1..4).map(|k| json!({ "actions": vec![json!({ "yaw_deg": 30 * k }); 4] })).collect();
    let mut all = vec![json!({ "actions": actions() })];
    all.extend(others);
    let together = imagine(&s, id, json!({ "candidates": all, "seed": 3 }));
    assert_eq!(together["model_calls"].as_u64(), Some(4), "one call per step for 4 candidates: {}", together["model_calls"]);
    let (a, b) = (rgb(&alone["candidates"][0]["frames"][0]["image_png"]), rgb(&together["candidates"][0]["frames"][0]["image_png"]));
    let worst = a.iter().zip(&b).map(|(x, y)| x.abs_diff(*y)).max().unwrap();
    assert!(worst <= 2, "the batched frame differs by {worst} grey levels");
    assert_ne!(together["candidates"][1]["frames"][0]["image_png"], together["candidates"][0]["frames"][0]["image_png"], "other actions, another future");
}

/// Candidates that begin alike are one future until they part: its frames are made once,
/// and each candidate still gets, frame for frame, what it gets imagined alone.
#[test]
fn candidates_with_the_same_first_actions_share_those_frames() {
    let s = Server::start(&temp_store("imagine-prefix"), &[]);
    let id = session(&s, 8);
    let (go, turn) = (json!({ "forward": true }), json!({ "yaw_deg": 15 }));
    let seqs = [vec![go.clone(), go.clone(), turn.clone()], vec![go.clone(), go.clone(), go.clone()], vec![go.clone(), turn.clone(), go.clone()], vec![turn.clone(), go.clone(), go.clone()]];
    let body = |seqs: &[Vec<Value>]| json!({ "candidates": seqs.iter().map(|a| json!({ "actions": a })).collect::<Vec<_>>(), "seed": 5, "frames": "all" });
    let together = imagine(&s, id, body(&seqs));
    // Step 0: go, turn; step 1: go·go, go·turn, turn·go; step 2: all four apart.
    assert_eq!(together["frames_made"].as_u64(), Some(2 + 3 + 4), "{}", together["frames_made"]);
    for (k, seq) in seqs.iter().enumerate() {
        let alone = imagine(&s, id, body(std::slice::from_ref(seq)));
        assert_eq!(alone["frames_made"].as_u64(), Some(3));
        for h in 0..3 {
            let (a, b) = (rgb(&alone["candidates"][0]["frames"][h]["image_png"]), rgb(&together["candidates"][k]["frames"][h]["image_png"]));
            let worst = a.iter().zip(&b).map(|(x, y)| x.abs_diff(*y)).max().unwrap();
            assert!(worst <= 2, "candidate {k}, step {h}: differs from alone by {worst} grey levels");
        }
    }
    let c = &together["candidates"];
    assert_eq!(c[0]["frames"][1]["image_png"], c[1]["frames"][1]["image_png"], "one prefix, one frame");
    assert_ne!(c[0]["frames"][2]["image_png"], c[1]["frames"][2]["image_png"], "apart at step 2");
}
/// Returning to the view of frame 0 scores closer to a goal of frame 0 than looking away.
#[test]
fn a_goal_image_scores_the_candidates() {
    let s = Server::start(&temp_store("imagine-goal"), &[]);
    let id = session(&s, 6);
    let start = s.get(&format!("/v1/sessions/{id}/frames/0")).1["pose"].clone();
    let away = json!({ "c2w": { "rotation": [[-1, 0, 0], [0, 1, 0], [0, 0, -1]], "position": start["position"] } });
    let goal = {
        use base64::Engine;
        base64::engine::general_purpose::STANDARD.encode(s.bytes(&format!("/v1/sessions/{id}/frames/0/image")))
    };
    let r = imagine(&s, id, json!({ "candidates": [{ "poses": [{ "c2w": start }] }, { "poses": [away] }], "goal_png": goal, "frames": "none" }));
    let (back, turned) = (&r["candidates"][0]["goal"], &r["candidates"][1]["goal"]);
    assert!(back["psnr_db"].as_f64().unwrap() > turned["psnr_db"].as_f64().unwrap(), "back {back}, turned {turned}");
    assert!(back["latent_mse"].as_f64().unwrap() < turned["latent_mse"].as_f64().unwrap(), "back {back}, turned {turned}");
    assert!(r["candidates"][0]["frames"].as_array().unwrap().is_empty());
}

/// Scored by latents alone, a last step whose frame is not answered is not decoded: no PSNR,
/// and (this model has no heads, so a step's memory keeps the sampled latent) the same
/// latent difference as when it is decoded.
#[test]
fn a_goal_scored_by_latents_alone_leaves_the_last_step_undecoded() {
    let s = Server::start(&temp_store("imagine-latent-goal"), &[]);
    let id = session(&s, 6);
    let goal = {
        use base64::Engine;
        base64::engine::general_purpose::STANDARD.encode(s.bytes(&format!("/v1/sessions/{id}/frames/0/image")))
    };
    let candidates = json!([{ "actions": [{ "forward": true }, { "yaw_deg": 15 }] }, { "actions": [{ "yaw_deg": -30 }, { "forward": true }] }]);
    let ask = |extra: Value| {
        let mut body = json!({ "candidates": candidates, "goal_png": goal, "seed": 3 });
        body.as_object_mut().unwrap().extend(extra.as_object().unwrap().clone());
        imagine(&s, id, body)
    };
    let both = ask(json!({ "frames": "none" }));
    let latent = ask(json!({ "frames": "none", "goal_score": "latent" }));
    let shown = ask(json!({ "frames": "last", "goal_score": "latent" }));
    for k in 0..2 {
        let (b, l) = (&both["candidates"][k]["goal"], &latent["candidates"][k]["goal"]);
        assert!(b["psnr_db"].as_f64().is_some() && l["psnr_db"].is_null(), "{b} {l}");
        assert_eq!(b["latent_mse"], l["latent_mse"], "candidate {k}");
        assert!(shown["candidates"][k]["frames"][0]["image_png"].is_string() && shown["candidates"][k]["goal"]["psnr_db"].is_null());
    }
}

#[test]
fn bad_candidates_horizons_and_sizes_are_refused_naming_the_field() {
    let s = Server::start(&temp_store("imagine-bad"), &[]);
    let id = session(&s, 7);
    let one = json!({ "actions": [{}] });
    let pose = json!({ "c2w": { "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "position": [0, 70, 0] } });
    let cases: Vec<(Value, &str)> = vec![
        (json!({ "candidates": [] }), "candidates"),
        (json!({ "candidates": vec![one.clone(); 65] }), "candidates"),
        (json!({}), "candidates"),
        (json!({ "candidates": [{}] }), "candidates[0].actions"),
        (json!({ "candidates": [{ "actions": [] }] }), "candidates[0].actions"),
        (json!({ "candidates": [{ "actions": vec![json!({}); 65] }] }), "candidates[0].actions"),
        (json!({ "candidates": [one.clone(), { "actions": [{}, {}] }] }), "candidates[1].actions"),
        (json!({ "candidates": [{ "actions": [{}, { "yaw_deg": 999 }] }] }), "candidates[0].actions[1].yaw_deg"),
        (json!({ "candidates": [{ "actions": [{ "fly": true }] }] }), "candidates[0].actions[0]"),
        (json!({ "candidates": [{ "actions": [{}], "poses": [pose.clone(), pose.clone()] }] }), "candidates[0].poses"),
        (json!({ "candidates": [{ "poses": [{ "c2w": { "rotation": [[2, 0, 0], [0, 1, 0], [0, 0, 1]], "position": [0, 0, 0] } }] }] }), "candidates[0].poses[0]"),
        (json!({ "candidates": [one.clone()], "frames": { "every": 0 } }), "frames.every"),
        (json!({ "candidates": [one.clone()], "frames": "sometimes" }), "frames"),
        (json!({ "candidates": [one.clone()], "format": "jpeg" }), "format"),
        (json!({ "candidates": [one.clone()], "steps": 0 }), "steps"),
        (json!({ "candidates": [one.clone()], "seed": u64::MAX }), "seed"),
        (json!({ "candidates": [one.clone()], "goal_png": "not base64!" }), "goal_png"),
        (json!({ "candidates": [one.clone()], "goal_score": "ssim" }), "goal_score"),
        (json!({ "candidates": vec![json!({ "actions": vec![json!({}); 64] }); 64], "frames": "all" }), "frames"),
    ];
    for (body, field) in cases {
        let (code, r) = s.post(&format!("/v1/sessions/{id}/imagine"), &body);
        assert_eq!(code, 400, "{body}: {r}");
        let named = r["error"]["field"].as_str().unwrap_or_default();
        assert!(named.starts_with(field), "{body}: named {named:?}, not {field}: {r}");
    }
    // A goal of another size than the model's frames.
    let small = {
        use base64::Engine;
        let mut bytes = Vec::new();
        let mut encoder = png::Encoder::new(&mut bytes, 8, 8);
        encoder.set_color(png::ColorType::Rgb);
        encoder.write_header().unwrap().write_image_data(&[7; 8 * 8 * 3]).unwrap();
        base64::engine::general_purpose::STANDARD.encode(bytes)
    };
    let (code, r) = s.post(&format!("/v1/sessions/{id}/imagine"), &json!({ "candidates": [one.clone()], "goal_png": small }));
    assert_eq!((code, r["error"]["field"].as_str()), (400, Some("goal_png")), "{r}");
    let (code, r) = s.post("/v1/sessions/999/imagine", &json!({ "candidates": [one] }));
    assert_eq!((code, r["error"]["field"].as_str()), (404, Some("session")), "{r}");
    assert_eq!(s.get(&format!("/v1/sessions/{id}")).1["frames"].as_u64(), Some(3), "nothing refused was stored");
}

#[test]
fn the_limits_are_the_servers_flags() {
    let s = Server::start(&temp_store("imagine-limits"), &["--imagine-max-candidates", "2", "--imagine-max-horizon", "3"]);
    let id = session(&s, 7);
    let one = json!({ "actions": [{}] });
    let (code, r) = s.post(&format!("/v1/sessions/{id}/imagine"), &json!({ "candidates": [one.clone(), one.clone(), one.clone()] }));
    assert_eq!((code, r["error"]["field"].as_str()), (400, Some("candidates")), "{r}");
    let (code, r) = s.post(&format!("/v1/sessions/{id}/imagine"), &json!({ "candidates": [{ "actions": [{}, {}, {}, {}] }] }));
    assert_eq!((code, r["error"]["field"].as_str()), (400, Some("candidates[0].actions")), "{r}");
    let r = imagine(&s, id, json!({ "candidates": [{ "actions": [{}, {}, {}] }, { "actions": [{}, {}, {}] }] }));
    assert_eq!(r["candidates"].as_array().map(Vec::len), Some(2), "{r}");
}

#[test]
fn a_server_without_a_model_cannot_imagine() {
    let s = Server::start(&temp_store("imagine-memory-only"), &["--memory-only"]);
    let (code, r) = s.post("/v1/sessions/1/imagine", &json!({ "candidates": [{ "actions": [{}] }] }));
    assert_eq!((code, r["error"]["field"].as_str()), (409, Some("model")), "{r}");
}
