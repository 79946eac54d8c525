//! pathfarm coordinator: REST API, scheduler, merger, store and dashboard.
