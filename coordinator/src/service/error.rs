//! What the service floor answers when it cannot do something. It knows nothing of HTTP: the
//! HTTP floor gives each [`Failure`] its status and the error its JSON body.

use crate::farm::FarmError;

/// The kind of a failure (one HTTP status each, in `http::error`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Failure {
    BadRequest,
    Forbidden,
    NotFound,
    Conflict,
    Unprocessable,
    /// Our disk is full: the client may retry later.
    InsufficientStorage,
    /// The database could not save: retry later.
    Unavailable,
    Internal,
}

/// A refusal or failure of the service: its kind, a stable code and a message for people.
#[derive(Debug)]
pub struct ServiceError {
    pub kind: Failure,
    pub code: &'static str,
    pub message: String,
}

impl ServiceError {
    pub fn new(kind: Failure, code: &'static str, message: impl Into<String>) -> Self {
        Self { kind, code, message: message.into() }
    }
    pub fn not_found(message: impl Into<String>) -> Self {
        Self::new(Failure::NotFound, "not_found", message)
    }
    pub fn conflict(code: &'static str, message: impl Into<String>) -> Self {
        Self::new(Failure::Conflict, code, message)
    }
    pub fn unprocessable(code: &'static str, message: impl Into<String>) -> Self {
        Self::new(Failure::Unprocessable, code, message)
    }
    pub fn internal(message: impl Into<String>) -> Self {
        Self::new(Failure::Internal, "internal", message)
    }
}

impl std::fmt::Display for ServiceError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.message)
    }
}

impl From<FarmError> for ServiceError {
    fn from(e: FarmError) -> Self {
        let (kind, code) = match &e {
            FarmError::NoJob(_) => (Failure::NotFound, "not_found"),
            FarmError::NoWorker(_) => (Failure::NotFound, "unknown_worker"),
            FarmError::LeaseLost(_) => (Failure::Conflict, "lease_lost"),
            FarmError::ResultMismatch { .. } => (Failure::Unprocessable, "result_mismatch"),
            FarmError::BadState { .. } => (Failure::Conflict, "bad_state"),
            FarmError::InvalidJob(_) => (Failure::Unprocessable, "invalid_job"),
            FarmError::OverBudget(_) => (Failure::Unprocessable, "over_budget"),
            FarmError::WrongWorker(_) => (Failure::Forbidden, "wrong_worker"),
            FarmError::Stale(_) => (Failure::Conflict, "stale"),
        };
        Self::new(kind, code, e.to_string())
    }
}

pub type ServiceResult<T> = Result<T, ServiceError>;

/// A failed write on the coordinator's own disk: 507 when the disk is full (the client may retry
/// later), 500 otherwise; the message names what was not stored, never a server path.
pub fn storage_error(e: &std::io::Error, what: &str) -> ServiceError {
    tracing::error!(error = %e, "storing {what} failed");
    if e.kind() == std::io::ErrorKind::StorageFull || e.raw_os_error() == Some(28) {
        ServiceError::new(
            Failure::InsufficientStorage,
            "insufficient_storage",
            format!("the coordinator's disk is full: {what} was not stored; retry later"),
        )
    } else {
        ServiceError::new(
            Failure::Internal,
            "storage_error",
            format!("the coordinator could not store {what} ({})", e.kind()),
        )
    }
}

/// A failed database write: 507 when the disk is full, 503 otherwise; the message says what was
/// not saved.
pub fn database_error(e: &anyhow::Error, what: &str) -> ServiceError {
    tracing::error!(error = %format!("{e:#}"), "saving {what} failed");
    let full = e.downcast_ref::<rusqlite::Error>().and_then(rusqlite::Error::sqlite_error_code)
        == Some(rusqlite::ErrorCode::DiskFull)
        || e.downcast_ref::<std::io::Error>().is_some_and(|io| io.raw_os_error() == Some(28));
    if full {
        ServiceError::new(
            Failure::InsufficientStorage,
            "insufficient_storage",
            format!("the coordinator's disk is full: {what} was not saved; retry later"),
        )
    } else {
        ServiceError::new(
            Failure::Unavailable,
            "storage_unavailable",
            format!("the coordinator could not save {what}; retry later"),
        )
    }
}
