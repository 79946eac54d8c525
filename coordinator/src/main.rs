//! `pathfarm-coordinator`: the service.

fn main() {}
