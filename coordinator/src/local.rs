//! Workers inside the coordinator's process (`--local-workers N`, the demo). They are the same
//! daemon as `pathfarm-worker run` and talk to the coordinator over real HTTP on loopback.

use pathfarm_worker::daemon::{Daemon, DaemonConfig};
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::Duration;

/// Running local workers; stopped (and joined) by [`LocalWorkers::stop`] or on drop.
pub struct LocalWorkers {
    shutdown: Arc<AtomicBool>,
    handles: Vec<JoinHandle<()>>,
}

impl LocalWorkers {
    /// Starts `count` workers that share the machine's cores.
    pub fn start(url: &str, token: Option<String>, count: usize, cache_dir: &Path) -> anyhow::Result<Self> {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        let threads = (cores / count.max(1)).max(1);
        let shutdown = Arc::new(AtomicBool::new(false));
        let mut handles = Vec::new();
        for i in 0..count {
            let cfg = DaemonConfig {
                coordinator: url.trim_end_matches('/').to_string(),
                token: token.clone(),
                threads,
                cache_dir: cache_dir.to_path_buf(),
                cache_max_bytes: 4 << 30,
                name: format!("local-{i}"),
                lease_wait: Duration::from_millis(500),
                tags: pathfarm_worker::daemon::automatic_tags(),
                ca_cert: None,
            };
            let mut daemon = Daemon::new(cfg)?;
            let flag = shutdown.clone();
            handles.push(std::thread::Builder::new().name(format!("local-worker-{i}")).spawn(move || {
                if let Err(e) = daemon.run(&flag) {
                    tracing::error!(worker = i, "local worker stopped: {e:#}");
                }
            })?);
        }
        tracing::info!(count, threads, "local workers started");
        Ok(Self { shutdown, handles })
    }

    pub fn stop(&mut self) {
        self.shutdown.store(true, Ordering::Relaxed);
        for h in self.handles.drain(..) {
            let _ = h.join();
        }
    }
}

impl Drop for LocalWorkers {
    fn drop(&mut self) {
        self.stop();
    }
}
