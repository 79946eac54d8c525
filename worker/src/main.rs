//! `pathfarm-worker`: render a scene locally, or run as a farm worker daemon.

fn main() {}
