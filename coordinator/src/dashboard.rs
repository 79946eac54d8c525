//! The web dashboard at `/`: one HTML page with embedded script, no build step.

use crate::server::AppState;
use axum::Router;
use axum::response::Html;
use axum::routing::get;
use std::sync::Arc;

const INDEX: &str = include_str!("dashboard/index.html");

pub fn routes() -> Router<Arc<AppState>> {
    Router::new().route("/", get(|| async { Html(INDEX) }))
}
