//! What the evaluation programs (`evaluate`, `memory_probe`, `study`) share:
//! their error, which names the setting (as its flag is written) that
//! cannot work, and loading a model with the folder in the message.

use std::path::{Path, PathBuf};

use model::{Model, ModelError, RuntimeOptions};

use crate::features::FeatureError;
use crate::probe::ProbeError;
use crate::suite::SuiteError;

#[derive(Debug, thiserror::Error)]
pub enum ProgramError {
    /// A setting that cannot work, named as its flag is.
    #[error("{field}: {message}")]
    Setting { field: &'static str, message: String },
    #[error("{what}: {source}")]
    Model { what: String, source: ModelError },
    #[error("{what}: {source}")]
    Feature { what: &'static str, source: FeatureError },
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error(transparent)]
    Suite(#[from] SuiteError),
    #[error(transparent)]
    Probe(#[from] ProbeError),
    #[error(transparent)]
    Json(#[from] serde_json::Error),
}

pub fn setting(field: &'static str, message: impl Into<String>) -> ProgramError {
    ProgramError::Setting { field, message: message.into() }
}

/// Maps an I/O error on `path` (for `map_err`).
pub fn io(path: &Path) -> impl FnOnce(std::io::Error) -> ProgramError + '_ {
    move |source| ProgramError::Io { path: path.to_path_buf(), source }
}

/// Writes `text` to `path` through a temporary file, so a reader never sees half of it.
pub fn write_atomically(path: &Path, text: &str) -> Result<(), ProgramError> {
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(io(parent))?;
    }
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, text).map_err(io(&tmp))?;
    std::fs::rename(&tmp, path).map_err(io(path))
}

/// Loads the model in `dir`; the error says what it was for.
pub fn load_model(dir: &Path, runtime: RuntimeOptions, what: impl FnOnce() -> String) -> Result<Model, ProgramError> {
    Model::load(dir, runtime).map_err(|source| ProgramError::Model { what: what(), source })
}
