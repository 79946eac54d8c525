//! Bearer tokens (client, worker, metrics) and the per-worker secret.

use super::*;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Role {
    Client,
    Worker,
}

pub use crate::farm::token_matches;

/// The bearer token of a request, if any.
pub fn bearer(headers: &HeaderMap) -> Option<&str> {
    headers.get(header::AUTHORIZATION).and_then(|v| v.to_str().ok()).and_then(|v| v.strip_prefix("Bearer "))
}

/// Checks `token` for a route that `allowed` roles may use: missing or unknown 401, the wrong
/// kind 403; with no tokens configured everything is allowed.
pub fn authorize_token(auth: &Auth, token: Option<&str>, allowed: &[Role]) -> ApiResult<()> {
    if auth.client.is_none() && auth.worker.is_none() {
        return Ok(());
    }
    let token = token
        .filter(|t| !t.is_empty())
        .ok_or_else(|| ApiError::new(StatusCode::UNAUTHORIZED, "unauthorized", "missing bearer token"))?;
    let role = if auth.client.as_deref().is_some_and(|t| token_matches(token, t)) {
        Role::Client
    } else if auth.worker.as_deref().is_some_and(|t| token_matches(token, t)) {
        Role::Worker
    } else {
        return Err(ApiError::new(StatusCode::UNAUTHORIZED, "unauthorized", "invalid token"));
    };
    if allowed.contains(&role) {
        Ok(())
    } else {
        Err(ApiError::new(StatusCode::FORBIDDEN, "forbidden", format!("a {role:?} token may not use this route")))
    }
}

/// The `X-Pathfarm-Worker-Secret` header of a request, if any.
pub fn worker_secret(headers: &HeaderMap) -> Option<&str> {
    headers.get(WORKER_SECRET_HEADER).and_then(|v| v.to_str().ok())
}

/// A new worker's secret: 32 bytes from the operating system's CSPRNG, hex-encoded.
pub(crate) fn new_worker_secret() -> ApiResult<String> {
    let mut buf = [0u8; 32];
    getrandom::getrandom(&mut buf).map_err(|e| {
        tracing::error!(error = %e, "the operating system's random number generator failed");
        ApiError::internal("could not make a worker secret")
    })?;
    Ok(hex::encode(buf))
}

pub(crate) fn authorize(state: &AppState, headers: &HeaderMap, allowed: &[Role]) -> ApiResult<()> {
    authorize_token(&state.auth, bearer(headers), allowed)
}

pub(crate) async fn require_client(State(state): State<Arc<AppState>>, req: Request, next: Next) -> Response {
    match authorize(&state, req.headers(), &[Role::Client]) {
        Ok(()) => next.run(req).await,
        Err(e) => e.into_response(),
    }
}

pub(crate) async fn require_worker(State(state): State<Arc<AppState>>, req: Request, next: Next) -> Response {
    match authorize(&state, req.headers(), &[Role::Worker]) {
        Ok(()) => next.run(req).await,
        Err(e) => e.into_response(),
    }
}

pub(crate) async fn require_any(State(state): State<Arc<AppState>>, req: Request, next: Next) -> Response {
    match authorize(&state, req.headers(), &[Role::Client, Role::Worker]) {
        Ok(()) => next.run(req).await,
        Err(e) => e.into_response(),
    }
}
