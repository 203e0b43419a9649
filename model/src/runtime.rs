//! Finding and loading ONNX Runtime (`load-dynamic`: nothing is downloaded at
//! build time), and building sessions on the CPU or CUDA execution provider.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use ort::environment::Environment;
use ort::session::Session;

use crate::error::ModelError;

/// Which execution provider runs the graphs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Provider {
    Cpu,
    /// Fails loudly when the CUDA provider cannot be registered.
    Cuda,
    /// CUDA when it works, else CPU; the model reports which one runs.
    Auto,
}

impl std::str::FromStr for Provider {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "cpu" => Ok(Provider::Cpu),
            "cuda" => Ok(Provider::Cuda),
            "auto" => Ok(Provider::Auto),
            _ => Err(format!("unknown provider {s:?}; one of cpu, cuda, auto")),
        }
    }
}

/// How sessions are built.
#[derive(Clone, Copy, Debug)]
pub struct RuntimeOptions {
    pub provider: Provider,
    /// Intra-op threads per session; 0 lets ONNX Runtime decide.
    pub threads: usize,
}

impl Default for RuntimeOptions {
    fn default() -> Self {
        RuntimeOptions { provider: Provider::Cpu, threads: 0 }
    }
}

const HOW_TO_GET_IT: &str = "set ORT_DYLIB_PATH to libonnxruntime.so (for example .venv/lib/python3.11/site-packages/onnxruntime/capi/libonnxruntime.so.1.31.1), or run ./scripts/test.sh once, which installs the onnxruntime wheel into .venv";

/// `ORT_DYLIB_PATH` when set, else the `onnxruntime` wheel in a `.venv` at
/// or above the working directory or this repository's root.
pub fn locate_library() -> Result<PathBuf, ModelError> {
    let mut roots: Vec<PathBuf> = std::env::current_dir().map(|d| d.ancestors().map(Path::to_path_buf).collect()).unwrap_or_default();
    roots.push(Path::new(env!("CARGO_MANIFEST_DIR")).join(".."));
    locate_library_in(std::env::var_os("ORT_DYLIB_PATH").map(PathBuf::from), &roots)
}

/// [`locate_library`] with its inputs explicit (for tests).
pub fn locate_library_in(explicit: Option<PathBuf>, roots: &[PathBuf]) -> Result<PathBuf, ModelError> {
    if let Some(path) = explicit {
        return if path.is_file() {
            Ok(path)
        } else {
            Err(ModelError::LibraryNotFound(format!("ORT_DYLIB_PATH={} is not a file; {HOW_TO_GET_IT}", path.display())))
        };
    }
    for root in roots {
        let Ok(libs) = std::fs::read_dir(root.join(".venv/lib")) else { continue };
        for python in libs.flatten() {
            let capi = python.path().join("site-packages/onnxruntime/capi");
            let Ok(files) = std::fs::read_dir(&capi) else { continue };
            let mut found: Vec<PathBuf> = files
                .flatten()
                .map(|f| f.path())
                .filter(|p| p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with("libonnxruntime.so")))
                .collect();
            found.sort();
            if let Some(lib) = found.pop() {
                return Ok(lib);
            }
        }
    }
    Err(ModelError::LibraryNotFound(HOW_TO_GET_IT.to_string()))
}

static ENVIRONMENT: OnceLock<Result<Environment, ModelError>> = OnceLock::new();

/// The process-wide ONNX Runtime environment, loading the library on first use.
pub fn environment() -> Result<&'static Environment, ModelError> {
    let env = ENVIRONMENT.get_or_init(|| {
        let path = locate_library()?;
        let builder = ort::init_from(&path).map_err(|e| ModelError::LibraryLoad { path: path.clone(), message: e.to_string() })?;
        builder.with_name("worldpack").build().map_err(|e| ModelError::LibraryLoad { path, message: e.to_string() })
    });
    match env {
        Ok(env) => Ok(env),
        // The first failure is kept; later callers get the same error.
        Err(ModelError::LibraryLoad { path, message }) => Err(ModelError::LibraryLoad { path: path.clone(), message: message.clone() }),
        Err(e) => Err(ModelError::LibraryNotFound(e.to_string().trim_start_matches("ONNX Runtime library not found: ").to_string())),
    }
}

/// Builds a session for one graph; returns it with the provider that runs it.
pub fn build_session(file: &Path, options: RuntimeOptions) -> Result<(Session, &'static str), ModelError> {
    let env = environment()?;
    let make = |cuda: bool| -> Result<Session, ModelError> {
        let mut builder = Session::builder(env)?;
        if options.threads > 0 {
            builder = builder.with_intra_threads(options.threads)?;
        }
        if cuda {
            builder = builder
                .with_execution_providers([ort::ep::CUDA::default().build().error_on_failure()])
                .map_err(|e| ModelError::ProviderUnavailable { provider: "cuda".into(), message: e.to_string() })?;
        }
        Ok(builder.commit_from_file(file)?)
    };
    match options.provider {
        Provider::Cpu => Ok((make(false)?, "cpu")),
        Provider::Cuda => Ok((make(true)?, "cuda")),
        Provider::Auto => match make(true) {
            Ok(session) => Ok((session, "cuda")),
            Err(ModelError::ProviderUnavailable { .. }) => Ok((make(false)?, "cpu")),
            Err(e) => Err(e),
        },
    }
}
