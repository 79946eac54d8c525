//! The top floor: binds the listener, wires the service's loops and the HTTP router together,
//! and runs them until shutdown.

pub use crate::service::{AppState, Auth, SCENE_GC_AFTER_MS, ServerConfig};
use pathfarm_common::film::write_atomic;
use std::net::SocketAddr;
use std::sync::Arc;

/// A running coordinator.
pub struct Server {
    pub addr: SocketAddr,
    pub state: Arc<AppState>,
    task: tokio::task::JoinHandle<()>,
}

impl Server {
    /// Binds, starts the background loops and serves until dropped or the task ends.
    pub async fn start(config: ServerConfig) -> anyhow::Result<Self> {
        let state = Arc::new(AppState::new(config.clone())?);
        let listener = tokio::net::TcpListener::bind(config.listen).await?;
        let addr = listener.local_addr()?;
        write_atomic(&config.data_dir.join("coordinator.addr"), addr.to_string().as_bytes())?;
        tokio::spawn(crate::service::loops::maintenance_loop(state.clone()));
        tokio::spawn(crate::service::outputs::output_loop(state.clone()));
        tokio::spawn(crate::service::loops::checkpoint_loop(state.clone()));
        tokio::spawn(crate::service::webhook::run(state.clone()));
        let tls = match &config.tls {
            Some((cert, key)) => Some(crate::http::conn::tls_acceptor(cert, key)?),
            None => None,
        };
        let app = crate::http::router(state.clone());
        let mut limits = config.conn;
        limits.max_connections = crate::http::conn::fit_to_fd_limit(limits.max_connections);
        let scheme = if tls.is_some() { "https" } else { "http" };
        let task = tokio::spawn(crate::http::conn::serve(listener, app, limits, state.clone(), tls));
        tracing::info!(
            %addr,
            data_dir = %config.data_dir.display(),
            max_connections = limits.max_connections,
            header_timeout_ms = limits.header_timeout.as_millis() as u64,
            idle_timeout_ms = limits.idle_timeout.as_millis() as u64,
            scheme,
            "coordinator listening"
        );
        Ok(Self { addr, state, task })
    }

    pub fn url(&self) -> String {
        let scheme = if self.state.config.tls.is_some() { "https" } else { "http" };
        format!("{scheme}://{}", self.addr)
    }

    /// Serves until the process gets SIGINT or SIGTERM.
    pub async fn run_until_signal(self) -> anyhow::Result<()> {
        shutdown_signal().await;
        tracing::info!("shutting down");
        self.task.abort();
        Ok(())
    }
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
