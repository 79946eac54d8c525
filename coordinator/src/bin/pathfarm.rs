//! `pathfarm`: the client CLI.

fn main() {}
