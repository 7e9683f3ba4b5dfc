//! The API's errors: an HTTP status and a JSON body `{"error": "...", "field": "..."}` naming the
//! request field at fault where there is one.

use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};

/// An error answered to a request.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{}{message}", field.as_ref().map(|f| format!("{f}: ")).unwrap_or_default())]
pub struct ApiError {
    pub status: StatusCode,
    /// The request field at fault (`camera.fov`, `question`, ...).
    pub field: Option<String>,
    pub message: String,
}

impl ApiError {
    /// 400: a field of the request is invalid.
    pub fn field(field: impl Into<String>, message: impl Into<String>) -> Self {
        Self { status: StatusCode::BAD_REQUEST, field: Some(field.into()), message: message.into() }
    }

    /// An error with `status` and no field.
    pub fn status(status: StatusCode, message: impl Into<String>) -> Self {
        Self { status, field: None, message: message.into() }
    }

    /// 500: the model failed (a backend error); the message says what failed.
    pub fn internal(message: impl Into<String>) -> Self {
        Self::status(StatusCode::INTERNAL_SERVER_ERROR, message)
    }

    /// A model error: the request's (400, naming `field` when given: a bad argument, a camera the
    /// op refuses, a prompt over the context) or the server's (500: files, the backend).
    pub fn from_model(e: model::Error, field: Option<&str>) -> Self {
        use model::vlm::VlmError;
        match e {
            model::Error::Input(_) | model::Error::Splat(_) | model::Error::Vlm(VlmError::Prompt(_)) => {
                Self { status: StatusCode::BAD_REQUEST, field: field.map(String::from), message: e.to_string() }
            }
            e => Self::internal(e.to_string()),
        }
    }

    /// The JSON body.
    pub fn body(&self) -> serde_json::Value {
        serde_json::json!({ "error": self.message, "field": self.field })
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        (self.status, axum::Json(self.body())).into_response()
    }
}
