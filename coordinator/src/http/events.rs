//! Live events for dashboards: `GET /api/v1/events`, a server-sent event stream.
//!
//! The handlers publish bare [`crate::service::Event`]s (an enum: job, image, frame, worker) on a broadcast channel;
//! each connection coalesces them (at most one message per id every [`MIN_GAP`]) and turns them
//! into JSON messages:
//!
//! | SSE event     | data                                                    |
//! |---------------|---------------------------------------------------------|
//! | `snapshot`    | `{"jobs": [JobInfo], "workers": [WorkerInfo]}`, first    |
//! | `job`         | the job's `JobInfo`                                     |
//! | `job_deleted` | `{"id": N}`                                             |
//! | `workers`     | `[WorkerInfo]`, on worker changes and every 2 s         |
//! | `image`       | `{"id": N}`: the job's preview and EXR were rewritten   |
//! | `frame`       | `{"id": N, "frame": F}`: frame F of sequence N is written (every one, in order) |
//! | `resync`      | `{}`: events were dropped; fetch the lists again        |
//!
//! A comment line keeps idle connections open. Browsers' `EventSource` cannot send headers, so
//! besides `Authorization: Bearer` this route takes the client token as `?token=`.

use crate::http::ApiError;
use crate::service::{AppState, Auth, now_ms};
use axum::extract::{Query, State};
use axum::http::HeaderMap;
use axum::response::sse::{Event as SseEvent, KeepAlive, Sse};
use futures_util::stream::Stream;
use pathfarm_common::protocol::{JobId, JobInfo, WorkerInfo};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeSet, HashMap};
use std::convert::Infallible;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::{broadcast, mpsc};

/// Shortest time between two messages about the same job (or two worker lists).
pub const MIN_GAP: Duration = Duration::from_millis(250);
/// The worker list is sent at least this often (states like `offline` change without events).
pub const WORKERS_EVERY: Duration = Duration::from_secs(2);
/// Keep-alive comment interval.
pub const KEEP_ALIVE: Duration = Duration::from_secs(15);

/// Query of `GET /events`.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
pub struct EventsQuery {
    /// The client token, for clients that cannot send an `Authorization` header (EventSource).
    pub token: Option<String>,
}

/// First message of the stream: everything a dashboard shows.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct Snapshot {
    pub jobs: Vec<JobInfo>,
    pub workers: Vec<WorkerInfo>,
}

/// Data of `image` and `job_deleted` messages.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct IdOnly {
    pub id: u64,
}

/// Client-token check that also takes the token from the query string.
pub fn authorize_client(auth: &Auth, headers: &HeaderMap, query_token: Option<&str>) -> Result<(), ApiError> {
    crate::http::authorize_token(auth, crate::http::bearer(headers).or(query_token), &[crate::http::Role::Client])
}

fn message(name: &str, data: &impl Serialize) -> SseEvent {
    SseEvent::default().event(name).data(serde_json::to_string(data).unwrap_or_else(|_| "{}".into()))
}

fn snapshot(state: &AppState) -> Snapshot {
    let farm = state.farm.lock();
    let now = now_ms();
    Snapshot { jobs: farm.jobs().map(|j| j.info(now)).collect(), workers: farm.workers(now) }
}

/// Data of `frame` messages.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct FrameWritten {
    pub id: u64,
    pub frame: i32,
}

/// Frame messages one connection holds at most; beyond, it is told to `resync`.
const MAX_PENDING_FRAMES: usize = 4096;

/// What one connection still has to say.
#[derive(Default)]
struct Pending {
    jobs: BTreeSet<JobId>,
    images: BTreeSet<JobId>,
    /// Frames written, in order (not coalesced: each is news).
    frames: Vec<FrameWritten>,
    /// Frame messages were dropped: the client must fetch the lists again.
    resync: bool,
    workers: bool,
}

/// Coalesces events per id and turns them into messages (one connection).
struct Coalescer {
    pending: Pending,
    last_job: HashMap<JobId, Instant>,
    last_image: HashMap<JobId, Instant>,
    last_workers: Instant,
}

impl Coalescer {
    fn new() -> Self {
        Self {
            pending: Pending::default(),
            last_job: HashMap::new(),
            last_image: HashMap::new(),
            last_workers: Instant::now(),
        }
    }

    fn note(&mut self, event: crate::service::Event) {
        use crate::service::Event;
        match event {
            Event::Frame { id, frame } => {
                if self.pending.frames.len() < MAX_PENDING_FRAMES {
                    self.pending.frames.push(FrameWritten { id, frame });
                } else {
                    self.pending.resync = true;
                }
            }
            Event::Job { id } => {
                self.pending.jobs.insert(id);
            }
            Event::Image { id } => {
                self.pending.images.insert(id);
            }
            Event::Worker { .. } => self.pending.workers = true,
        }
    }

    /// Messages due now.
    fn flush(&mut self, state: &AppState) -> Vec<SseEvent> {
        let now = Instant::now();
        let due = |last: &HashMap<JobId, Instant>, id: &JobId| last.get(id).is_none_or(|t| now - *t >= MIN_GAP);
        let jobs: Vec<JobId> = self.pending.jobs.iter().copied().filter(|id| due(&self.last_job, id)).collect();
        let images: Vec<JobId> = self.pending.images.iter().copied().filter(|id| due(&self.last_image, id)).collect();
        let workers =
            (self.pending.workers && now - self.last_workers >= MIN_GAP) || now - self.last_workers >= WORKERS_EVERY;
        let mut out = Vec::new();
        if !jobs.is_empty() || workers {
            let farm = state.farm.lock();
            let t = now_ms();
            for id in &jobs {
                match farm.job(*id) {
                    Ok(j) => out.push(message("job", &j.info(t))),
                    Err(_) => out.push(message("job_deleted", &IdOnly { id: *id })),
                }
            }
            if workers {
                out.push(message("workers", &farm.workers(t)));
            }
        }
        for id in jobs {
            self.pending.jobs.remove(&id);
            self.last_job.insert(id, now);
        }
        if std::mem::take(&mut self.pending.resync) {
            out.push(SseEvent::default().event("resync").data("{}"));
        }
        for f in std::mem::take(&mut self.pending.frames) {
            out.push(message("frame", &f));
        }
        for id in images {
            out.push(message("image", &IdOnly { id }));
            self.pending.images.remove(&id);
            self.last_image.insert(id, now);
        }
        if workers {
            self.pending.workers = false;
            self.last_workers = now;
        }
        out
    }
}

/// Feeds one connection until the client goes away.
async fn pump(state: Arc<AppState>, mut rx: broadcast::Receiver<crate::service::Event>, tx: mpsc::Sender<SseEvent>) {
    let mut c = Coalescer::new();
    let mut tick = tokio::time::interval(Duration::from_millis(100));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            () = tx.closed() => return,
            r = rx.recv() => match r {
                Ok(ev) => c.note(ev),
                Err(broadcast::error::RecvError::Lagged(_)) => {
                    if tx.send(SseEvent::default().event("resync").data("{}")).await.is_err() {
                        return;
                    }
                }
                Err(broadcast::error::RecvError::Closed) => return,
            },
            _ = tick.tick() => {
                for m in c.flush(&state) {
                    if tx.send(m).await.is_err() {
                        return;
                    }
                }
            }
        }
    }
}

/// `GET /api/v1/events`.
pub async fn events(
    State(state): State<Arc<AppState>>,
    Query(q): Query<EventsQuery>,
    headers: HeaderMap,
) -> Result<Sse<impl Stream<Item = Result<SseEvent, Infallible>>>, ApiError> {
    authorize_client(&state.auth, &headers, q.token.as_deref())?;
    // Subscribe before the snapshot, so nothing falls between the two.
    let rx = state.events.subscribe();
    let first = message("snapshot", &snapshot(&state));
    let (tx, out) = mpsc::channel::<SseEvent>(64);
    let _ = tx.try_send(first);
    tokio::spawn(pump(state, rx, tx));
    let stream = futures_util::stream::unfold(out, |mut out| async move { out.recv().await.map(|m| (Ok(m), out)) });
    Ok(Sse::new(stream).keep_alive(KeepAlive::new().interval(KEEP_ALIVE)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::ServerConfig;
    use axum::body::Body;
    use axum::http::{Request, StatusCode, header};
    use futures_util::StreamExt;
    use tower::ServiceExt;

    fn auth() -> Auth {
        Auth { client: Some("client-secret".into()), worker: Some("worker-secret".into()) }
    }

    fn bearer(t: &str) -> HeaderMap {
        let mut h = HeaderMap::new();
        h.insert(header::AUTHORIZATION, format!("Bearer {t}").parse().expect("header"));
        h
    }

    #[test]
    fn token_from_header_or_query() {
        let none = HeaderMap::new();
        assert!(authorize_client(&Auth::default(), &none, None).is_ok());
        let a = auth();
        assert!(authorize_client(&a, &bearer("client-secret"), None).is_ok());
        assert!(authorize_client(&a, &none, Some("client-secret")).is_ok());
        assert_eq!(authorize_client(&a, &none, None).map_err(|e| e.status), Err(StatusCode::UNAUTHORIZED));
        assert_eq!(
            authorize_client(&a, &none, Some("client-secreT")).map_err(|e| e.status),
            Err(StatusCode::UNAUTHORIZED)
        );
        assert_eq!(
            authorize_client(&a, &bearer("worker-secret"), None).map_err(|e| e.status),
            Err(StatusCode::FORBIDDEN)
        );
        assert_eq!(
            authorize_client(&a, &none, Some("worker-secret")).map_err(|e| e.status),
            Err(StatusCode::FORBIDDEN)
        );
    }

    /// Reads the stream for `d`, returning the text received.
    async fn read_for(body: Body, d: Duration) -> String {
        let mut stream = body.into_data_stream();
        let mut text = String::new();
        let _ = tokio::time::timeout(d, async {
            while let Some(Ok(chunk)) = stream.next().await {
                text.push_str(&String::from_utf8_lossy(&chunk));
            }
        })
        .await;
        text
    }

    #[tokio::test]
    async fn stream_starts_with_a_snapshot_and_coalesces_bursts() {
        let tmp = tempfile::tempdir().expect("tempdir");
        let mut cfg = ServerConfig::new("127.0.0.1:0".parse().expect("addr"), tmp.path().to_path_buf());
        cfg.auth = auth();
        let state = Arc::new(AppState::new(cfg).expect("state"));
        let app = crate::http::router(state.clone());

        let req = Request::builder().uri("/api/v1/events").body(Body::empty()).expect("request");
        assert_eq!(app.clone().oneshot(req).await.expect("response").status(), StatusCode::UNAUTHORIZED);

        let req = Request::builder().uri("/api/v1/events?token=client-secret").body(Body::empty()).expect("request");
        let resp = app.oneshot(req).await.expect("response");
        assert_eq!(resp.status(), StatusCode::OK);
        let ct = resp.headers().get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or_default();
        assert!(ct.starts_with("text/event-stream"), "{ct}");
        let body = resp.into_body();
        let publisher = {
            let state = state.clone();
            tokio::spawn(async move {
                tokio::time::sleep(Duration::from_millis(50)).await;
                for _ in 0..500 {
                    state.publish(crate::service::Event::Job { id: 7 });
                    state.publish(crate::service::Event::Image { id: 7 });
                    tokio::task::yield_now().await;
                }
                state.publish_frame(7, 12);
                state.publish_frame(7, 13);
            })
        };
        let text = read_for(body, Duration::from_millis(700)).await;
        publisher.await.expect("publisher");
        assert!(text.starts_with("event: snapshot\ndata: {\"jobs\":[],\"workers\":[]}"), "{text}");
        // Job 7 does not exist: its messages say so. 500 events in a burst, 700 ms: a few messages.
        let jobs = text.matches("event: job_deleted\ndata: {\"id\":7}").count();
        let images = text.matches("event: image\ndata: {\"id\":7}").count();
        assert!((1..=4).contains(&jobs), "{jobs} job messages:\n{text}");
        assert!((1..=4).contains(&images), "{images} image messages:\n{text}");
        // Frame messages are not coalesced: both, in order.
        let f12 = text.find("event: frame\ndata: {\"id\":7,\"frame\":12}").expect("frame 12");
        let f13 = text.find("event: frame\ndata: {\"id\":7,\"frame\":13}").expect("frame 13");
        assert!(f12 < f13, "{text}");
    }
}
