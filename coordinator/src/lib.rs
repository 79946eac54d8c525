//! pathfarm coordinator: the REST API, the farm state machine (scheduler and merger), scene
//! storage, progressive output, the web dashboard, local workers, the demo and the client.

pub mod api;
pub mod client;
pub mod conn;
pub mod dashboard;
pub mod demo;
pub mod events;
pub mod farm;
pub mod local;
pub mod openapi;
pub mod server;
pub mod store;
pub mod webhook;
