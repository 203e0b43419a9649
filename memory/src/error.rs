//! One error type for every bad input the crate can be handed.
//!
//! Each variant names the offending field, so a CLI or HTTP layer can pass
//! the message straight to the user.

use thiserror::Error;

#[derive(Debug, Clone, PartialEq, Error)]
pub enum InputError {
    #[error("`{field}` must be finite, got {value}")]
    NotFinite { field: String, value: f64 },

    #[error("`{field}` must be > 0, got {value}")]
    NotPositive { field: String, value: f64 },

    #[error("`{field}` is not a rotation: {reason}")]
    NotARotation { field: String, reason: String },

    #[error("`near` ({near}) must be smaller than `far` ({far})")]
    NearNotBeforeFar { near: f64, far: f64 },

    #[error("`{field}` must lie strictly between 0 and 180 degrees, got {value}")]
    FovOutOfRange { field: String, value: f64 },

    #[error("`{field}`: {reason}")]
    Invalid { field: String, reason: String },
}

impl InputError {
    /// The name of the field the error is about.
    pub fn field(&self) -> &str {
        match self {
            InputError::NotFinite { field, .. }
            | InputError::NotPositive { field, .. }
            | InputError::NotARotation { field, .. }
            | InputError::FovOutOfRange { field, .. }
            | InputError::Invalid { field, .. } => field,
            InputError::NearNotBeforeFar { .. } => "near",
        }
    }

    pub(crate) fn invalid(field: &str, reason: impl Into<String>) -> Self {
        InputError::Invalid { field: field.to_string(), reason: reason.into() }
    }
}

/// Checks that every value is finite, naming `field` (with an index for arrays).
pub fn check_finite(field: &str, values: &[f64]) -> Result<(), InputError> {
    for (i, &value) in values.iter().enumerate() {
        if !value.is_finite() {
            let field = if values.len() == 1 { field.to_string() } else { format!("{field}[{i}]") };
            return Err(InputError::NotFinite { field, value });
        }
    }
    Ok(())
}

impl InputError {
    /// The same error with its field placed under `prefix` (`target.intrinsics` + `fx`).
    pub fn within(self, prefix: &str) -> InputError {
        let join = |f: String| if prefix.is_empty() { f } else { format!("{prefix}.{f}") };
        match self {
            InputError::NotFinite { field, value } => InputError::NotFinite { field: join(field), value },
            InputError::NotPositive { field, value } => InputError::NotPositive { field: join(field), value },
            InputError::NotARotation { field, reason } => InputError::NotARotation { field: join(field), reason },
            InputError::FovOutOfRange { field, value } => InputError::FovOutOfRange { field: join(field), value },
            InputError::Invalid { field, reason } => InputError::Invalid { field: join(field), reason },
            InputError::NearNotBeforeFar { near, far } => {
                InputError::Invalid { field: join("near".into()), reason: format!("near ({near}) must be smaller than far ({far})") }
            }
        }
    }
}
