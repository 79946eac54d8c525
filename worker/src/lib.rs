//! pathfarm worker: the renderer (`render`, pure: no async, no I/O) and the worker daemon.

pub mod cli;
pub mod daemon;
pub mod denoise;
pub mod render;
