//! A model's graphs served by Triton Inference Server (or any server of the
//! KServe v2 open inference protocol), as a [`model::Backend`]: the sampler,
//! packing and warps stay in this process, only the graph calls travel.
//!
//! Each graph is one Triton model named `<manifest name>-<graph>`: `encoder`,
//! `decoder` and `denoiser-<layout>` (see [`model_name`]). Tensors travel in
//! the binary tensor extension (a JSON header, then raw little-endian float32),
//! not as JSON numbers: a 16-frame context is 64 KB of floats per call.
//! `serving/triton/host.py` hosts a model folder this way;
//! `serving/triton/repository.py` writes the same names as a model
//! repository for Triton's own onnxruntime backend.

use std::time::Duration;

use model::manifest::GraphSpec;
use model::{Backend, GraphRole, Manifest, ModelError, Tensor};
use serde_json::{Value, json};

/// The dependency's name in errors (and so in a 503's `field`).
const SERVICE: &str = "triton";
/// The binary tensor extension's header: the JSON part's length in bytes.
const HEADER_LENGTH: &str = "Inference-Header-Content-Length";

/// The shape a tensor travels with. Triton needs at least one axis besides
/// the batch axis, so a tensor that is only the batch axis (the timestep, one
/// per item) travels as (batch, 1); the model repository reshapes it back.
fn wire_shape(shape: &[usize]) -> Vec<usize> {
    if shape.len() == 1 { vec![shape[0], 1] } else { shape.to_vec() }
}

/// The Triton model that serves `role` of the model named `name`.
pub fn model_name(name: &str, role: GraphRole) -> String {
    match role {
        GraphRole::Encoder => format!("{name}-encoder"),
        GraphRole::Decoder => format!("{name}-decoder"),
        GraphRole::Denoiser(layout) => format!("{name}-denoiser-{layout}"),
        GraphRole::Fusion => format!("{name}-fusion"),
    }
}

/// One graph on the server: the Triton model's infer URL and the manifest's spec.
struct RemoteGraph {
    infer_url: String,
    spec: GraphSpec,
}

pub struct KServeBackend {
    base: String,
    agent: ureq::Agent,
    encoder: RemoteGraph,
    decoder: RemoteGraph,
    denoisers: Vec<(String, RemoteGraph)>,
    fusion: Option<RemoteGraph>,
}

impl KServeBackend {
    /// Connects to `url` (`triton://HOST:PORT` or `http://HOST:PORT`, the
    /// server's HTTP port) and checks that every graph the manifest lists is
    /// served, ready, with the manifest's inputs and outputs.
    pub fn connect(url: &str, manifest: &Manifest) -> Result<KServeBackend, ModelError> {
        let base = base_url(url)?;
        let agent = ureq::AgentBuilder::new().timeout_connect(Duration::from_secs(5)).timeout(Duration::from_secs(120)).build();
        let graph = |role: GraphRole, spec: GraphSpec| -> Result<RemoteGraph, ModelError> {
            let name = model_name(&manifest.name, role);
            let metadata = get_json(&agent, &base, &format!("/v2/models/{name}"))?;
            check_metadata(&name, &spec, &metadata)?;
            let ready = agent.get(&format!("{base}/v2/models/{name}/ready")).call();
            if ready.is_err() {
                return Err(unavailable(&base, format!("model {name} is loaded but not ready")));
            }
            Ok(RemoteGraph { infer_url: format!("{base}/v2/models/{name}/infer"), spec })
        };
        let encoder = graph(GraphRole::Encoder, manifest.autoencoder.encoder.clone())?;
        let decoder = graph(GraphRole::Decoder, manifest.autoencoder.decoder.clone())?;
        let denoisers = manifest
            .denoiser
            .layouts
            .iter()
            .map(|l| Ok((l.name.clone(), graph(GraphRole::Denoiser(&l.name), l.graph())?)))
            .collect::<Result<Vec<_>, ModelError>>()?;
        let fusion = manifest.fusion.clone().map(|spec| graph(GraphRole::Fusion, spec)).transpose()?;
        Ok(KServeBackend { base, agent, encoder, decoder, denoisers, fusion })
    }

    /// The server's HTTP address (`http://HOST:PORT`).
    pub fn url(&self) -> &str {
        &self.base
    }

    fn graph(&self, role: GraphRole) -> Result<&RemoteGraph, ModelError> {
        match role {
            GraphRole::Encoder => Ok(&self.encoder),
            GraphRole::Decoder => Ok(&self.decoder),
            GraphRole::Fusion => self.fusion.as_ref().ok_or_else(model::backend::no_fusion),
            GraphRole::Denoiser(layout) => self.denoisers.iter().find(|(n, _)| n == layout).map(|(_, g)| g).ok_or_else(|| {
                let known: Vec<&str> = self.denoisers.iter().map(|(n, _)| n.as_str()).collect();
                ModelError::Input { field: "layout".into(), message: format!("this model has no {layout:?} layout; it has {known:?}") }
            }),
        }
    }
}

impl Backend for KServeBackend {
    fn ready(&self) -> Result<(), ModelError> {
        self.agent.get(&format!("{}/v2/health/ready", self.base)).call().map(|_| ()).map_err(|e| call_error(&self.base, e))
    }

    fn run(&self, role: GraphRole, inputs: &[(&str, &Tensor)]) -> Result<Vec<Tensor>, ModelError> {
        let graph = self.graph(role)?;
        let ordered = graph.spec.ordered_inputs(inputs)?;
        let (header, body) = encode_request(&graph.spec, &ordered);
        let response = self
            .agent
            .post(&graph.infer_url)
            .set("Content-Type", "application/octet-stream")
            .set(HEADER_LENGTH, &header.to_string())
            .send_bytes(&body)
            .map_err(|e| call_error(&self.base, e))?;
        let header_len = response.header(HEADER_LENGTH).map(str::parse::<usize>);
        let mut bytes = Vec::new();
        std::io::Read::read_to_end(&mut response.into_reader(), &mut bytes).map_err(|e| unavailable(&self.base, format!("reading the answer: {e}")))?;
        let header_len = match header_len {
            Some(Ok(n)) if n <= bytes.len() => n,
            None => bytes.len(),
            _ => return Err(remote(format!("{}: a bad {HEADER_LENGTH} header", graph.infer_url))),
        };
        decode_response(&graph.spec, &bytes[..header_len], &bytes[header_len..])
    }

    fn provider(&self) -> &str {
        SERVICE
    }
}

/// `triton://HOST:PORT` or `http://HOST:PORT` to `http://HOST:PORT`.
fn base_url(url: &str) -> Result<String, ModelError> {
    let rest = url.strip_prefix("triton://").or_else(|| url.strip_prefix("http://"));
    match rest.map(|r| r.trim_end_matches('/')) {
        Some(host) if !host.is_empty() && !host.contains('/') => Ok(format!("http://{host}")),
        _ => Err(ModelError::Input {
            field: "model_backend".into(),
            message: format!("{url:?}: expected triton://HOST:PORT (Triton's HTTP port)"),
        }),
    }
}

/// The JSON header (its length in bytes) and the whole body: header, then
/// each input's float32 data, little-endian, in the header's order.
fn encode_request(spec: &GraphSpec, inputs: &[&Tensor]) -> (usize, Vec<u8>) {
    let header = json!({
        "inputs": spec.inputs.iter().zip(inputs).map(|(s, t)| json!({
            "name": s.name, "shape": wire_shape(&t.shape), "datatype": "FP32",
            "parameters": {"binary_data_size": t.data.len() * 4},
        })).collect::<Vec<_>>(),
        "outputs": spec.outputs.iter().map(|o| json!({"name": o.name, "parameters": {"binary_data": true}})).collect::<Vec<_>>(),
    });
    let mut body = serde_json::to_vec(&header).expect("a JSON value serialises");
    let header_len = body.len();
    body.reserve(inputs.iter().map(|t| t.data.len() * 4).sum());
    for t in inputs {
        body.extend(t.data.iter().flat_map(|v| v.to_le_bytes()));
    }
    (header_len, body)
}

/// The outputs in the spec's order from an answer's JSON header and binary part.
fn decode_response(spec: &GraphSpec, header: &[u8], mut binary: &[u8]) -> Result<Vec<Tensor>, ModelError> {
    let header: Value = serde_json::from_slice(header).map_err(|e| remote(format!("an answer that is not KServe v2 JSON: {e}")))?;
    let outputs = header["outputs"].as_array().ok_or_else(|| remote(format!("an answer without outputs: {header}")))?;
    // Binary outputs follow in the header's order; each says its byte size.
    let mut found: Vec<(String, Tensor)> = Vec::with_capacity(outputs.len());
    for o in outputs {
        let name = o["name"].as_str().unwrap_or_default().to_string();
        let shape = o["shape"].as_array().map(|s| s.iter().filter_map(Value::as_u64).map(|d| d as usize).collect::<Vec<_>>()).unwrap_or_default();
        if o["datatype"] != "FP32" {
            return Err(remote(format!("output {name}: datatype {}, expected FP32", o["datatype"])));
        }
        let data: Vec<f32> = match o["parameters"]["binary_data_size"].as_u64() {
            Some(size) => {
                let size = size as usize;
                if size > binary.len() || !size.is_multiple_of(4) {
                    return Err(remote(format!("output {name}: {size} bytes announced, {} left", binary.len())));
                }
                let (mine, rest) = binary.split_at(size);
                binary = rest;
                mine.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()
            }
            None => o["data"].as_array().map(|d| d.iter().filter_map(Value::as_f64).map(|v| v as f32).collect()).unwrap_or_default(),
        };
        if data.len() != shape.iter().product::<usize>() {
            return Err(remote(format!("output {name}: shape {shape:?} but {} values", data.len())));
        }
        found.push((name, Tensor::new(shape, data)));
    }
    spec.outputs
        .iter()
        .map(|o| {
            let at = found.iter().position(|(n, _)| *n == o.name).ok_or_else(|| remote(format!("the answer lacks output {}", o.name)))?;
            let mut t = found.swap_remove(at).1;
            if o.shape.len() == 1 && t.shape.len() == 2 && t.shape[1] == 1 {
                t.shape.pop(); // back from its wire shape
            }
            Ok(t)
        })
        .collect()
}

/// Refuses a served model whose tensors differ from the manifest's (names,
/// FP32, rank; Triton reports a batched model's batch axis as -1).
fn check_metadata(name: &str, spec: &GraphSpec, metadata: &Value) -> Result<(), ModelError> {
    for (kind, declared, served) in [("input", &spec.inputs, &metadata["inputs"]), ("output", &spec.outputs, &metadata["outputs"])] {
        let served = served.as_array().cloned().unwrap_or_default();
        for d in declared {
            let mismatch = |actual: String| ModelError::Mismatch {
                file: format!("triton model {name}"),
                tensor: d.name.clone(),
                expected: format!("FP32 {:?}", d.shape),
                actual,
            };
            let Some(s) = served.iter().find(|s| s["name"] == d.name.as_str()) else {
                let names: Vec<&str> = served.iter().filter_map(|s| s["name"].as_str()).collect();
                return Err(mismatch(format!("no {kind} of that name; it has {names:?}")));
            };
            let dims: Vec<i64> = s["shape"].as_array().map(|a| a.iter().filter_map(Value::as_i64).collect()).unwrap_or_default();
            let want: Vec<i64> = if d.shape.len() == 1 { vec![-1, 1] } else { d.dims() };
            let fits = dims.len() == want.len() && dims.iter().zip(want).all(|(&got, want)| want < 0 || got == want);
            if s["datatype"] != "FP32" || !fits {
                return Err(mismatch(format!("{} {dims:?}", s["datatype"])));
            }
        }
    }
    Ok(())
}

fn get_json(agent: &ureq::Agent, base: &str, path: &str) -> Result<Value, ModelError> {
    let response = agent.get(&format!("{base}{path}")).call().map_err(|e| call_error(base, e))?;
    response.into_json().map_err(|e| remote(format!("{base}{path}: {e}")))
}

/// Transport failures and 503 are the server being away (retry later); any
/// other status is the server's own error, passed on with its message.
fn call_error(base: &str, e: ureq::Error) -> ModelError {
    match e {
        ureq::Error::Status(503, _) => unavailable(base, "the server answered 503".into()),
        ureq::Error::Status(404, r) => {
            let url = r.get_url().to_string();
            remote(format!("{url}: not found ({}); is the model loaded? (serving/triton/host.py --model DIR)", error_text(r)))
        }
        ureq::Error::Status(code, r) => {
            let url = r.get_url().to_string();
            remote(format!("{url}: HTTP {code}: {}", error_text(r)))
        }
        ureq::Error::Transport(t) => unavailable(base, t.to_string()),
    }
}

/// The `error` of a KServe v2 error answer, or its whole body.
fn error_text(r: ureq::Response) -> String {
    let body = r.into_string().unwrap_or_default();
    serde_json::from_str::<Value>(&body).ok().and_then(|v| v["error"].as_str().map(String::from)).unwrap_or(body)
}

fn unavailable(base: &str, message: String) -> ModelError {
    ModelError::Unavailable { service: SERVICE.into(), message: format!("{base}: {message}") }
}

fn remote(message: String) -> ModelError {
    ModelError::Remote { service: SERVICE.into(), message }
}

#[cfg(test)]
mod tests {
    use super::*;
    use model::manifest::{Dim, TensorSpec};

    fn spec() -> GraphSpec {
        let t = |name: &str| TensorSpec { name: name.into(), shape: vec![Dim::Named("batch".into()), Dim::Fixed(2)], dtype: "float32".into() };
        GraphSpec { file: "g.onnx".into(), inputs: vec![t("a"), t("b")], outputs: vec![t("y"), t("z")] }
    }

    #[test]
    fn urls_name_the_http_port_or_are_refused() {
        assert_eq!(base_url("triton://127.0.0.1:8000").unwrap(), "http://127.0.0.1:8000");
        assert_eq!(base_url("http://host:9/").unwrap(), "http://host:9");
        for bad in ["127.0.0.1:8000", "triton://", "grpc://h:1", "triton://h:1/v2"] {
            assert!(matches!(base_url(bad), Err(ModelError::Input { ref field, .. }) if field == "model_backend"), "{bad}");
        }
    }

    #[test]
    fn a_request_carries_each_input_once_in_the_spec_order() {
        let (a, b) = (Tensor::new(vec![1, 2], vec![1.0, 2.0]), Tensor::new(vec![1, 2], vec![3.0, -0.5]));
        let (n, body) = encode_request(&spec(), &[&a, &b]);
        let header: Value = serde_json::from_slice(&body[..n]).unwrap();
        assert_eq!(header["inputs"][1]["name"], "b");
        assert_eq!(header["inputs"][0]["parameters"]["binary_data_size"], 8);
        let floats: Vec<f32> = body[n..].chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect();
        assert_eq!(floats, [1.0, 2.0, 3.0, -0.5]);
    }

    #[test]
    fn answers_are_read_by_name_and_byte_size_and_checked() {
        // Outputs in the opposite order to the spec, the second as JSON numbers.
        let header = json!({"outputs": [
            {"name": "z", "datatype": "FP32", "shape": [1, 2], "parameters": {"binary_data_size": 8}},
            {"name": "y", "datatype": "FP32", "shape": [1, 2], "data": [5.0, 6.0]},
        ]});
        let bin: Vec<u8> = [7.0f32, 8.0].iter().flat_map(|v| v.to_le_bytes()).collect();
        let out = decode_response(&spec(), header.to_string().as_bytes(), &bin).unwrap();
        assert_eq!((out[0].data.clone(), out[1].data.clone()), (vec![5.0, 6.0], vec![7.0, 8.0]));
        // Fewer bytes than announced is an error, not a short tensor.
        assert!(decode_response(&spec(), header.to_string().as_bytes(), &bin[..6]).is_err());
    }

    #[test]
    fn a_served_model_must_match_the_manifest() {
        let io = |names: [&str; 2], dims: Value| names.iter().map(|n| json!({"name": n, "datatype": "FP32", "shape": dims})).collect::<Vec<_>>();
        let good = json!({"inputs": io(["a", "b"], json!([-1, 2])), "outputs": io(["y", "z"], json!([-1, 2]))});
        assert!(check_metadata("m", &spec(), &good).is_ok());
        let renamed = json!({"inputs": io(["a", "c"], json!([-1, 2])), "outputs": io(["y", "z"], json!([-1, 2]))});
        assert!(matches!(check_metadata("m", &spec(), &renamed), Err(ModelError::Mismatch { ref tensor, .. }) if tensor == "b"));
        let resized = json!({"inputs": io(["a", "b"], json!([-1, 3])), "outputs": io(["y", "z"], json!([-1, 2]))});
        assert!(check_metadata("m", &spec(), &resized).is_err());
    }
}
