//! The committed model through ONNX Runtime from Rust, against the PyTorch
//! references written at export: every graph, the packing of memory plans
//! into the denoiser's inputs, and the samplers step by step.

use std::path::{Path, PathBuf};

use memory::policy::{SelectedFrame, Slot};
use memory::{ContextPlan, Pose};
use model::pack::{ContextFrame, pack, stack};
use model::{Method, Model, ModelError, Provider, RuntimeOptions, Sampler, Tensor};
use serde_json::Value;

fn fixture() -> PathBuf {
    fixture_named("small")
}

/// The committed paper-token-geometry model (random weights): 224x224 frames,
/// 4x28x28 latents, 196 / 49 / 16 tokens per frame at rates 1 / 4 / 16.
fn paper_tokens() -> PathBuf {
    fixture_named("paper_tokens")
}

fn fixture_named(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures").join(name)
}

fn model() -> Model {
    load(&fixture())
}

fn load(dir: &Path) -> Model {
    Model::load(dir, RuntimeOptions { provider: Provider::Cpu, threads: 1 }).unwrap_or_else(|e| panic!("{} loads: {e}", dir.display()))
}

fn reference(folder: &str, name: &str) -> Tensor {
    reference_in(&fixture(), folder, name)
}

fn reference_in(dir: &Path, folder: &str, name: &str) -> Tensor {
    let path = dir.join(folder).join(format!("{name}.npy"));
    let (shape, data) = world::npy::read::<f32>(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    Tensor::new(shape, data)
}

fn manifest_json() -> Value {
    manifest_json_in(&fixture())
}

fn manifest_json_in(dir: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(dir.join("manifest.json")).unwrap()).unwrap()
}

/// The manifest's tolerance for its references: |a - b| <= abs + rel |b|.
#[derive(Clone, Copy)]
struct Tolerance {
    abs: f32,
    rel: f32,
}

fn tolerance(dir: &Path) -> Tolerance {
    let t = &manifest_json_in(dir)["reference"]["tolerance"];
    Tolerance { abs: t["abs"].as_f64().unwrap() as f32, rel: t["rel"].as_f64().unwrap() as f32 }
}

fn assert_close(actual: &Tensor, expected: &Tensor, what: &str, tol: Tolerance) {
    assert_eq!(actual.shape, expected.shape, "{what}: shape");
    let worst = actual
        .data
        .iter()
        .zip(&expected.data)
        .map(|(a, b)| (a - b).abs() - (tol.abs + tol.rel * b.abs()))
        .fold(f32::NEG_INFINITY, f32::max);
    assert!(worst <= 0.0, "{what}: exceeds the tolerance by {worst:e}");
}

fn inputs_of<'a>(dir: &Path, graph: &model::Graph, folder: &str, store: &'a mut Vec<(String, Tensor)>) -> Vec<(&'a str, &'a Tensor)> {
    *store = graph.spec().inputs.iter().map(|s| (s.name.clone(), reference_in(dir, folder, &s.name))).collect();
    store.iter().map(|(n, t)| (n.as_str(), t)).collect()
}

#[test]
fn every_graph_matches_pytorch() {
    graphs_match_pytorch(&fixture());
}

fn graphs_match_pytorch(dir: &Path) {
    let m = load(dir);
    assert_eq!(m.provider(), "cpu");
    let local = m.local().unwrap();
    let mut graphs: Vec<(String, &model::Graph)> = vec![("encoder".into(), &local.encoder), ("decoder".into(), &local.decoder)];
    for layout in &m.manifest().denoiser.layouts {
        graphs.push((format!("denoiser_{}", layout.name), local.denoiser(&layout.name).unwrap()));
    }
    assert_eq!(graphs.len(), 4, "encoder, decoder, worldpack and baseline denoisers");
    for (name, graph) in graphs {
        let folder = format!("reference/{name}");
        let mut store = Vec::new();
        let inputs = inputs_of(dir, graph, &folder, &mut store);
        let outputs = graph.run(&inputs).unwrap();
        for (spec, got) in graph.spec().outputs.iter().zip(&outputs) {
            assert_close(got, &reference_in(dir, &folder, &spec.name), &format!("{name}.{}", spec.name), tolerance(dir));
        }
    }
}

#[test]
fn encode_and_decode_apply_the_latent_scale() {
    let m = model();
    let scale = m.manifest().autoencoder.latent_scale as f32;
    let latent = m.encode(&reference("reference/encoder", "image")).unwrap();
    let raw = reference("reference/encoder", "latent");
    let scaled = Tensor::new(raw.shape.clone(), raw.data.iter().map(|v| v * scale).collect());
    assert_close(&latent, &scaled, "encode", tolerance(&fixture()));
    let image = m.decode(&scaled).unwrap();
    assert_close(&image, &reference("reference/decoder", "image"), "decode", tolerance(&fixture()));
}

#[test]
fn packing_a_plan_reproduces_the_reference_inputs() {
    packing_reproduces_the_reference_inputs(&fixture());
}

fn packing_reproduces_the_reference_inputs(dir: &Path) {
    let m = load(dir);
    let reference = |folder: &str, name: &str| reference_in(dir, folder, name);
    for layout in &m.manifest().denoiser.layouts {
        let folder = format!("reference/denoiser_{}", layout.name);
        let rows: Value = serde_json::from_str(&std::fs::read_to_string(dir.join(&folder).join("plan.json")).unwrap()).unwrap();
        let latent = &m.manifest().autoencoder.latent;
        let n = latent.len();
        let mut packed = Vec::new();
        for (b, row) in rows["rows"].as_array().unwrap().iter().enumerate() {
            let target_time = row["target_time"].as_u64().unwrap();
            let target = pose(&row["target_c2w"]);
            // The frames' latents are the reference context tensors themselves.
            let mut frames: Vec<(u64, Vec<f32>, Pose)> = Vec::new();
            let mut slots = Vec::new();
            let mut seen = std::collections::HashMap::new();
            for s in row["slots"].as_array().unwrap() {
                let rate = s["rate"].as_u64().unwrap() as u32;
                let at = seen.entry(rate).or_insert(0usize);
                let frame = s["frame"].as_u64().map(|id| {
                    let ctx = reference(&folder, &format!("context_r{rate}"));
                    let k = ctx.shape[1];
                    let start = (b * k + *at) * n;
                    frames.push((id, ctx.data[start..start + n].to_vec(), pose(&s["c2w"])));
                    SelectedFrame { id, time: id, overlap: 0.0, score: 0.0 }
                });
                *at += 1;
                slots.push(Slot { rate, frame });
            }
            let plan = ContextPlan { slots };
            let p = pack(layout, latent, None, &plan, target_time, &target, |id| {
                frames.iter().find(|f| f.0 == id).map(|f| ContextFrame { latent: &f.1, time: f.0, pose: &f.2, generated: false })
            })
            .unwrap();
            let want_rel = reference(&folder, "rel_time").data[b];
            assert_eq!(p.rel_time, want_rel, "rel_time of row {b}");
            packed.push(p.tensors);
        }
        let batch = stack(&packed.iter().map(|t| t.as_slice()).collect::<Vec<_>>());
        for (name, tensor) in &batch {
            assert_close(tensor, &reference(&folder, name), &format!("{} packed {name}", layout.name), tolerance(dir));
        }
    }
}

fn pose(v: &Value) -> Pose {
    Pose::from_matrix_rows(serde_json::from_value(v.clone()).unwrap()).unwrap()
}

#[test]
fn samplers_follow_the_pytorch_traces() {
    samplers_follow_the_traces(&fixture());
}

fn samplers_follow_the_traces(dir: &Path) {
    let m = load(dir);
    let reference = |folder: &str, name: &str| reference_in(dir, folder, name);
    let traces = manifest_json_in(dir)["reference"]["traces"].clone();
    for (method_name, info) in traces.as_object().unwrap() {
        let method: Method = method_name.parse().unwrap();
        let folder = info["folder"].as_str().unwrap();
        let layout = info["layout"].as_str().unwrap();
        let steps = info["steps"].as_u64().unwrap() as usize;
        let sampler = Sampler::new(&m.manifest().diffusion, steps, method, info["eta"].as_f64().unwrap()).unwrap();
        let want_t: Vec<usize> = world::npy::read::<i64>(&dir.join(folder).join("timesteps.npy")).unwrap().1.iter().map(|&t| t as usize).collect();
        assert_eq!(sampler.timesteps, want_t, "{method_name} timesteps");
        let xs = reference(folder, "x");
        let eps_ref = reference(folder, "eps");
        let noise = reference(folder, "noise");
        let per = xs.data.len() / xs.shape[0];
        let sample_shape = xs.shape[1..].to_vec();
        let graph = m.local().unwrap().denoiser(layout).unwrap();
        let cond_folder = format!("reference/denoiser_{layout}");
        let mut store = Vec::new();
        let mut inputs = inputs_of(dir, graph, &cond_folder, &mut store);
        let batch = sample_shape[0];
        let mut free_run = xs.data[..per].to_vec();
        for (i, &t) in sampler.timesteps.iter().enumerate() {
            // Teacher-forced: from PyTorch's state, the step must land on PyTorch's next state.
            let x = Tensor::new(sample_shape.clone(), xs.data[i * per..(i + 1) * per].to_vec());
            let ts = Tensor::new(vec![batch], vec![t as f32; batch]);
            inputs.retain(|(n, _)| *n != "x_t" && *n != "timestep");
            let mut call = inputs.clone();
            call.push(("x_t", &x));
            call.push(("timestep", &ts));
            let eps = graph.run(&call).unwrap().remove(0);
            let slice = |t: &Tensor, k: usize| Tensor::new(sample_shape.clone(), t.data[k * per..(k + 1) * per].to_vec());
            assert_close(&eps, &slice(&eps_ref, i), &format!("{method_name} step {i} eps"), tolerance(dir));
            let z = &noise.data[i * per..(i + 1) * per];
            let next = Tensor::new(sample_shape.clone(), sampler.step(i, &x.data, &eps.data, z, &mut None));
            assert_close(&next, &slice(&xs, i + 1), &format!("{method_name} step {i} state"), tolerance(dir));
            // Free-running from the same start noise, Rust alone.
            let fx = Tensor::new(sample_shape.clone(), free_run.clone());
            let mut call = inputs.clone();
            call.push(("x_t", &fx));
            call.push(("timestep", &ts));
            let feps = graph.run(&call).unwrap().remove(0);
            free_run = sampler.step(i, &free_run, &feps.data, z, &mut None);
        }
        let last = xs.shape[0] - 1;
        assert_close(&Tensor::new(sample_shape.clone(), free_run), &Tensor::new(sample_shape.clone(), xs.data[last * per..].to_vec()),
            &format!("{method_name} free run"), tolerance(dir));
    }
}

/// The paper's token geometry (issue: paper scale): the runtime loads a
/// 224x224 model whose 28x28 latents cost 196 / 49 / 16 tokens per frame,
/// packs 22 frames into 844 context tokens against the baseline's 784, and
/// every graph, the packing of its plans and both samplers match PyTorch.
#[test]
fn the_paper_token_geometry_loads_packs_and_runs() {
    let dir = paper_tokens();
    let m = load(&dir);
    let img = &m.manifest().image;
    assert_eq!((img.width, img.height), (224, 224));
    let l = &m.manifest().autoencoder.latent;
    assert_eq!((l.channels, l.height, l.width), (4, 28, 28));
    let tokens = |name: &str| {
        let layout = m.manifest().layout(name).unwrap();
        let per: Vec<(u32, usize, u64)> = layout.slots.iter().map(|s| (s.rate, s.count, s.tokens_per_frame)).collect();
        (per, layout.frames, layout.context_tokens)
    };
    assert_eq!(tokens("worldpack"), (vec![(1, 2, 196), (4, 4, 49), (16, 16, 16)], 22, 844));
    assert_eq!(tokens("baseline"), (vec![(1, 4, 196)], 4, 784));
    graphs_match_pytorch(&dir);
    packing_reproduces_the_reference_inputs(&dir);
    samplers_follow_the_traces(&dir);
}

#[test]
fn the_respacing_matches_numpy() {
    let m = model();
    let s = Sampler::new(&m.manifest().diffusion, 10, Method::Ancestral, 0.0).unwrap();
    assert_eq!(s.timesteps, [999, 888, 777, 666, 555, 444, 333, 222, 111, 0]);
    let s = Sampler::new(&m.manifest().diffusion, 1000, Method::Ddim, 0.0).unwrap();
    assert_eq!(s.len(), 1000);
    let err = Sampler::new(&m.manifest().diffusion, 0, Method::Ddim, 0.0).unwrap_err();
    assert!(err.to_string().starts_with("steps:"), "{err}");
}

fn copy_fixture(name: &str) -> PathBuf {
    copy_files_of(&fixture(), name)
}

/// A temporary folder named after `name` with the files (not the reference
/// folders) of the model folder `from`: enough to load it.
fn copy_files_of(from: &Path, name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("worldpack-model-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let p = entry.unwrap().path();
        if p.is_file() {
            std::fs::copy(&p, dir.join(p.file_name().unwrap())).unwrap();
        }
    }
    dir
}

fn load_err(dir: &Path) -> ModelError {
    match Model::load(dir, RuntimeOptions::default()) {
        Ok(_) => panic!("{} loaded", dir.display()),
        Err(e) => e,
    }
}

#[test]
fn a_wrong_folder_says_what_it_expected() {
    let err = load_err(Path::new("/nonexistent/model")).to_string();
    assert!(err.contains("/nonexistent/model") && err.contains("manifest.json"), "{err}");
    let err = load_err(&std::env::temp_dir()).to_string();
    assert!(err.contains("cannot read manifest.json"), "{err}");
}

#[test]
fn a_manifest_that_disagrees_with_a_graph_names_the_tensor() {
    let dir = copy_fixture("mismatch");
    let mut m = manifest_json();
    m["denoiser"]["layouts"][0]["inputs"][0]["shape"][2] = serde_json::json!(32);
    std::fs::write(dir.join("manifest.json"), m.to_string()).unwrap();
    let err = load_err(&dir);
    let text = err.to_string();
    assert!(matches!(err, ModelError::Mismatch { .. }), "{text}");
    assert!(text.contains("tensor x_t") && text.contains("32") && text.contains("16"), "{text}");

    let mut m = manifest_json();
    m["denoiser"]["layouts"][0]["slots"][1]["tokens_per_frame"] = serde_json::json!(15);
    std::fs::write(dir.join("manifest.json"), m.to_string()).unwrap();
    let text = load_err(&dir).to_string();
    assert!(text.contains("denoiser.layouts[0].slots[1].tokens_per_frame") && text.contains("expected 16"), "{text}");

    std::fs::write(dir.join("manifest.json"), manifest_json().to_string()).unwrap();
    std::fs::remove_file(dir.join("decoder.onnx")).unwrap();
    let text = load_err(&dir).to_string();
    assert!(text.contains("decoder.onnx is listed in manifest.json but missing"), "{text}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn cuda_is_used_when_present_and_refused_loudly_when_absent() {
    match Model::load(&fixture(), RuntimeOptions { provider: Provider::Cuda, threads: 1 }) {
        Ok(m) => assert_eq!(m.provider(), "cuda"),
        Err(e) => {
            assert!(matches!(e, ModelError::ProviderUnavailable { .. }), "{e}");
            assert!(e.to_string().contains("cuda"), "{e}");
            // auto falls back to the CPU and says so.
            let m = Model::load(&fixture(), RuntimeOptions { provider: Provider::Auto, threads: 1 }).unwrap();
            assert_eq!(m.provider(), "cpu");
        }
    }
}

#[test]
fn a_missing_library_says_how_to_get_it() {
    let err = model::runtime::locate_library_in(Some("/nonexistent/libonnxruntime.so".into()), &[]).unwrap_err().to_string();
    assert!(err.contains("ORT_DYLIB_PATH=/nonexistent/libonnxruntime.so") && err.contains("scripts/test.sh"), "{err}");
    let err = model::runtime::locate_library_in(None, &[std::env::temp_dir()]).unwrap_err().to_string();
    assert!(err.contains("ORT_DYLIB_PATH") && err.contains("onnxruntime wheel"), "{err}");
    assert!(model::runtime::locate_library().is_ok(), "the test setup (.venv) provides the library");
}

#[test]
fn bad_plans_name_the_slot() {
    let m = model();
    let layout = m.manifest().layout("baseline").unwrap();
    let latent = &m.manifest().autoencoder.latent;
    let target = Pose::from_position(Default::default());
    let z = vec![0.0; latent.len()];
    let frame = |_id: u64| Some(ContextFrame { latent: &z, time: 3, pose: &target, generated: false });
    let sel = |id| Some(SelectedFrame { id, time: 3, overlap: 0.0, score: 0.0 });
    let plan = ContextPlan { slots: vec![Slot { rate: 4, frame: sel(1) }] };
    let err = pack(layout, latent, None, &plan, 5, &target, frame).unwrap_err().to_string();
    assert!(err.starts_with("plan.slots[0].rate") && err.contains("no rate 4"), "{err}");
    let plan = ContextPlan { slots: vec![Slot { rate: 1, frame: None }] };
    let err = pack(layout, latent, None, &plan, 5, &target, frame).unwrap_err().to_string();
    assert!(err.starts_with("plan:"), "{err}");
    let plan = ContextPlan { slots: vec![Slot { rate: 1, frame: sel(1) }] };
    let err = pack(layout, latent, None, &plan, 3, &target, frame).unwrap_err().to_string();
    assert!(err.contains("not before the target"), "{err}");
    let slots = (0..5).map(|_| Slot { rate: 1, frame: sel(1) }).collect();
    let err = pack(layout, latent, None, &ContextPlan { slots }, 5, &target, frame).unwrap_err().to_string();
    assert!(err.starts_with("plan.slots[4]"), "{err}");
}

/// The fused geometry model's head through ONNX Runtime against PyTorch; a
/// head on a model without the warp input is refused by name, and a model
/// without a head says so when asked to fuse.
#[test]
fn the_fusion_head_matches_pytorch() {
    let dir = fixture_named("variants/worldpack_geometry_fused");
    let m = load(&dir);
    let graph = m.local().unwrap().fusion.as_ref().expect("the fused model has a head");
    let mut store = Vec::new();
    let inputs = inputs_of(&dir, graph, "reference/fusion", &mut store);
    let image = m.run(model::GraphRole::Fusion, &inputs).unwrap().remove(0);
    assert_close(&image, &reference_in(&dir, "reference/fusion", "image"), "fusion.image", tolerance(&dir));

    let err = model().run(model::GraphRole::Fusion, &inputs).unwrap_err().to_string();
    assert!(err.starts_with("fusion:") && err.contains("no fusion head"), "{err}");
    let copy = copy_fixture("fusion-without-warp");
    let mut manifest = manifest_json();
    manifest["fusion"] = manifest_json_in(&dir)["fusion"].clone();
    std::fs::write(copy.join("manifest.json"), manifest.to_string()).unwrap();
    let err = load_err(&copy).to_string();
    assert!(err.contains("fusion") && err.contains("takes no warp"), "{err}");
    let _ = std::fs::remove_dir_all(&copy);
}

/// The served student's head pair (python -m worldpack_train fusion-pair)
/// against PyTorch: its first output, the frame shown, is the head of the
/// model named `pair.shown`, exactly where no warp landed and with the warp's
/// detail where it did (`pair.warp_detail`); its second, the frame the memory
/// keeps, is another. A second output of any other name is refused by name.
#[test]
fn a_head_pair_shows_one_head_and_keeps_the_other() {
    let dir = fixture_named("variants/worldpack_geometry_fused_1step");
    let m = load(&dir);
    let manifest = manifest_json_in(&dir);
    let shown = load(&fixture_named(&format!("variants/{}", manifest["fusion"]["pair"]["shown"]["model"].as_str().expect("fusion.pair.shown.model"))));
    let graph = m.local().unwrap().fusion.as_ref().expect("the student has a head");
    assert_eq!(graph.spec().outputs.iter().map(|o| o.name.as_str()).collect::<Vec<_>>(), ["image", "kept"]);
    let mut store = Vec::new();
    let inputs = inputs_of(&dir, graph, "reference/fusion", &mut store);
    let outputs = m.run(model::GraphRole::Fusion, &inputs).unwrap();
    for (spec, got) in graph.spec().outputs.iter().zip(&outputs) {
        assert_close(got, &reference_in(&dir, "reference/fusion", &spec.name), &format!("fusion.{}", spec.name), tolerance(&dir));
    }
    let apart = |a: &Tensor, b: &Tensor| a.data.iter().zip(&b.data).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
    let alone = shown.run(model::GraphRole::Fusion, &inputs).unwrap().remove(0);
    assert!(apart(&outputs[1], &outputs[0]) > 0.01, "the frame kept is the frame shown");
    assert!(manifest["fusion"]["pair"]["warp_detail"].as_f64() > Some(0.0), "the served pair takes the warp's detail");
    assert!(apart(&outputs[0], &alone) > 0.01, "where the warp landed the frame shown has none of the warp's detail");
    // Where nothing landed, the warp's detail rule has nothing to give: the frame shown is the shown head's.
    let mut nothing_landed = store.clone();
    for (name, tensor) in &mut nothing_landed {
        if name == "landed" {
            tensor.data.iter_mut().for_each(|v| *v = 0.0);
        }
    }
    let inputs: Vec<(&str, &Tensor)> = nothing_landed.iter().map(|(n, t)| (n.as_str(), t)).collect();
    let (shown_frame, alone) = (m.run(model::GraphRole::Fusion, &inputs).unwrap().remove(0), shown.run(model::GraphRole::Fusion, &inputs).unwrap().remove(0));
    assert!(apart(&shown_frame, &alone) < 1e-5, "with nothing landed the frame shown is {} from the shown model's head", apart(&shown_frame, &alone));

    let copy = copy_files_of(&dir, "pair-name");
    let mut wrong = manifest.clone();
    wrong["fusion"]["outputs"][1]["name"] = "memory".into();
    std::fs::write(copy.join("manifest.json"), wrong.to_string()).unwrap();
    let err = load_err(&copy).to_string();
    assert!(err.contains("fusion.outputs") && err.contains("kept") && err.contains("memory"), "{err}");
    let _ = std::fs::remove_dir_all(&copy);
}

/// The distilled students (python -m worldpack_train distill): their graphs
/// (v-prediction turned into epsilon inside) match PyTorch, the sampler runs
/// each one's own grid by DDIM whatever steps and method are asked, and the
/// free-running Rust sample follows PyTorch's trace.
#[test]
fn distilled_students_run_their_own_grid() {
    for (name, grid) in [("variants/worldpack_geometry_fused_1step", vec![999]), ("variants/worldpack_geometry_fused_2step", vec![999, 499])] {
        let dir = fixture_named(name);
        let m = load(&dir);
        let distilled = m.manifest().diffusion.distilled.as_ref().unwrap_or_else(|| panic!("{name} is distilled"));
        assert_eq!(distilled.timesteps, grid, "{name}");
        for (steps, method) in [(10, Method::Ancestral), (grid.len(), Method::Ddim), (50, Method::Ddim)] {
            let s = Sampler::new(&m.manifest().diffusion, steps, method, 0.0).unwrap();
            assert_eq!((s.timesteps.as_slice(), s.method), (grid.as_slice(), Method::Ddim), "{name} asked {steps} {method:?}");
        }
        samplers_follow_the_traces(&dir);
    }
    // A grid that does not descend is refused by name.
    let copy = copy_fixture("distilled-bad-grid");
    let mut manifest = manifest_json();
    manifest["diffusion"]["distilled"] = serde_json::json!({ "timesteps": [499, 999] });
    std::fs::write(copy.join("manifest.json"), manifest.to_string()).unwrap();
    let err = load_err(&copy).to_string();
    assert!(err.contains("diffusion.distilled.timesteps") && err.contains("descending"), "{err}");
    let _ = std::fs::remove_dir_all(&copy);
}
