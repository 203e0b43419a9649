use std::path::PathBuf;

/// Everything that can go wrong loading or running a model, each saying what to do.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    #[error("ONNX Runtime library not found: {0}")]
    LibraryNotFound(String),
    #[error("cannot load ONNX Runtime from {path}: {message}")]
    LibraryLoad { path: PathBuf, message: String },
    #[error("{}: {message}", path.display())]
    Folder { path: PathBuf, message: String },
    #[error("manifest field {field}: {message}")]
    Manifest { field: String, message: String },
    #[error("{file}: tensor {tensor}: the manifest says {expected}, the graph has {actual}")]
    Mismatch { file: String, tensor: String, expected: String, actual: String },
    #[error("execution provider {provider} is not available: {message}")]
    ProviderUnavailable { provider: String, message: String },
    #[error("{field}: {message}")]
    Input { field: String, message: String },
    #[error("ONNX Runtime: {0}")]
    Ort(String),
    /// A remote backend cannot be reached (a transient fault: retry later).
    #[error("{service} is unavailable: {message}")]
    Unavailable { service: String, message: String },
    /// A remote backend answered with an error of its own.
    #[error("{service}: {message}")]
    Remote { service: String, message: String },
}

impl ModelError {
    pub(crate) fn input(field: impl Into<String>, message: impl Into<String>) -> Self {
        ModelError::Input { field: field.into(), message: message.into() }
    }

    pub(crate) fn manifest(field: impl Into<String>, message: impl Into<String>) -> Self {
        ModelError::Manifest { field: field.into(), message: message.into() }
    }
}

impl<R> From<ort::Error<R>> for ModelError {
    fn from(e: ort::Error<R>) -> Self {
        ModelError::Ort(e.to_string())
    }
}
