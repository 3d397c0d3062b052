//! Helpers around Canopy that are not part of the renderer: the fuzz harness.

pub mod fuzz;
