//! What the step without HTTP (`engine`, `session`, `batch`) fails with: the
//! field at fault, what is wrong, and which kind of failure it is. The routes
//! map each kind to an HTTP status (`error::ApiError`); the engine knows no HTTP.

use crate::store::StoreError;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// The caller sent something wrong.
    Invalid,
    NotFound,
    /// The request cannot be met in this state (no model loaded, an index already taken).
    Conflict,
    /// A dependency (the store, a remote model backend) does not answer; worth retrying.
    Unavailable,
    /// A fault of the server's own.
    Internal,
}

#[derive(Debug)]
pub struct EngineError {
    pub kind: Kind,
    pub field: String,
    pub message: String,
}

impl EngineError {
    pub fn new(kind: Kind, field: impl Into<String>, message: impl Into<String>) -> Self {
        EngineError { kind, field: field.into(), message: message.into() }
    }

    pub fn invalid(field: impl Into<String>, message: impl Into<String>) -> Self {
        Self::new(Kind::Invalid, field, message)
    }

    pub fn internal(message: impl std::fmt::Display) -> Self {
        Self::new(Kind::Internal, "", message.to_string())
    }

    /// The one refusal of a step on a server that runs without a model.
    pub fn no_model() -> Self {
        Self::new(Kind::Conflict, "model", "this server runs without a model (memory only): use observe")
    }
}

impl std::fmt::Display for EngineError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.field.is_empty() { write!(f, "{}", self.message) } else { write!(f, "{}: {}", self.field, self.message) }
    }
}

impl std::error::Error for EngineError {}

impl From<memory::InputError> for EngineError {
    fn from(e: memory::InputError) -> Self {
        EngineError::invalid(e.field(), e.to_string())
    }
}

impl From<model::ModelError> for EngineError {
    fn from(e: model::ModelError) -> Self {
        match e {
            model::ModelError::Input { field, message } => EngineError::invalid(field, message),
            model::ModelError::Unavailable { ref service, .. } => EngineError::new(Kind::Unavailable, service.clone(), e.to_string()),
            other => EngineError::internal(other),
        }
    }
}

impl From<StoreError> for EngineError {
    fn from(e: StoreError) -> Self {
        match e {
            StoreError::Unavailable(_) => EngineError::new(Kind::Unavailable, "store", e.to_string()),
            StoreError::Taken { .. } | StoreError::HasForks { .. } => EngineError::new(Kind::Conflict, "session", e.to_string()),
            StoreError::Missing(_) => EngineError::new(Kind::NotFound, "session", e.to_string()),
            other => EngineError::internal(other),
        }
    }
}
