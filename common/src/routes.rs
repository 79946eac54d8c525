//! Every URL path of the coordinator, defined once.
//!
//! The router registers these templates (`{id}` segments are axum's path parameters), the
//! handlers' `#[utoipa::path]` attributes document them, and the clients (the worker daemon, the
//! `pathfarm` CLI, the load tool) fill them with [`fill`]. API paths are relative to
//! [`API`](crate::protocol::API); the others are served at the root.
//!
//! `coordinator/tests/openapi.rs` reads the router's `.route(routes::NAME, ...)` calls and looks
//! the names up in [`ALL`], so a route added here and registered there must also be documented.

use std::fmt::Display;

macro_rules! paths {
    ($($(#[$meta:meta])* $name:ident = $path:literal;)*) => {
        $($(#[$meta])* pub const $name: &str = $path;)*
        /// `(name, template)` of every path above, for tests that read the router's source.
        pub const ALL: &[(&str, &str)] = &[$((stringify!($name), $path)),*];
    };
}

paths! {
    // Clients (`require_client`).
    /// `POST`: upload a scene (GLB or a bundle).
    SCENES = "/scenes";
    /// `GET` (clients and workers): download a scene; `DELETE`: remove an unused one.
    SCENE = "/scenes/{id}";
    /// `POST`: submit a job; `GET`: list jobs (paged).
    JOBS = "/jobs";
    /// `GET`: a job's info; `DELETE`: remove it and its outputs.
    JOB = "/jobs/{id}";
    JOB_CANCEL = "/jobs/{id}/cancel";
    JOB_PAUSE = "/jobs/{id}/pause";
    JOB_RESUME = "/jobs/{id}/resume";
    JOB_PRIORITY = "/jobs/{id}/priority";
    JOB_LOG = "/jobs/{id}/log";
    JOB_TILES = "/jobs/{id}/tiles";
    JOB_EXR = "/jobs/{id}/image.exr";
    JOB_PNG = "/jobs/{id}/preview.png";
    JOB_FRAMES = "/jobs/{id}/frames";
    FRAME_EXR = "/jobs/{id}/frames/{frame}/image.exr";
    FRAME_PNG = "/jobs/{id}/frames/{frame}/preview.png";
    /// The dashboard's convergence plot of a job.
    JOB_CONVERGENCE = "/jobs/{id}/convergence";
    WORKERS = "/workers";
    // Workers (`require_worker`).
    WORKER_REGISTER = "/workers/register";
    WORKER_HEARTBEAT = "/workers/{id}/heartbeat";
    WORKER_LEASE = "/workers/{id}/lease";
    LEASE_RESULT = "/leases/{id}/result";
    LEASE_RELEASE = "/leases/{id}/release";
    /// `GET`: a denoise step's input (colour, albedo, normal of the frame).
    LEASE_DENOISE_INPUT = "/leases/{id}/denoise-input";
    /// `PUT`: a denoise step's output (the `denoised` layer).
    LEASE_DENOISED = "/leases/{id}/denoised";
    // Own authentication or none.
    EVENTS = "/events";
    OPENAPI = "/openapi.json";
    // At the root, outside the API.
    HEALTHZ = "/healthz";
    METRICS = "/metrics";
    DASHBOARD = "/";
    DASHBOARD_SCRIPT = "/dashboard/app.js";
    DASHBOARD_STYLE = "/dashboard/style.css";
    DASHBOARD_ICON = "/dashboard/icon.svg";
}

/// `template` with its `{name}` segments replaced by `args`, in order: `fill(JOB_CANCEL, &[&7])`
/// is `/jobs/7/cancel`. Panics when the counts differ (a programming error, caught by tests).
pub fn fill(template: &str, args: &[&dyn Display]) -> String {
    let mut out = String::with_capacity(template.len() + 16);
    let mut args = args.iter();
    let mut rest = template;
    while let Some(open) = rest.find('{') {
        let close = rest[open..].find('}').map_or(rest.len(), |c| open + c);
        out.push_str(&rest[..open]);
        let arg = args.next().unwrap_or_else(|| panic!("too few arguments for {template}"));
        out.push_str(&arg.to_string());
        rest = &rest[(close + 1).min(rest.len())..];
    }
    out.push_str(rest);
    assert!(args.next().is_none(), "too many arguments for {template}");
    out
}

/// The number of `{name}` segments of a template.
pub fn params(template: &str) -> usize {
    template.matches('{').count()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fill_replaces_segments_in_order() {
        assert_eq!(fill(JOB_CANCEL, &[&7]), "/jobs/7/cancel");
        assert_eq!(fill(FRAME_EXR, &[&3, &-12]), "/jobs/3/frames/-12/image.exr");
        assert_eq!(fill(JOBS, &[]), "/jobs");
    }

    #[test]
    #[should_panic(expected = "too few arguments")]
    fn fill_refuses_missing_arguments() {
        fill(FRAME_PNG, &[&1]);
    }

    #[test]
    fn templates_are_distinct_well_formed_paths() {
        let mut seen = std::collections::BTreeSet::new();
        for (name, path) in ALL {
            assert!(path.starts_with('/'), "{name}: {path}");
            assert!(seen.insert(*path), "{name}: {path} defined twice");
            assert_eq!(path.matches('{').count(), path.matches('}').count(), "{name}: {path}");
            let filled = fill(path, &vec![&0 as &dyn Display; params(path)]);
            assert!(!filled.contains('{') && !filled.contains('}'), "{name}: {filled}");
        }
    }
}
