//! Canopy: an out-of-core streaming renderer. This crate holds the importers, the archive
//! builder and the command-line front end; `canopy-format` holds the on-disk format.

pub mod build;
pub mod import;
pub mod inspect;
pub mod progress;
pub mod units;
