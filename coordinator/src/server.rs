//! The top floor: binds the listener, wires the service's loops and the HTTP router together,
//! and runs them until shutdown.

pub use crate::service::{AppState, Auth, SCENE_GC_AFTER_MS, ServerConfig};
use pathfarm_common::film::write_atomic;
use std::net::SocketAddr;
use std::sync::Arc;

/// A running coordinator: [`run`] on a task of its own, stopped by [`Server::shutdown`].
pub struct Server {
    pub addr: SocketAddr,
    pub state: Arc<AppState>,
    stop: tokio::sync::oneshot::Sender<()>,
    task: tokio::task::JoinHandle<anyhow::Result<()>>,
}

impl Server {
    /// Opens the data dir, binds, writes `coordinator.addr` and starts [`run`]; it serves until
    /// [`Server::shutdown`] (or the runtime ends).
    pub async fn start(config: ServerConfig) -> anyhow::Result<Self> {
        let state = Arc::new(AppState::new(config.clone())?);
        let listener = tokio::net::TcpListener::bind(config.listen).await?;
        let addr = listener.local_addr()?;
        write_atomic(&config.data_dir.join("coordinator.addr"), addr.to_string().as_bytes())?;
        // A bad certificate or key is the start's error, not a later one.
        let tls = tls_acceptor(&config)?;
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let task = tokio::spawn(serve(listener, state.clone(), tls, async move {
            // A dropped `Server` serves on (as before `shutdown` existed); only a send stops it.
            if stopped.await.is_err() {
                std::future::pending::<()>().await;
            }
        }));
        Ok(Self { addr, state, stop, task })
    }

    pub fn url(&self) -> String {
        let scheme = if self.state.config.tls.is_some() { "https" } else { "http" };
        format!("{scheme}://{}", self.addr)
    }

    /// Stops serving and the loops, and writes a final checkpoint of every job.
    pub async fn shutdown(self) -> anyhow::Result<()> {
        let _ = self.stop.send(());
        self.task.await?
    }

    /// Serves until the process gets SIGINT or SIGTERM, then shuts down as [`Server::shutdown`].
    pub async fn run_until_signal(self) -> anyhow::Result<()> {
        shutdown_signal().await;
        self.shutdown().await
    }
}

/// Serves the API on `listener` with the background loops (lease expiry and maintenance,
/// progressive output, checkpoints, webhooks) until `shutdown` resolves; then stops accepting,
/// stops the loops and writes a final checkpoint of every job, so nothing merged is lost.
pub async fn run(
    listener: tokio::net::TcpListener,
    state: Arc<AppState>,
    shutdown: impl std::future::Future<Output = ()>,
) -> anyhow::Result<()> {
    let tls = tls_acceptor(&state.config)?;
    serve(listener, state, tls, shutdown).await
}

fn tls_acceptor(config: &ServerConfig) -> anyhow::Result<Option<tokio_rustls::TlsAcceptor>> {
    Ok(match &config.tls {
        Some((cert, key)) => Some(crate::http::conn::tls_acceptor(cert, key)?),
        None => None,
    })
}

async fn serve(
    listener: tokio::net::TcpListener,
    state: Arc<AppState>,
    tls: Option<tokio_rustls::TlsAcceptor>,
    shutdown: impl std::future::Future<Output = ()>,
) -> anyhow::Result<()> {
    use crate::service::{loops, outputs, webhook};
    let addr = listener.local_addr()?;
    let app = crate::http::router(state.clone());
    let mut limits = state.config.conn;
    limits.max_connections = crate::http::conn::fit_to_fd_limit(limits.max_connections);
    let scheme = if tls.is_some() { "https" } else { "http" };
    let tasks = [
        tokio::spawn(loops::maintenance_loop(state.clone())),
        tokio::spawn(outputs::output_loop(state.clone())),
        tokio::spawn(loops::checkpoint_loop(state.clone())),
        tokio::spawn(crate::service::residency::residency_loop(state.clone())),
        tokio::spawn(webhook::run(state.clone())),
        tokio::spawn(crate::http::conn::serve(listener, app, limits, state.clone(), tls)),
    ];
    tracing::info!(
        %addr,
        data_dir = %state.config.data_dir.display(),
        max_connections = limits.max_connections,
        header_timeout_ms = limits.header_timeout.as_millis() as u64,
        idle_timeout_ms = limits.idle_timeout.as_millis() as u64,
        scheme,
        "coordinator listening"
    );
    shutdown.await;
    tracing::info!("shutting down");
    for t in &tasks {
        t.abort();
    }
    for t in tasks {
        let _ = t.await;
    }
    let st = state.clone();
    let jobs = tokio::task::spawn_blocking(move || loops::checkpoint_all(&st)).await?;
    tracing::info!(jobs, "final checkpoint written");
    Ok(())
}

/// Resolves on SIGINT or SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        () = ctrl_c => {},
        () = term => {},
    }
}
