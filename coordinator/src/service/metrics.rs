//! Counters and histograms, and the Prometheus exposition through `prometheus-client` (the
//! Prometheus project's Rust client): OpenMetrics text, with the standard `process_*` metrics on
//! Linux.
//!
//! The request-path counters stay plain atomics (the HTTP floor bumps them); the farm's counts
//! and states are read under its lock once per scrape. Each scrape registers constant metrics
//! holding those values, and clones of the two latency histograms, into a fresh registry that
//! the crate encodes, so names, `# TYPE` lines and escaping are the crate's, not ours.

use super::*;
use prometheus_client::encoding::text::encode;
use prometheus_client::metrics::counter::ConstCounter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::{ConstGauge, Gauge};
use prometheus_client::metrics::histogram::Histogram;
use prometheus_client::registry::Registry;

/// Latency histogram buckets in seconds (Prometheus `le`).
const BUCKETS: [f64; 10] = [0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1];

/// The `Content-Type` of [`AppState::metrics_text`].
pub const METRICS_CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

pub struct Metrics {
    pub bytes_received: AtomicU64,
    /// Open TCP connections.
    pub connections_open: AtomicU64,
    /// Connections closed by the header or idle timeout.
    pub connections_timed_out: AtomicU64,
    /// Quiet connections closed to make room under the connection cap.
    pub connections_evicted: AtomicU64,
    /// New connections closed because the cap was reached and every connection was busy.
    pub connections_refused: AtomicU64,
    merge_latency: Histogram,
    lease_latency: Histogram,
}

impl Default for Metrics {
    fn default() -> Self {
        Self {
            bytes_received: AtomicU64::new(0),
            connections_open: AtomicU64::new(0),
            connections_timed_out: AtomicU64::new(0),
            connections_evicted: AtomicU64::new(0),
            connections_refused: AtomicU64::new(0),
            merge_latency: Histogram::new(BUCKETS),
            lease_latency: Histogram::new(BUCKETS),
        }
    }
}

impl Metrics {
    pub fn observe_merge(&self, d: Duration) {
        self.merge_latency.observe(d.as_secs_f64());
    }
    pub fn observe_lease(&self, d: Duration) {
        self.lease_latency.observe(d.as_secs_f64());
    }
}

/// The standard process metrics of the Prometheus clients, read from `/proc/self`.
#[derive(Debug, Default, Clone, Copy, PartialEq)]
pub struct ProcessStats {
    pub resident_memory_bytes: u64,
    pub virtual_memory_bytes: u64,
    pub cpu_seconds: f64,
    pub open_fds: u64,
    /// The soft limit on open files; `None` when unlimited.
    pub max_fds: Option<u64>,
    pub start_time_seconds: f64,
}

impl ProcessStats {
    /// Reads this process's figures; `None` off Linux or when `/proc` is not mounted.
    pub fn read() -> Option<Self> {
        if !cfg!(target_os = "linux") {
            return None;
        }
        // Kernel clock ticks per second: USER_HZ, 100 on every Linux ABI (what the Go client's
        // procfs assumes as well).
        const TICKS: f64 = 100.0;
        let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
        // Fields after the command name, which is in parentheses and may hold spaces: the first
        // is field 3 (state), so field n is at index n - 3.
        let rest = &stat[stat.rfind(')')? + 1..];
        let f: Vec<&str> = rest.split_whitespace().collect();
        let field = |n: usize| f.get(n - 3).and_then(|v| v.parse::<u64>().ok());
        let (utime, stime, start_ticks) = (field(14)?, field(15)?, field(22)?);
        let status = std::fs::read_to_string("/proc/self/status").ok()?;
        let kb = |key: &str| {
            status.lines().find_map(|l| {
                l.strip_prefix(key)?.trim().strip_suffix("kB")?.trim().parse::<u64>().ok().map(|v| v * 1024)
            })
        };
        let boot: u64 = std::fs::read_to_string("/proc/stat")
            .ok()?
            .lines()
            .find_map(|l| l.strip_prefix("btime ")?.trim().parse().ok())?;
        let limits = std::fs::read_to_string("/proc/self/limits").ok()?;
        let max_fds = limits.lines().find(|l| l.starts_with("Max open files")).and_then(|l| {
            // "Max open files  <soft>  <hard>  files": the soft limit is the first number.
            l["Max open files".len()..].split_whitespace().next()?.parse().ok()
        });
        Some(Self {
            resident_memory_bytes: kb("VmRSS:")?,
            virtual_memory_bytes: kb("VmSize:")?,
            cpu_seconds: (utime + stime) as f64 / TICKS,
            open_fds: std::fs::read_dir("/proc/self/fd").ok()?.count() as u64,
            max_fds,
            start_time_seconds: boot as f64 + start_ticks as f64 / TICKS,
        })
    }

    fn register(&self, r: &mut Registry) {
        let p = *self;
        r.register(
            "process_resident_memory_bytes",
            "Resident memory size in bytes.",
            ConstGauge::new(p.resident_memory_bytes as i64),
        );
        r.register(
            "process_virtual_memory_bytes",
            "Virtual memory size in bytes.",
            ConstGauge::new(p.virtual_memory_bytes as i64),
        );
        r.register(
            "process_cpu_seconds",
            "Total user and system CPU time spent in seconds.",
            ConstCounter::new(p.cpu_seconds),
        );
        r.register("process_open_fds", "Number of open file descriptors.", ConstGauge::new(p.open_fds as i64));
        if let Some(max) = p.max_fds {
            r.register("process_max_fds", "Maximum number of open file descriptors.", ConstGauge::new(max as i64));
        }
        r.register(
            "process_start_time_seconds",
            "Start time of the process since unix epoch in seconds.",
            ConstGauge::new(p.start_time_seconds),
        );
    }
}

type StateFamily = Family<Vec<(&'static str, &'static str)>, Gauge>;

fn by_state(states: &HashMap<&'static str, u64>, all: &[&'static str]) -> StateFamily {
    let family = StateFamily::default();
    for &s in all {
        family.get_or_create(&vec![("state", s)]).set(states.get(s).copied().unwrap_or(0) as i64);
    }
    family
}

impl AppState {
    /// The OpenMetrics text exposition (`Content-Type` [`METRICS_CONTENT_TYPE`]).
    pub fn metrics_text(&self) -> String {
        let (states, workers, c, leases) = {
            let farm = self.farm.lock();
            let mut states: HashMap<&'static str, u64> = HashMap::new();
            for j in farm.jobs() {
                *states.entry(j.state.as_str()).or_default() += 1;
            }
            let mut workers: HashMap<&'static str, u64> = HashMap::new();
            for w in farm.workers(now_ms()) {
                let s = match w.state {
                    pathfarm_common::protocol::WorkerState::Idle => "idle",
                    pathfarm_common::protocol::WorkerState::Busy => "busy",
                    pathfarm_common::protocol::WorkerState::Offline => "offline",
                };
                *workers.entry(s).or_default() += 1;
            }
            (states, workers, farm.counters.clone(), farm.leases_held())
        };
        let m = &self.metrics;
        let load = |a: &AtomicU64| a.load(Ordering::Relaxed);
        let mut r = Registry::default();
        r.register(
            "pathfarm_jobs",
            "Jobs by state.",
            by_state(&states, &["queued", "running", "paused", "completed", "failed", "cancelled"]),
        );
        r.register("pathfarm_workers", "Workers by state.", by_state(&workers, &["idle", "busy", "offline"]));
        // Counters: the encoder appends `_total` to each name.
        let counters = [
            ("pathfarm_units_leased", "Units handed out.", c.units_leased),
            ("pathfarm_units_merged", "Units merged into films.", c.units_merged),
            ("pathfarm_units_failed", "Units reported failed by workers.", c.units_failed),
            ("pathfarm_leases_expired", "Leases that expired.", c.leases_expired),
            ("pathfarm_results_rejected", "Results refused (lost lease, corrupt, mismatched).", c.results_rejected),
            ("pathfarm_samples", "Pixel samples merged.", c.samples_merged),
            ("pathfarm_bytes_received", "Request body bytes received (scenes and results).", load(&m.bytes_received)),
            (
                "pathfarm_connections_timed_out",
                "Connections closed by the header or idle timeout.",
                load(&m.connections_timed_out),
            ),
            (
                "pathfarm_connections_evicted",
                "Quiet connections closed to make room under --max-connections.",
                load(&m.connections_evicted),
            ),
            (
                "pathfarm_connections_refused",
                "New connections closed at --max-connections with every connection busy.",
                load(&m.connections_refused),
            ),
        ];
        for (name, help, v) in counters {
            r.register(name, help, ConstCounter::new(v));
        }
        r.register("pathfarm_leases_held", "Leases currently held.", ConstGauge::new(leases as i64));
        r.register(
            "pathfarm_connections_open",
            "Open TCP connections.",
            ConstGauge::new(load(&m.connections_open) as i64),
        );
        r.register("pathfarm_merge_seconds", "Time to decode and merge a result.", m.merge_latency.clone());
        r.register("pathfarm_lease_seconds", "Time to pick a unit for a lease.", m.lease_latency.clone());
        if let Some(p) = ProcessStats::read() {
            p.register(&mut r);
        }
        let mut out = String::new();
        // Writing into a String cannot fail; an encoder error would be a bug in a metric type.
        if let Err(e) = encode(&mut out, &r) {
            tracing::error!("encoding metrics: {e}");
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn process_stats_are_read_on_linux() {
        let read = ProcessStats::read();
        if !cfg!(target_os = "linux") {
            assert_eq!(read, None);
            return;
        }
        let p = read.expect("/proc/self unreadable on Linux");
        assert!(p.resident_memory_bytes > 0 && p.virtual_memory_bytes >= p.resident_memory_bytes, "{p:?}");
        assert!(p.open_fds >= 3, "{p:?}"); // stdin, stdout, stderr at least
        let now = SystemTime::now().duration_since(UNIX_EPOCH).expect("clock").as_secs_f64();
        // Started in the past, and not before the year 2020.
        assert!(p.start_time_seconds <= now + 1.0 && p.start_time_seconds > 1.577e9, "{p:?} now {now}");
        assert!(p.max_fds.is_none_or(|m| m >= p.open_fds), "{p:?}");
    }
}
