//! The web dashboard at `/`: one HTML page, a stylesheet and a script embedded in the binary
//! (no build step, nothing from other hosts); it reads the REST API and follows
//! `GET /api/v1/events` for live updates.
//!
//! It also serves `GET /api/v1/jobs/{id}/convergence`: the estimated noise of a job's image after
//! each completed pass, measured from the film's variance layer by a small tracker task that
//! follows the job events (and on demand, for passes it missed).

use crate::api::ApiError;
use crate::events::authorize_client;
use crate::server::AppState;
use axum::Router;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{Html, IntoResponse, Json, Response};
use axum::routing::get;
use pathfarm_common::protocol::JobId;
use serde::Serialize;
use std::collections::HashMap;
use std::sync::{Arc, Mutex, Weak};

const INDEX: &str = include_str!("dashboard/index.html");
const SCRIPT: &str = include_str!("dashboard/app.js");
const STYLE: &str = include_str!("dashboard/style.css");
const ICON: &str = include_str!("dashboard/icon.svg");

/// Estimated noise of a job's image after a pass.
#[derive(Clone, Debug, PartialEq, Serialize, utoipa::ToSchema)]
pub struct ConvergencePoint {
    /// Passes merged for every tile when this was measured.
    pub passes_done: u32,
    /// Samples per pixel merged for the whole image.
    pub spp_done: u32,
    /// Mean samples per pixel actually in the film (tiles of later passes may be merged too).
    pub mean_spp: f64,
    /// Root mean square over pixels of the standard error of the pixel mean (luminance).
    pub rmse: f64,
    /// Mean pixel luminance.
    pub mean_luminance: f64,
    /// `rmse / mean_luminance` (0 for a black image).
    pub relative: f64,
}

/// `GET /jobs/{id}/convergence` answer.
#[derive(Clone, Debug, Serialize, utoipa::ToSchema)]
pub struct Convergence {
    pub id: JobId,
    /// Passes of the job's plan.
    pub passes_total: u32,
    /// One point per pass seen completing, in pass order.
    pub points: Vec<ConvergencePoint>,
}

/// Per job, the noise measured after each completed pass.
#[derive(Default)]
pub struct History {
    jobs: Mutex<HashMap<JobId, Vec<ConvergencePoint>>>,
}

fn measure(job: &crate::farm::Job) -> ConvergencePoint {
    let img = job.film.resolve();
    let (mut var, mut lum, mut spp, mut n) = (0.0f64, 0.0f64, 0.0f64, 0u64);
    for i in 0..img.samples.len() {
        spp += f64::from(img.samples[i]);
        if img.samples[i] > 0.0 {
            let [r, g, b] = img.rgb[i];
            var += f64::from(img.variance[i].max(0.0));
            lum += 0.2126 * f64::from(r) + 0.7152 * f64::from(g) + 0.0722 * f64::from(b);
            n += 1;
        }
    }
    let pixels = img.samples.len().max(1) as f64;
    let (rmse, mean) = if n > 0 { ((var / n as f64).sqrt(), lum / n as f64) } else { (0.0, 0.0) };
    ConvergencePoint {
        passes_done: job.passes_done,
        spp_done: job.plan.passes.get(job.passes_done as usize).map_or(job.settings.spp, |p| p.s0),
        mean_spp: spp / pixels,
        rmse,
        mean_luminance: mean,
        relative: if mean > 0.0 { rmse / mean } else { 0.0 },
    }
}

impl History {
    /// Measures job `id` if a pass completed since its last point; forgets deleted jobs.
    pub fn record(&self, state: &AppState, id: JobId) {
        let last = self.last_pass(id);
        let point = {
            let farm = state.farm.lock();
            match farm.job(id) {
                Ok(job) if job.passes_done > 0 && last.is_none_or(|l| job.passes_done > l) => Some(measure(job)),
                Ok(_) => None,
                Err(_) => {
                    drop(farm);
                    self.lock().remove(&id);
                    None
                }
            }
        };
        if let Some(p) = point {
            let mut jobs = self.lock();
            let points = jobs.entry(id).or_default();
            if points.last().is_none_or(|l| p.passes_done > l.passes_done) {
                points.push(p);
            }
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<JobId, Vec<ConvergencePoint>>> {
        self.jobs.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn last_pass(&self, id: JobId) -> Option<u32> {
        self.lock().get(&id).and_then(|v| v.last()).map(|p| p.passes_done)
    }

    pub fn points(&self, id: JobId) -> Vec<ConvergencePoint> {
        self.lock().get(&id).cloned().unwrap_or_default()
    }
}

/// Follows job events and records a point whenever a job completes a pass.
async fn track(state: Weak<AppState>, history: Arc<History>) {
    let Some(mut rx) = state.upgrade().map(|s| s.events.subscribe()) else { return };
    loop {
        match rx.recv().await {
            Ok(ev) if ev.kind == "job" => {
                let Some(s) = state.upgrade() else { return };
                history.record(&s, ev.id);
            }
            Ok(_) => {}
            Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => {
                let Some(s) = state.upgrade() else { return };
                let ids: Vec<JobId> = s.farm.lock().jobs().map(|j| j.id).collect();
                for id in ids {
                    history.record(&s, id);
                }
            }
            Err(tokio::sync::broadcast::error::RecvError::Closed) => return,
        }
    }
}

#[derive(Debug, serde::Deserialize)]
struct TokenQuery {
    token: Option<String>,
}

async fn convergence(
    State(state): State<Arc<AppState>>,
    history: Arc<History>,
    headers: HeaderMap,
    token: Option<String>,
    id: String,
) -> Result<Json<Convergence>, ApiError> {
    authorize_client(&state.auth, &headers, token.as_deref())?;
    let id: JobId = id
        .parse()
        .map_err(|_| ApiError::new(StatusCode::BAD_REQUEST, "bad_id", format!("job id {id:?} is not a number")))?;
    let passes_total = {
        let farm = state.farm.lock();
        farm.job(id)?.plan.passes.len() as u32
    };
    history.record(&state, id);
    Ok(Json(Convergence { id, passes_total, points: history.points(id) }))
}

fn asset(content_type: &'static str, body: &'static str) -> Response {
    let mut r = ([(header::CONTENT_TYPE, content_type)], body).into_response();
    r.headers_mut().insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    r
}

/// The dashboard's routes; starts the convergence tracker when called inside a Tokio runtime.
pub fn routes(state: &Arc<AppState>) -> Router<Arc<AppState>> {
    let history = Arc::new(History::default());
    if let Ok(rt) = tokio::runtime::Handle::try_current() {
        rt.spawn(track(Arc::downgrade(state), history.clone()));
    }
    Router::new()
        .route("/", get(|| async { Html(INDEX) }))
        .route("/dashboard/app.js", get(|| async { asset("text/javascript; charset=utf-8", SCRIPT) }))
        .route("/dashboard/style.css", get(|| async { asset("text/css; charset=utf-8", STYLE) }))
        .route("/dashboard/icon.svg", get(|| async { asset("image/svg+xml", ICON) }))
        .route(
            "/api/v1/jobs/{id}/convergence",
            get(move |st: State<Arc<AppState>>, Path(id): Path<String>, Query(q): Query<TokenQuery>, h: HeaderMap| {
                convergence(st, history.clone(), h, q.token, id)
            }),
        )
}
