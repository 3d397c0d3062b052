//! The Canopy node archive: byte-exact records (see `FORMAT.md`), encodings, a writer that
//! never leaves a half-written file at its target path, and a bounds-checked mmap reader.

#[cfg(not(target_endian = "little"))]
compile_error!(
    "the archive format is little-endian and read by casting; big-endian hosts are not supported"
);

pub mod atomic;
pub mod bake;
pub mod bake_parts;
pub mod codec;
pub mod error;
pub mod node;
pub mod reader;
pub mod records;
pub mod validate;
mod validate_page;
pub mod verify;
pub mod writer;

pub use codec::Grid;
pub use error::{FormatError, Result};
pub use node::{Node, NodeFlags, Tri};
pub use reader::Archive;
pub use records::*;
pub use verify::PageReport;
pub use writer::{
    encode_page, encode_tile, renumber_page, ArchiveWriter, EncodedPage, EncodedTile, PageContents,
    PageMeta, SceneInfo, Streams, WriterState,
};
