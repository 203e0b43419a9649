//! One ONNX graph: its sessions (a pool, so concurrent callers do not queue
//! on one `Session::run(&mut self)`) and the check of its inputs and outputs
//! against the manifest.

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use ort::session::Session;
use ort::value::{TensorRef, ValueType};

use crate::error::ModelError;
use crate::manifest::{Dim, GraphSpec, TensorSpec};
use crate::tensor::Tensor;
use crate::runtime::{RuntimeOptions, build_session};

pub struct Graph {
    path: PathBuf,
    spec: GraphSpec,
    options: RuntimeOptions,
    provider: &'static str,
    idle: Mutex<Vec<Session>>,
}

impl Graph {
    /// Opens `dir/spec.file` and checks it against the manifest's spec.
    pub fn open(dir: &Path, spec: &GraphSpec, options: RuntimeOptions) -> Result<Graph, ModelError> {
        let path = dir.join(&spec.file);
        if !path.is_file() {
            return Err(ModelError::Folder { path: dir.to_path_buf(), message: format!("{} is listed in manifest.json but missing", spec.file) });
        }
        let (session, provider) = build_session(&path, options)?;
        check_io(&spec.file, spec, &session)?;
        Ok(Graph { path, spec: spec.clone(), options, provider, idle: Mutex::new(vec![session]) })
    }

    /// Opens a graph no manifest describes (a user's feature network): its
    /// inputs and outputs are read from the file, and must be float32.
    pub fn open_self_described(path: &Path, options: RuntimeOptions) -> Result<Graph, ModelError> {
        if !path.is_file() {
            return Err(ModelError::input(path.display().to_string(), "no such ONNX file"));
        }
        let (session, provider) = build_session(path, options)?;
        let describe = |outlets: &[ort::value::Outlet]| -> Result<Vec<TensorSpec>, ModelError> {
            outlets
                .iter()
                .map(|o| match o.dtype() {
                    ValueType::Tensor { ty, shape, .. } if format!("{ty:?}").eq_ignore_ascii_case("float32") => Ok(TensorSpec {
                        name: o.name().to_string(),
                        shape: shape.iter().map(|&d| if d < 0 { Dim::Named("dynamic".into()) } else { Dim::Fixed(d) }).collect(),
                        dtype: "float32".into(),
                    }),
                    other => Err(ModelError::input(path.display().to_string(), format!("{}: {other:?}; feature networks take and give float32 tensors", o.name()))),
                })
                .collect()
        };
        let file = path.file_name().map(|f| f.to_string_lossy().into_owned()).unwrap_or_default();
        let spec = GraphSpec { file, inputs: describe(session.inputs())?, outputs: describe(session.outputs())? };
        let dir = path.parent().unwrap_or(Path::new("."));
        Ok(Graph { path: dir.join(&spec.file), spec, options, provider, idle: Mutex::new(vec![session]) })
    }

    /// The execution provider running this graph (`cpu` or `cuda`).
    pub fn provider(&self) -> &'static str {
        self.provider
    }

    /// Sessions opened so far (idle ones; busy ones are out on loan).
    pub fn sessions(&self) -> usize {
        self.idle.lock().unwrap_or_else(|p| p.into_inner()).len()
    }

    pub fn spec(&self) -> &GraphSpec {
        &self.spec
    }

    /// Runs the graph on named inputs (every input of the spec, any order);
    /// returns the outputs in the spec's order.
    pub fn run(&self, inputs: &[(&str, &Tensor)]) -> Result<Vec<Tensor>, ModelError> {
        let mut feed = Vec::with_capacity(inputs.len());
        for (spec, t) in self.spec.inputs.iter().zip(self.spec.ordered_inputs(inputs)?) {
            let value = TensorRef::from_array_view((t.shape.clone(), &t.data[..]))?;
            feed.push((spec.name.clone(), value));
        }
        let mut session = self.checkout()?;
        let result = (|| {
            let outputs = session.run(feed)?;
            self.spec
                .outputs
                .iter()
                .map(|o| {
                    let (shape, data) = outputs[o.name.as_str()].try_extract_tensor::<f32>()?;
                    Ok(Tensor::new(shape.iter().map(|&d| d as usize).collect(), data.to_vec()))
                })
                .collect::<Result<Vec<_>, ModelError>>()
        })();
        self.idle.lock().unwrap_or_else(|p| p.into_inner()).push(session);
        result
    }

    /// An idle session, or a new one when every session is busy.
    fn checkout(&self) -> Result<Session, ModelError> {
        if let Some(s) = self.idle.lock().unwrap_or_else(|p| p.into_inner()).pop() {
            return Ok(s);
        }
        Ok(build_session(&self.path, self.options)?.0)
    }
}

fn check_io(file: &str, spec: &GraphSpec, session: &Session) -> Result<(), ModelError> {
    for (kind, declared, actual) in [("input", &spec.inputs, session.inputs()), ("output", &spec.outputs, session.outputs())] {
        let names: Vec<&str> = actual.iter().map(|o| o.name()).collect();
        for d in declared.iter() {
            let Some(a) = actual.iter().find(|a| a.name() == d.name) else {
                return Err(ModelError::Mismatch {
                    file: file.into(),
                    tensor: d.name.clone(),
                    expected: format!("an {kind} called {:?}", d.name),
                    actual: format!("{kind}s {names:?}"),
                });
            };
            let (ty, shape) = match a.dtype() {
                ValueType::Tensor { ty, shape, .. } => (format!("{ty:?}"), shape.iter().copied().collect::<Vec<i64>>()),
                other => (format!("{other:?}"), vec![]),
            };
            if shape != d.dims() || !ty.eq_ignore_ascii_case("float32") {
                return Err(ModelError::Mismatch {
                    file: file.into(),
                    tensor: d.name.clone(),
                    expected: format!("float32 {:?}", d.shape),
                    actual: format!("{ty} {shape:?} (-1 = dynamic)"),
                });
            }
        }
        if declared.len() != actual.len() {
            return Err(ModelError::Mismatch {
                file: file.into(),
                tensor: format!("({kind}s)"),
                expected: format!("{} {kind}s", declared.len()),
                actual: format!("{} {kind}s {names:?}", actual.len()),
            });
        }
    }
    Ok(())
}
