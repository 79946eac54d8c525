//! The renderer. Pure: no async, no I/O, no global state. Everything a unit computes is a
//! function of (scene, settings, tile, sample range).

pub mod bsdf;
pub mod geometry;
pub mod microfacet;
pub mod sampler;
pub mod sampling;
