//! Counters and histograms, and the Prometheus exposition.

use super::*;

/// Latency histogram buckets in seconds (Prometheus `le`).
const BUCKETS: [f64; 10] = [0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1];

#[derive(Default)]
pub struct Histogram {
    counts: [AtomicU64; BUCKETS.len() + 1],
    sum_ns: AtomicU64,
}

impl Histogram {
    pub fn observe(&self, d: Duration) {
        let s = d.as_secs_f64();
        let i = BUCKETS.iter().position(|&b| s <= b).unwrap_or(BUCKETS.len());
        self.counts[i].fetch_add(1, Ordering::Relaxed);
        self.sum_ns.fetch_add(d.as_nanos() as u64, Ordering::Relaxed);
    }

    fn render(&self, name: &str, help: &str, out: &mut String) {
        use std::fmt::Write;
        let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} histogram");
        let mut cum = 0;
        for (i, b) in BUCKETS.iter().enumerate() {
            cum += self.counts[i].load(Ordering::Relaxed);
            let _ = writeln!(out, "{name}_bucket{{le=\"{b}\"}} {cum}");
        }
        cum += self.counts[BUCKETS.len()].load(Ordering::Relaxed);
        let _ = writeln!(out, "{name}_bucket{{le=\"+Inf\"}} {cum}");
        let _ = writeln!(out, "{name}_sum {}", self.sum_ns.load(Ordering::Relaxed) as f64 * 1e-9);
        let _ = writeln!(out, "{name}_count {cum}");
    }
}

#[derive(Default)]
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
    pub merge_latency: Histogram,
    pub lease_latency: Histogram,
}

impl Metrics {
    pub fn observe_merge(&self, d: Duration) {
        self.merge_latency.observe(d);
    }
    pub fn observe_lease(&self, d: Duration) {
        self.lease_latency.observe(d);
    }
}

impl AppState {
    /// Prometheus text exposition.
    pub fn metrics_text(&self) -> String {
        use std::fmt::Write;
        let mut out = String::new();
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
        let _ = writeln!(out, "# HELP pathfarm_jobs Jobs by state.\n# TYPE pathfarm_jobs gauge");
        for s in ["queued", "running", "paused", "completed", "failed", "cancelled"] {
            let _ = writeln!(out, "pathfarm_jobs{{state=\"{s}\"}} {}", states.get(s).copied().unwrap_or(0));
        }
        let _ = writeln!(out, "# HELP pathfarm_workers Workers by state.\n# TYPE pathfarm_workers gauge");
        for s in ["idle", "busy", "offline"] {
            let _ = writeln!(out, "pathfarm_workers{{state=\"{s}\"}} {}", workers.get(s).copied().unwrap_or(0));
        }
        let counters = [
            ("pathfarm_units_leased_total", "Units handed out.", c.units_leased),
            ("pathfarm_units_merged_total", "Units merged into films.", c.units_merged),
            ("pathfarm_units_failed_total", "Units reported failed by workers.", c.units_failed),
            ("pathfarm_leases_expired_total", "Leases that expired.", c.leases_expired),
            (
                "pathfarm_results_rejected_total",
                "Results refused (lost lease, corrupt, mismatched).",
                c.results_rejected,
            ),
            ("pathfarm_samples_total", "Pixel samples merged.", c.samples_merged),
            (
                "pathfarm_bytes_received_total",
                "Request body bytes received (scenes and results).",
                self.metrics.bytes_received.load(Ordering::Relaxed),
            ),
            (
                "pathfarm_connections_timed_out_total",
                "Connections closed by the header or idle timeout.",
                self.metrics.connections_timed_out.load(Ordering::Relaxed),
            ),
            (
                "pathfarm_connections_evicted_total",
                "Quiet connections closed to make room under --max-connections.",
                self.metrics.connections_evicted.load(Ordering::Relaxed),
            ),
            (
                "pathfarm_connections_refused_total",
                "New connections closed at --max-connections with every connection busy.",
                self.metrics.connections_refused.load(Ordering::Relaxed),
            ),
        ];
        for (name, help, v) in counters {
            let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} counter\n{name} {v}");
        }
        let _ = writeln!(
            out,
            "# HELP pathfarm_leases_held Leases currently held.\n# TYPE pathfarm_leases_held gauge\npathfarm_leases_held {leases}"
        );
        let _ = writeln!(
            out,
            "# HELP pathfarm_connections_open Open TCP connections.\n# TYPE pathfarm_connections_open gauge\npathfarm_connections_open {}",
            self.metrics.connections_open.load(Ordering::Relaxed)
        );
        self.metrics.merge_latency.render("pathfarm_merge_seconds", "Time to decode and merge a result.", &mut out);
        self.metrics.lease_latency.render("pathfarm_lease_seconds", "Time to pick a unit for a lease.", &mut out);
        out
    }
}
