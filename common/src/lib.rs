//! Shared code of pathfarm: the scene model and its glTF loader, the job plan (tiles x passes),
//! the film (exact fixed-point tile sums, merge, EXR/PNG encoding) and the wire protocol.
//!
//! Nothing here renders and nothing here is async: the worker and the coordinator both build on it.

pub mod adaptive;
pub mod assembly;
pub mod film;
pub mod frames;
pub mod job;
pub mod protocol;
pub mod routes;
pub mod scene;
