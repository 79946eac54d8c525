//! The web dashboard at `/`: one HTML page, a stylesheet and a script embedded in the binary
//! (no build step, nothing from other hosts); it reads the REST API and follows
//! `GET /api/v1/events` for live updates.
//!
//! It also serves `GET /api/v1/jobs/{id}/convergence`: the estimated noise of a job's image after
//! each completed pass, measured from the film's variance layer by a small tracker task that
//! follows the job events (and on demand, for passes it missed).

use crate::http::ApiError;
use crate::http::events::authorize_client;
use crate::service::AppState;
use axum::Router;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{Html, IntoResponse, Json, Response};
use axum::routing::get;
use pathfarm_common::film::{Film, luminance};
use pathfarm_common::protocol::API;
use pathfarm_common::protocol::JobId;
use pathfarm_common::routes;
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

/// At most this many pixels are read per measurement (a regular subset of larger images), so
/// the farm lock is held briefly whatever the resolution: 16k pixels put the RMS error within
/// about 1% (1/sqrt(n)), enough for a chart; 64k cost 1.8% of the coordinator's CPU under the
/// load tool (a measurement per completed pass).
const MAX_MEASURED_PIXELS: usize = 1 << 14;

/// Mean samples per pixel, RMS standard error of the pixel means and mean luminance, over a
/// regular subset of the pixels. The variance is the film's `variance.Y` layer (the same formula
/// as [`Film::resolve`]), computed for the chosen pixels only.
pub fn noise(film: &Film) -> (f64, f64, f64) {
    let n = film.sums.len();
    let stride = n.div_ceil(MAX_MEASURED_PIXELS).max(1);
    let (mut var, mut lum, mut spp, mut seen, mut lit) = (0.0f64, 0.0f64, 0.0f64, 0u64, 0u64);
    for p in film.sums.iter().step_by(stride) {
        let w = p.weight();
        seen += 1;
        spp += w;
        if w > 0.0 {
            let v = p.variance_of_mean();
            if v.is_finite() {
                var += v;
            }
            // The mean's luminance, splats included.
            lum += f64::from(luminance(p.radiance_sum().map(|c| (c / w) as f32)));
            lit += 1;
        }
    }
    if lit == 0 {
        return (0.0, 0.0, 0.0);
    }
    (spp / seen as f64, (var / lit as f64).sqrt(), lum / lit as f64)
}

/// A point of a single-frame job (a sequence's frames have no convergence curve).
fn measure(job: &crate::farm::Job) -> Option<ConvergencePoint> {
    let (mean_spp, rmse, mean) = noise(&*job.film()?);
    let passes_done = job.passes_done();
    Some(ConvergencePoint {
        passes_done,
        spp_done: job.plan.passes.get(passes_done as usize).map_or(job.settings.spp, |p| p.s0),
        mean_spp,
        rmse,
        mean_luminance: mean,
        relative: if mean > 0.0 { rmse / mean } else { 0.0 },
    })
}

impl History {
    /// Measures job `id` if a pass completed since its last point; forgets deleted jobs.
    pub fn record(&self, state: &AppState, id: JobId) {
        let last = self.last_pass(id);
        let point = {
            let farm = state.farm.lock();
            match farm.job(id) {
                Ok(job) if job.passes_done() > 0 && last.is_none_or(|l| job.passes_done() > l) => measure(job),
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
            Ok(crate::service::Event::Job { id }) => {
                let Some(s) = state.upgrade() else { return };
                history.record(&s, id);
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
        .route(routes::DASHBOARD, get(|| async { Html(INDEX) }))
        .route(routes::DASHBOARD_SCRIPT, get(|| async { asset("text/javascript; charset=utf-8", SCRIPT) }))
        .route(routes::DASHBOARD_STYLE, get(|| async { asset("text/css; charset=utf-8", STYLE) }))
        .route(routes::DASHBOARD_ICON, get(|| async { asset("image/svg+xml", ICON) }))
        .route(
            &format!("{API}{}", routes::JOB_CONVERGENCE),
            get(move |st: State<Arc<AppState>>, Path(id): Path<String>, Query(q): Query<TokenQuery>, h: HeaderMap| {
                convergence(st, history.clone(), h, q.token, id)
            }),
        )
}

#[cfg(test)]
mod tests {
    use super::*;
    use pathfarm_common::film::{SampleValue, TileAccum, add_sample};
    use pathfarm_common::job::TileRect;

    /// On a small film (every pixel read), the noise is the film's variance layer's.
    #[test]
    fn noise_matches_the_variance_layer() {
        let rect = TileRect { x0: 0, y0: 0, x1: 24, y1: 16 };
        let mut tile = TileAccum::new(rect);
        for y in 0..16 {
            for x in 0..24 {
                for s in 0..(1 + (x + y) % 5) {
                    let v = 0.1 * f32::from((x * 7 + y * 3 + s * 11) as u16 % 13);
                    let sample = SampleValue { radiance: [v, v * 0.5, v * 2.0], ..Default::default() };
                    add_sample(tile.pixel_mut(x, y), &sample);
                }
            }
        }
        let mut film = Film::new(24, 16);
        film.add_tile(&tile);
        let img = film.resolve();
        let n = img.variance.len() as f64;
        let rmse = (img.variance.iter().map(|v| f64::from(*v)).sum::<f64>() / n).sqrt();
        let lum = img.rgb.iter().map(|c| f64::from(luminance(*c))).sum::<f64>() / n;
        let spp = img.samples.iter().map(|s| f64::from(*s)).sum::<f64>() / n;
        let (s, r, l) = noise(&film);
        assert!((s - spp).abs() < 1e-9, "{s} {spp}");
        assert!((r - rmse).abs() < 1e-6 * rmse.max(1e-9), "{r} {rmse}");
        assert!((l - lum).abs() < 1e-5 * lum, "{l} {lum}");
        assert!(r > 0.0);
        assert_eq!(noise(&Film::new(8, 8)), (0.0, 0.0, 0.0));
    }
}
