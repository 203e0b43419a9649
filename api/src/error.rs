//! Every failure as an HTTP status and a JSON body naming the field:
//! `{"error": {"field": "action.yaw_deg", "message": "..."}}`.

use axum::Json;
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde::Serialize;
use utoipa::ToSchema;

/// Seconds a refused client should wait before trying again (a step takes tens of milliseconds).
pub const RETRY_AFTER_S: &str = "1";

#[derive(Debug)]
pub struct ApiError {
    pub status: StatusCode,
    pub field: String,
    pub message: String,
}

impl ApiError {
    pub fn new(status: StatusCode, field: impl Into<String>, message: impl Into<String>) -> Self {
        ApiError { status, field: field.into(), message: message.into() }
    }

    pub fn bad(field: impl Into<String>, message: impl Into<String>) -> Self {
        Self::new(StatusCode::BAD_REQUEST, field, message)
    }

    pub fn not_found(field: impl Into<String>, message: impl Into<String>) -> Self {
        Self::new(StatusCode::NOT_FOUND, field, message)
    }

    pub fn internal(message: impl std::fmt::Display) -> Self {
        Self::new(StatusCode::INTERNAL_SERVER_ERROR, "", message.to_string())
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let body = ErrorBody { error: ErrorDetail { field: self.field, message: self.message } };
        // Refusals for load (a full session queue, too many model calls) are worth retrying; say when.
        if matches!(self.status, StatusCode::TOO_MANY_REQUESTS | StatusCode::SERVICE_UNAVAILABLE) {
            return (self.status, [(axum::http::header::RETRY_AFTER, RETRY_AFTER_S)], Json(body)).into_response();
        }
        (self.status, Json(body)).into_response()
    }
}

impl From<memory::InputError> for ApiError {
    fn from(e: memory::InputError) -> Self {
        ApiError::bad(e.field(), e.to_string())
    }
}

impl From<model::ModelError> for ApiError {
    fn from(e: model::ModelError) -> Self {
        match e {
            model::ModelError::Input { field, message } => ApiError::bad(field, message),
            model::ModelError::Unavailable { ref service, .. } => ApiError::new(StatusCode::SERVICE_UNAVAILABLE, service.clone(), e.to_string()),
            other => ApiError::internal(other),
        }
    }
}

impl From<crate::store::StoreError> for ApiError {
    fn from(e: crate::store::StoreError) -> Self {
        match e {
            crate::store::StoreError::Unavailable(_) => ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "store", e.to_string()),
            crate::store::StoreError::Taken { .. } => ApiError::new(StatusCode::CONFLICT, "session", e.to_string()),
            other => ApiError::internal(other),
        }
    }
}

/// Every refusal: the field at fault (a JSON path into the request, or
/// `session`, `index`, `content-type`, ...) and what is wrong with it.
#[derive(Serialize, ToSchema)]
pub struct ErrorBody {
    pub error: ErrorDetail,
}

#[derive(Serialize, ToSchema)]
pub struct ErrorDetail {
    #[schema(example = "action.yaw_deg")]
    pub field: String,
    pub message: String,
}
