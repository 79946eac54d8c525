//! Serving TCP connections: the accept loop, a cap on open connections, and per-connection
//! timeouts, so idle or half-sent connections (slowloris) cannot use up the process's file
//! descriptors and lock out health probes, workers and clients.
//!
//! Rules, checked about four times per `header_timeout`:
//! - a new connection must deliver its first request head within `header_timeout` of being
//!   accepted;
//! - a later request's head must be complete within `header_timeout` of its first byte (bytes
//!   of a request body the handler did not read, after an early answer such as 401, count as
//!   such a head: draining them is bounded the same way);
//! - between requests, a connection on which no byte moves for `idle_timeout` is closed;
//! - while a request is being handled (from its head until its response body is written) the
//!   connection is never closed for being quiet: a lease long poll (up to 20 s), a scene being
//!   loaded or an event stream are not idle. Only authorized requests get that far for long,
//!   an unauthorized one is answered at once.
//!
//! At most `max_connections` are open. A connection accepted beyond the cap closes the open
//! connection that is not handling a request and has been quiet longest; when every connection
//! is handling a request, the new one waits up to a second for a slot and is closed otherwise.
//! The same eviction frees a descriptor when `accept` fails (EMFILE).

use crate::service::{AppState, ConnLimits};
use axum::Router;
use axum::body::{Body, Bytes};
use hyper::body::Incoming;
use hyper_util::rt::TokioIo;
use std::collections::HashMap;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{Notify, Semaphore};
use tower::ServiceExt;

/// Descriptors kept for everything but connections (SQLite, scenes, checkpoints, images).
const FD_RESERVE: u64 = 128;

/// `max_connections`, lowered to fit the process's open-file limit (Linux: `/proc/self/limits`).
pub fn fit_to_fd_limit(max_connections: usize) -> usize {
    let soft = std::fs::read_to_string("/proc/self/limits").ok().and_then(|t| {
        t.lines()
            .find(|l| l.starts_with("Max open files"))
            .and_then(|l| l.split_whitespace().nth(3))
            .and_then(|v| v.parse::<u64>().ok())
    });
    match soft {
        Some(soft) if (max_connections as u64).saturating_add(FD_RESERVE) > soft => {
            let fit = soft.saturating_sub(FD_RESERVE).max(16) as usize;
            tracing::warn!(
                max_connections,
                open_file_limit = soft,
                using = fit,
                "--max-connections does not fit the open-file limit; raise it (ulimit -n, LimitNOFILE)"
            );
            fit.min(max_connections)
        }
        _ => max_connections,
    }
}

const NONE: u64 = u64::MAX;

/// What the watchdog and the eviction need to know about one connection (times in ms since
/// the server's `base`).
struct ConnState {
    accepted_ms: u64,
    last_io_ms: AtomicU64,
    /// First byte of a request head not yet handed to the service; `NONE` if none.
    head_since_ms: AtomicU64,
    /// Requests being handled (head received, response body not yet written).
    in_flight: AtomicUsize,
    /// Requests handed to the service so far.
    served: AtomicU64,
    evicted: AtomicBool,
    close: Notify,
}

struct Clock(Instant);

impl Clock {
    fn ms(&self) -> u64 {
        self.0.elapsed().as_millis() as u64
    }
}

/// The TCP stream, noting when bytes move.
struct Tracked {
    io: TcpStream,
    st: Arc<ConnState>,
    clock: Arc<Clock>,
}

impl AsyncRead for Tracked {
    fn poll_read(self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<std::io::Result<()>> {
        let this = self.get_mut();
        let before = buf.filled().len();
        let r = Pin::new(&mut this.io).poll_read(cx, buf);
        if matches!(r, Poll::Ready(Ok(()))) && buf.filled().len() > before {
            let now = this.clock.ms();
            this.st.last_io_ms.store(now, Ordering::Relaxed);
            if this.st.in_flight.load(Ordering::Relaxed) == 0 {
                let _ = this.st.head_since_ms.compare_exchange(NONE, now, Ordering::Relaxed, Ordering::Relaxed);
            }
        }
        r
    }
}

impl Tracked {
    fn wrote(&self, r: &Poll<std::io::Result<usize>>) {
        if matches!(r, Poll::Ready(Ok(n)) if *n > 0) {
            self.st.last_io_ms.store(self.clock.ms(), Ordering::Relaxed);
        }
    }
}

impl AsyncWrite for Tracked {
    fn poll_write(self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<std::io::Result<usize>> {
        let this = self.get_mut();
        let r = Pin::new(&mut this.io).poll_write(cx, buf);
        this.wrote(&r);
        r
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        let this = self.get_mut();
        let r = Pin::new(&mut this.io).poll_write_vectored(cx, bufs);
        this.wrote(&r);
        r
    }

    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.get_mut().io).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.get_mut().io).poll_shutdown(cx)
    }
}

/// Marks a request as being handled until dropped (with its response body).
struct InFlight {
    st: Arc<ConnState>,
    clock: Arc<Clock>,
}

impl InFlight {
    fn new(st: Arc<ConnState>, clock: Arc<Clock>) -> Self {
        st.in_flight.fetch_add(1, Ordering::Relaxed);
        st.served.fetch_add(1, Ordering::Relaxed);
        st.head_since_ms.store(NONE, Ordering::Relaxed);
        Self { st, clock }
    }
}

impl Drop for InFlight {
    fn drop(&mut self) {
        // The idle clock starts when the answer is out.
        self.st.last_io_ms.store(self.clock.ms(), Ordering::Relaxed);
        self.st.in_flight.fetch_sub(1, Ordering::Relaxed);
    }
}

/// A response body that keeps its request marked as being handled until it is written.
struct GuardedBody {
    inner: Body,
    _guard: InFlight,
}

impl http_body::Body for GuardedBody {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Bytes>, axum::Error>>> {
        Pin::new(&mut self.get_mut().inner).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

/// Open connections, for eviction.
#[derive(Default)]
struct Registry {
    conns: Mutex<HashMap<u64, Arc<ConnState>>>,
}

impl Registry {
    fn conns(&self) -> std::sync::MutexGuard<'_, HashMap<u64, Arc<ConnState>>> {
        self.conns.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Asks the quietest connection that is not handling a request to close; false if none.
    fn evict_one(&self) -> bool {
        let conns = self.conns();
        let victim = conns
            .values()
            .filter(|c| c.in_flight.load(Ordering::Relaxed) == 0 && !c.evicted.load(Ordering::Relaxed))
            .min_by_key(|c| c.last_io_ms.load(Ordering::Relaxed));
        match victim {
            Some(c) => {
                c.evicted.store(true, Ordering::Relaxed);
                c.close.notify_one();
                true
            }
            None => false,
        }
    }
}

/// Why a connection was closed by its watchdog.
fn overdue(st: &ConnState, limits: &ConnLimits, now: u64) -> Option<&'static str> {
    if st.in_flight.load(Ordering::Relaxed) > 0 {
        return None;
    }
    let header = limits.header_timeout.as_millis() as u64;
    let head = st.head_since_ms.load(Ordering::Relaxed);
    if st.served.load(Ordering::Relaxed) == 0 {
        return (now.saturating_sub(st.accepted_ms) > header).then_some("no complete request head in time");
    }
    if head != NONE {
        return (now.saturating_sub(head) > header).then_some("request head not complete in time");
    }
    let idle = limits.idle_timeout.as_millis() as u64;
    (now.saturating_sub(st.last_io_ms.load(Ordering::Relaxed)) > idle).then_some("idle")
}

async fn watchdog(st: Arc<ConnState>, clock: Arc<Clock>, limits: ConnLimits) -> &'static str {
    let tick =
        (limits.header_timeout.min(limits.idle_timeout) / 4).clamp(Duration::from_millis(50), Duration::from_secs(1));
    loop {
        tokio::time::sleep(tick).await;
        if let Some(why) = overdue(&st, &limits, clock.ms()) {
            return why;
        }
    }
}

/// Serves `app` on `listener` until the task is dropped or aborted.
/// With `tls`, every connection is a TLS connection (HTTP/1.1 inside).
pub async fn serve(
    listener: TcpListener,
    app: Router,
    limits: ConnLimits,
    state: Arc<AppState>,
    tls: Option<tokio_rustls::TlsAcceptor>,
) {
    let clock = Arc::new(Clock(Instant::now()));
    let slots = Arc::new(Semaphore::new(limits.max_connections.max(1)));
    let registry = Arc::new(Registry::default());
    let mut builder = hyper::server::conn::http1::Builder::new();
    // Our watchdog does the timing (hyper's own header timeout would also cut the wait between
    // requests, and needs a timer).
    builder.header_read_timeout(None);
    let mut next_id: u64 = 0;
    loop {
        let (stream, peer) = match listener.accept().await {
            Ok(s) => s,
            Err(e) => {
                // Out of descriptors (or a connection reset before it was accepted): free one.
                tracing::warn!("accept failed: {e}");
                registry.evict_one();
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let permit = match slots.clone().try_acquire_owned() {
            Ok(p) => p,
            Err(_) => {
                if registry.evict_one() {
                    state.metrics.connections_evicted.fetch_add(1, Ordering::Relaxed);
                }
                match tokio::time::timeout(Duration::from_secs(1), slots.clone().acquire_owned()).await {
                    Ok(Ok(p)) => p,
                    _ => {
                        state.metrics.connections_refused.fetch_add(1, Ordering::Relaxed);
                        tracing::debug!(%peer, "connection cap reached, every connection busy: closing the new one");
                        continue;
                    }
                }
            }
        };
        let _ = stream.set_nodelay(true);
        let now = clock.ms();
        let st = Arc::new(ConnState {
            accepted_ms: now,
            last_io_ms: AtomicU64::new(now),
            head_since_ms: AtomicU64::new(NONE),
            in_flight: AtomicUsize::new(0),
            served: AtomicU64::new(0),
            evicted: AtomicBool::new(false),
            close: Notify::new(),
        });
        let id = next_id;
        next_id += 1;
        registry.conns().insert(id, st.clone());
        let tracked = Tracked { io: stream, st: st.clone(), clock: clock.clone() };
        let (registry, state, clock, app, builder, tls) =
            (registry.clone(), state.clone(), clock.clone(), app.clone(), builder.clone(), tls.clone());
        tokio::spawn(async move {
            let _permit = permit;
            state.metrics.connections_open.fetch_add(1, Ordering::Relaxed);
            let conn = Conn { app, builder, st, clock, limits, peer };
            match tls {
                None => conn.drive(tracked, &state).await,
                // The handshake counts against the header timeout, like a slow request head.
                Some(acceptor) => match tokio::time::timeout(limits.header_timeout, acceptor.accept(tracked)).await {
                    Ok(Ok(tls_stream)) => conn.drive(tls_stream, &state).await,
                    Ok(Err(e)) => tracing::debug!(%peer, "TLS handshake failed: {e}"),
                    Err(_) => {
                        state.metrics.connections_timed_out.fetch_add(1, Ordering::Relaxed);
                        tracing::debug!(%peer, "closing the connection: TLS handshake not complete in time");
                    }
                },
            }
            state.metrics.connections_open.fetch_sub(1, Ordering::Relaxed);
            registry.conns().remove(&id);
        });
    }
}

/// One accepted connection, ready to serve HTTP/1 over a plain or TLS stream.
struct Conn {
    app: Router,
    builder: hyper::server::conn::http1::Builder,
    st: Arc<ConnState>,
    clock: Arc<Clock>,
    limits: ConnLimits,
    peer: std::net::SocketAddr,
}

impl Conn {
    async fn drive<I>(self, io: I, state: &AppState)
    where
        I: AsyncRead + AsyncWrite + Unpin + Send + 'static,
    {
        let Conn { app, builder, st, clock, limits, peer } = self;
        let svc = {
            let (st, clock) = (st.clone(), clock.clone());
            hyper::service::service_fn(move |req: hyper::Request<Incoming>| {
                let (app, guard) = (app.clone(), InFlight::new(st.clone(), clock.clone()));
                async move {
                    let mut req = req.map(Body::new);
                    // The client's address, for per-address limits (worker registrations).
                    req.extensions_mut().insert(axum::extract::ConnectInfo(peer));
                    let resp = app.oneshot(req).await?;
                    Ok::<_, std::convert::Infallible>(resp.map(|inner| Body::new(GuardedBody { inner, _guard: guard })))
                }
            })
        };
        let conn = builder.serve_connection(TokioIo::new(io), svc);
        tokio::pin!(conn);
        tokio::select! {
            r = conn.as_mut() => {
                if let Err(e) = r {
                    tracing::debug!(%peer, "connection ended: {e}");
                }
            }
            why = watchdog(st.clone(), clock, limits) => {
                state.metrics.connections_timed_out.fetch_add(1, Ordering::Relaxed);
                tracing::debug!(%peer, "closing the connection: {why}");
            }
            () = st.close.notified() => {
                tracing::debug!(%peer, "closing a quiet connection to make room (connection cap)");
            }
        }
    }
}

/// A TLS acceptor for `cert` (PEM chain, leaf first) and `key` (PEM private key).
pub fn tls_acceptor(cert: &std::path::Path, key: &std::path::Path) -> anyhow::Result<tokio_rustls::TlsAcceptor> {
    use anyhow::Context as _;
    use rustls_pki_types::pem::PemObject;
    use rustls_pki_types::{CertificateDer, PrivateKeyDer};
    use tokio_rustls::rustls;
    let certs = CertificateDer::pem_file_iter(cert)
        .and_then(|it| it.collect::<Result<Vec<_>, _>>())
        .with_context(|| format!("reading the TLS certificate chain {}", cert.display()))?;
    anyhow::ensure!(!certs.is_empty(), "{} holds no PEM certificate", cert.display());
    let key = PrivateKeyDer::from_pem_file(key).with_context(|| format!("reading the TLS key {}", key.display()))?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut cfg = rustls::ServerConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .context("TLS protocol versions")?
        .with_no_client_auth()
        .with_single_cert(certs, key)
        .context("the TLS certificate and key do not form a valid pair")?;
    cfg.alpn_protocols = vec![b"http/1.1".to_vec()];
    Ok(tokio_rustls::TlsAcceptor::from(Arc::new(cfg)))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn state(accepted: u64, last_io: u64, head: u64, in_flight: usize, served: u64) -> ConnState {
        ConnState {
            accepted_ms: accepted,
            last_io_ms: AtomicU64::new(last_io),
            head_since_ms: AtomicU64::new(head),
            in_flight: AtomicUsize::new(in_flight),
            served: AtomicU64::new(served),
            evicted: AtomicBool::new(false),
            close: Notify::new(),
        }
    }

    #[test]
    fn watchdog_rules() {
        let l = ConnLimits {
            header_timeout: Duration::from_millis(1000),
            idle_timeout: Duration::from_millis(5000),
            max_connections: 8,
        };
        // A new connection: the first head is due a header timeout after the accept, bytes or not.
        assert_eq!(overdue(&state(0, 0, NONE, 0, 0), &l, 1000), None);
        assert!(overdue(&state(0, 0, NONE, 0, 0), &l, 1001).is_some());
        assert!(overdue(&state(0, 900, 500, 0, 0), &l, 1001).is_some());
        // Handling a request (a long poll): never, however quiet.
        assert_eq!(overdue(&state(0, 0, NONE, 1, 1), &l, 60_000), None);
        // Between requests: idle timeout since the last byte...
        assert_eq!(overdue(&state(0, 2000, NONE, 0, 1), &l, 7000), None);
        assert_eq!(overdue(&state(0, 2000, NONE, 0, 1), &l, 7001), Some("idle"));
        // ... and a started head must complete within the header timeout of its first byte.
        assert_eq!(overdue(&state(0, 2900, 2000, 0, 1), &l, 3000), None);
        assert!(overdue(&state(0, 2900, 2000, 0, 1), &l, 3001).is_some());
    }

    #[test]
    fn eviction_picks_the_quietest_connection_not_handling_a_request() {
        let r = Registry::default();
        r.conns().insert(1, Arc::new(state(0, 10, NONE, 1, 1)));
        r.conns().insert(2, Arc::new(state(0, 50, NONE, 0, 1)));
        r.conns().insert(3, Arc::new(state(0, 20, NONE, 0, 0)));
        assert!(r.evict_one());
        assert!(r.conns()[&3].evicted.load(Ordering::Relaxed));
        assert!(r.evict_one());
        assert!(r.conns()[&2].evicted.load(Ordering::Relaxed));
        // Connection 1 is handling a request.
        assert!(!r.evict_one());
        assert!(!r.conns()[&1].evicted.load(Ordering::Relaxed));
    }
}
