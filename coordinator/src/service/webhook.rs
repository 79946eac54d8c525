//! Job webhooks (`notify` in a job's body): when a job reaches a state its `notify.events` name,
//! the coordinator POSTs `{"event", "job": <JobInfo>, "sent_ms"}` to `notify.url`, signed with
//! `X-Pathfarm-Signature: sha256=<hex HMAC-SHA256 of the body>` keyed by `--webhook-secret`.
//!
//! Delivery never blocks the coordinator: the farm queues events, the maintenance loop moves them
//! into a bounded channel (an event that does not fit is dropped, and the job's log says so) and
//! a task sends them, a few at once, each with a timeout per attempt and retries with
//! exponential backoff. Every outcome goes to the job's log.

use crate::service::{AppState, now_ms};
use hmac::{Hmac, Mac};
use pathfarm_common::protocol::{JobId, JobInfo, NotifyEvent};
use sha2::Sha256;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::mpsc;

/// How webhooks are sent.
#[derive(Clone, Debug)]
pub struct WebhookConfig {
    /// The HMAC key; without it jobs asking for `notify` are refused (422).
    pub secret: Option<String>,
    /// Attempts per event (at least 1).
    pub attempts: u32,
    /// The wait before the first retry; it doubles after each failed attempt.
    pub retry_base: Duration,
    /// The limit of one attempt (connect, send, answer).
    pub timeout: Duration,
    /// Events waiting to be sent at most; beyond it new ones are dropped.
    pub queue: usize,
    /// Deliveries in flight at once.
    pub concurrency: usize,
}

impl Default for WebhookConfig {
    fn default() -> Self {
        Self {
            secret: None,
            attempts: 5,
            retry_base: Duration::from_secs(1),
            timeout: Duration::from_secs(5),
            queue: 1024,
            concurrency: 16,
        }
    }
}

/// One event for one job's webhook.
#[derive(Debug)]
pub struct Delivery {
    pub job: JobId,
    pub event: NotifyEvent,
    pub url: String,
    /// The job's info when the event happened.
    pub info: Box<JobInfo>,
}

/// The bounded queue between the maintenance loop and the sender task.
pub struct Queue {
    tx: mpsc::Sender<Delivery>,
    rx: Mutex<Option<mpsc::Receiver<Delivery>>>,
}

impl Queue {
    pub fn new(capacity: usize) -> Self {
        let (tx, rx) = mpsc::channel(capacity.max(1));
        Self { tx, rx: Mutex::new(Some(rx)) }
    }

    /// Queues a delivery without waiting; gives it back when the queue is full or closed.
    pub fn try_send(&self, d: Delivery) -> Result<(), Delivery> {
        self.tx.try_send(d).map_err(|e| match e {
            mpsc::error::TrySendError::Full(d) | mpsc::error::TrySendError::Closed(d) => d,
        })
    }
}

/// `sha256=<hex HMAC-SHA256(secret, body)>`, the value of `X-Pathfarm-Signature`.
pub fn signature(secret: &[u8], body: &[u8]) -> String {
    // HMAC takes keys of any length; new_from_slice cannot fail for it.
    let Ok(mut mac) = <Hmac<Sha256> as Mac>::new_from_slice(secret) else { return String::new() };
    mac.update(body);
    format!("sha256={}", hex::encode(mac.finalize().into_bytes()))
}

/// The JSON body of a delivery attempt.
pub fn body(event: NotifyEvent, info: &JobInfo, sent_ms: u64) -> Vec<u8> {
    serde_json::to_vec(&serde_json::json!({"event": event, "job": info, "sent_ms": sent_ms})).unwrap_or_default()
}

/// Moves the farm's queued events into the delivery queue (called by the maintenance loop).
pub fn enqueue_pending(state: &AppState) {
    let deliveries: Vec<Delivery> = {
        let mut farm = state.farm.lock();
        let now = now_ms();
        let events = farm.take_notifications();
        events
            .into_iter()
            .filter_map(|(id, event)| {
                let job = farm.job(id).ok()?;
                let url = job.notify.as_ref()?.url.clone();
                Some(Delivery { job: id, event, url, info: Box::new(job.info(now)) })
            })
            .collect()
    };
    for d in deliveries {
        if state.config.webhooks.secret.is_none() {
            let line =
                format!("notification {} not sent: the coordinator runs without --webhook-secret", d.event.as_str());
            tracing::warn!(job = d.job, event = d.event.as_str(), "{line}");
            state.log_job(d.job, line);
            continue;
        }
        if let Err(d) = state.webhooks.try_send(d) {
            let line = format!("notification {} dropped: the webhook queue is full", d.event.as_str());
            tracing::warn!(job = d.job, event = d.event.as_str(), "{line}");
            state.log_job(d.job, line);
        }
    }
}

/// Sends queued deliveries, at most `concurrency` at once, until the queue closes.
pub async fn run(state: Arc<AppState>) {
    let rx = state.webhooks.rx.lock().unwrap_or_else(|e| e.into_inner()).take();
    let Some(mut rx) = rx else { return };
    let cfg = state.config.webhooks.clone();
    let client = match reqwest::Client::builder()
        .timeout(cfg.timeout)
        .redirect(reqwest::redirect::Policy::none())
        .user_agent(concat!("pathfarm-coordinator/", env!("CARGO_PKG_VERSION")))
        .build()
    {
        Ok(c) => c,
        Err(e) => {
            tracing::error!(error = %e, "webhooks disabled: the HTTP client could not be built");
            return;
        }
    };
    let permits = Arc::new(tokio::sync::Semaphore::new(cfg.concurrency.max(1)));
    while let Some(d) = rx.recv().await {
        let Ok(permit) = permits.clone().acquire_owned().await else { return };
        let (state, client, cfg) = (state.clone(), client.clone(), cfg.clone());
        tokio::spawn(async move {
            deliver(&state, &client, &cfg, d).await;
            drop(permit);
        });
    }
}

async fn deliver(state: &AppState, client: &reqwest::Client, cfg: &WebhookConfig, d: Delivery) {
    let secret = cfg.secret.as_deref().unwrap_or_default().as_bytes();
    let event = d.event.as_str();
    let attempts = cfg.attempts.max(1);
    let log = |line: String| state.log_job(d.job, line);
    let mut last_error = String::new();
    for attempt in 1..=attempts {
        let body = body(d.event, &d.info, now_ms());
        let sent = client
            .post(&d.url)
            .header(reqwest::header::CONTENT_TYPE, "application/json")
            .header("X-Pathfarm-Event", event)
            .header("X-Pathfarm-Signature", signature(secret, &body))
            .body(body)
            .send()
            .await;
        match sent {
            Ok(resp) if resp.status().is_success() => {
                let status = resp.status().as_u16();
                tracing::info!(job = d.job, event, status, attempt, "webhook delivered");
                log(format!("notified {event}: {status}"));
                return;
            }
            Ok(resp) => last_error = format!("HTTP {}", resp.status()),
            // Without the URL: it may carry a token in its query.
            Err(e) => last_error = describe(&e.without_url()),
        }
        if attempt < attempts {
            let wait = cfg.retry_base.saturating_mul(1 << (attempt - 1).min(16));
            tracing::warn!(job = d.job, event, attempt, error = %last_error, wait_ms = wait.as_millis() as u64, "webhook attempt failed; retrying");
            log(format!(
                "notification {event}: attempt {attempt} failed ({last_error}); retrying in {} ms",
                wait.as_millis()
            ));
            tokio::time::sleep(wait).await;
        }
    }
    tracing::warn!(job = d.job, event, attempts, error = %last_error, "webhook not delivered");
    log(format!("notification {event} failed after {attempts} attempts: {last_error}"));
}

/// A reqwest error with its causes (the top level alone says little, e.g. "error sending request").
fn describe(e: &reqwest::Error) -> String {
    let mut s = e.to_string();
    let mut src = std::error::Error::source(e);
    while let Some(c) = src {
        s.push_str(": ");
        s.push_str(&c.to_string());
        src = c.source();
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn signature_is_rfc4231_hmac_sha256() {
        // RFC 4231 test case 2.
        assert_eq!(
            signature(b"Jefe", b"what do ya want for nothing?"),
            "sha256=5bdcc146bf60754e6a042426089575c75a003f089d2739839dec58b964ec3843"
        );
    }
}
