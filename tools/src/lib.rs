//! Helpers around Canopy that are not part of the renderer: the fuzz harness, the glb
//! container and the scene generators' random numbers.

pub mod fuzz;
pub mod glb;
pub mod jitter;
