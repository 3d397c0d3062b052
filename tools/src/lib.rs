//! Helpers around Canopy that are not part of the renderer: the fuzz harness and the glb
//! container.

pub mod fuzz;
pub mod glb;
