//! The radiance sidecar (`canopy bake`): per node of an archive, the light it reflects,
//! stored as one zstd block per archive page so a renderer pages it with the nodes. The
//! header names the archive by its header checksum (which covers, through the table
//! checksum, every page's checksum), so a bake never pairs with another archive. Layout in
//! `FORMAT.md`, "The radiance file".

use crate::atomic::{io, AtomicFile};
use crate::error::{FormatError, Result};
use crate::reader::Archive;
use bytemuck::{Pod, Zeroable};
use std::fs::File;
use std::path::{Path, PathBuf};

pub const RADIANCE_MAGIC: [u8; 8] = *b"CNPYRAD\x1a";
pub const RADIANCE_VERSION_MAJOR: u16 = 1;
pub const RADIANCE_VERSION_MINOR: u16 = 0;

/// What a node shows along each cube axis (+x, −x, +y, −y, +z, −z): projected area and
/// reflected power (radiance times projected area) over its triangles.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct BakedNode {
    pub area: [f32; 6],
    pub power: [[f32; 3]; 6],
}

const _: () = assert!(std::mem::size_of::<BakedNode>() == 96);

/// The 128-byte header at offset 0.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct RadianceHeader {
    pub magic: [u8; 8],
    pub version_major: u16,
    pub version_minor: u16,
    pub header_size: u32,
    /// The archive's `header_checksum` and `file_len`: its identity.
    pub archive_checksum: u64,
    pub archive_len: u64,
    pub nodes: u64,
    pub pages: u32,
    pub record_size: u32,
    pub bounces: u32,
    pub samples_per_triangle: u32,
    pub seed: u32,
    pub flags: u32,
    pub file_len: u64,
    pub blocks_offset: u64,
    /// xxh3-64 of the block table.
    pub blocks_checksum: u64,
    /// Bytes of wavelet coefficients (0 in version 1.0).
    pub coef_bytes: u64,
    /// xxh3-64 of this header with this field zeroed.
    pub header_checksum: u64,
    pub reserved: [u8; 24],
}

const _: () = assert!(std::mem::size_of::<RadianceHeader>() == 128);

/// Where archive page i's block lies (32 bytes; entry i of the table).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct BlockEntry {
    pub offset: u64,
    pub compressed_len: u32,
    pub raw_len: u32,
    /// xxh3-64 of the compressed bytes.
    pub checksum: u64,
    pub node_count: u32,
    pub reserved: u32,
}

const _: () = assert!(std::mem::size_of::<BlockEntry>() == 32);

/// How the light was baked, recorded in the header.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BakeInfo {
    pub bounces: u32,
    pub samples_per_triangle: u32,
    pub seed: u32,
}

/// Writes a radiance file block by block, in any page order; like the archive writer it
/// leaves nothing at the output path unless `finish` succeeds.
pub struct RadianceWriter {
    out: AtomicFile,
    path: PathBuf,
    header: RadianceHeader,
    blocks: Vec<BlockEntry>,
    written: Vec<bool>,
}

impl RadianceWriter {
    /// A file that will appear at `path`.
    pub fn create(path: &Path, archive: &Archive, info: BakeInfo) -> Result<RadianceWriter> {
        Self::start(AtomicFile::create(path, 128)?, path, archive, info)
    }

    /// An unnamed scratch file, for a bake made inside a render.
    pub fn temporary(archive: &Archive, info: BakeInfo) -> Result<RadianceWriter> {
        let what = Path::new("(temporary bake)");
        Self::start(AtomicFile::anonymous(what, 128)?, what, archive, info)
    }

    fn start(
        out: AtomicFile,
        path: &Path,
        archive: &Archive,
        info: BakeInfo,
    ) -> Result<RadianceWriter> {
        let header = RadianceHeader {
            magic: RADIANCE_MAGIC,
            version_major: RADIANCE_VERSION_MAJOR,
            version_minor: RADIANCE_VERSION_MINOR,
            header_size: 128,
            archive_checksum: archive.header.header_checksum,
            archive_len: archive.header.file_len,
            nodes: archive.header.nodes,
            pages: archive.pages.len() as u32,
            record_size: std::mem::size_of::<BakedNode>() as u32,
            bounces: info.bounces,
            samples_per_triangle: info.samples_per_triangle,
            seed: info.seed,
            flags: 0,
            file_len: 0,
            blocks_offset: 0,
            blocks_checksum: 0,
            coef_bytes: 0,
            header_checksum: 0,
            reserved: [0; 24],
        };
        let blocks = archive
            .pages
            .iter()
            .map(|p| BlockEntry {
                node_count: p.node_count,
                ..BlockEntry::default()
            })
            .collect();
        Ok(RadianceWriter {
            out,
            path: path.to_path_buf(),
            header,
            blocks,
            written: vec![false; archive.pages.len()],
        })
    }

    fn misuse(&self, what: String) -> FormatError {
        FormatError::BadRadiance {
            path: self.path.clone(),
            what,
        }
    }

    /// Appends page `page`'s nodes (one record per node, in page order).
    pub fn push(&mut self, page: u32, nodes: &[BakedNode]) -> Result<()> {
        let i = page as usize;
        match self.blocks.get(i) {
            Some(b) if b.node_count as usize == nodes.len() && !self.written[i] => {}
            _ => {
                return Err(self.misuse(format!(
                "block for page {page} ({} nodes) does not fit the archive or was written twice",
                nodes.len()
            )))
            }
        }
        let raw: &[u8] = bytemuck::cast_slice(nodes);
        let packed = zstd::bulk::compress(raw, 3).map_err(io(&self.path))?;
        self.blocks[i] = BlockEntry {
            offset: self.out.len(),
            compressed_len: packed.len() as u32,
            raw_len: raw.len() as u32,
            checksum: xxhash_rust::xxh3::xxh3_64(&packed),
            node_count: nodes.len() as u32,
            reserved: 0,
        };
        self.written[i] = true;
        self.out.write_all(&packed)
    }

    /// Writes the block table and the header and names the file; returns it open.
    pub fn finish(mut self) -> Result<File> {
        if let Some(i) = self.written.iter().position(|w| !w) {
            return Err(self.misuse(format!("no block was written for page {i}")));
        }
        let table: &[u8] = bytemuck::cast_slice(&self.blocks);
        let mut h = self.header;
        h.blocks_offset = self.out.len();
        h.file_len = h.blocks_offset + table.len() as u64;
        h.blocks_checksum = xxhash_rust::xxh3::xxh3_64(table);
        h.header_checksum = xxhash_rust::xxh3::xxh3_64(bytemuck::bytes_of(&h));
        let table = table.to_vec();
        self.out.write_all(&table)?;
        self.out.commit(bytemuck::bytes_of(&h))
    }
}

/// An open radiance file checked against its archive; blocks are read on demand.
pub struct RadianceFile {
    path: PathBuf,
    file: File,
    pub header: RadianceHeader,
    pub blocks: Vec<BlockEntry>,
}

impl RadianceFile {
    pub fn open(path: &Path, archive: &Archive) -> Result<RadianceFile> {
        let meta = std::fs::metadata(path).map_err(io(path))?;
        if !meta.is_file() {
            return Err(FormatError::BadRadiance {
                path: path.to_path_buf(),
                what: "not a regular file".into(),
            });
        }
        let file = File::open(path).map_err(io(path))?;
        RadianceFile::from_file(file, path, archive)
    }

    /// Checks the header, the identity, the table and every block's checksum (one read of
    /// the file, a block at a time); blocks are decoded and their values checked on demand.
    pub fn from_file(file: File, path: &Path, archive: &Archive) -> Result<RadianceFile> {
        let bad = |what: String| FormatError::BadRadiance {
            path: path.to_path_buf(),
            what,
        };
        let len = file.metadata().map_err(io(path))?.len();
        let mut head = [0u8; 128];
        let got = read_at(&file, &mut head, 0, len);
        if got.min(8) < 8 || head[..8] != RADIANCE_MAGIC {
            return Err(FormatError::NotRadiance {
                path: path.to_path_buf(),
            });
        }
        if got < 128 {
            return Err(bad(format!(
                "truncated: the 128-byte header, file has {len} bytes"
            )));
        }
        let h: RadianceHeader = bytemuck::pod_read_unaligned(&head);
        if h.version_major != RADIANCE_VERSION_MAJOR {
            return Err(bad(format!(
                "version {}.{}; this canopy reads {RADIANCE_VERSION_MAJOR}.x",
                h.version_major, h.version_minor
            )));
        }
        let mut zeroed = h;
        zeroed.header_checksum = 0;
        if xxhash_rust::xxh3::xxh3_64(bytemuck::bytes_of(&zeroed)) != h.header_checksum {
            return Err(bad("header checksum mismatch".into()));
        }
        if h.file_len != len {
            return Err(bad(format!(
                "truncated or extended: the header says {} bytes, the file has {len}",
                h.file_len
            )));
        }
        check_header(&h).map_err(bad)?;
        let wrong = |what: String| FormatError::WrongArchive {
            path: path.to_path_buf(),
            archive: archive.path().to_path_buf(),
            what,
        };
        let a = &archive.header;
        if (h.archive_checksum, h.archive_len) != (a.header_checksum, a.file_len) {
            return Err(wrong(format!(
                "archive checksum {:016x} and length {}, not {:016x} and {}",
                h.archive_checksum, h.archive_len, a.header_checksum, a.file_len
            )));
        }
        if (h.nodes, h.pages as usize) != (a.nodes, archive.pages.len()) {
            return Err(wrong(format!(
                "{} nodes in {} pages, not {} in {}",
                h.nodes,
                h.pages,
                a.nodes,
                archive.pages.len()
            )));
        }
        let blocks = read_blocks(&file, &h).map_err(bad)?;
        let mut packed = Vec::new();
        for (i, (b, p)) in blocks.iter().zip(&archive.pages).enumerate() {
            check_block(b, h.blocks_offset, p.node_count)
                .map_err(|what| bad(format!("block {i}: {what}")))?;
            packed.resize(b.compressed_len as usize, 0);
            if read_at(&file, &mut packed, b.offset, len) < packed.len()
                || xxhash_rust::xxh3::xxh3_64(&packed) != b.checksum
            {
                return Err(bad(format!("block {i}: checksum mismatch")));
            }
        }
        Ok(RadianceFile {
            path: path.to_path_buf(),
            file,
            header: h,
            blocks,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Page `page`'s records: checksum, exact decompressed size, finite non-negative values.
    pub fn read_block(&self, page: u32) -> Result<Vec<BakedNode>> {
        let bad = |what: String| FormatError::BadRadiance {
            path: self.path.clone(),
            what: format!("block {page}: {what}"),
        };
        let b = self
            .blocks
            .get(page as usize)
            .ok_or_else(|| bad("no such page".into()))?;
        let mut packed = vec![0u8; b.compressed_len as usize];
        if read_at(&self.file, &mut packed, b.offset, self.header.file_len) < packed.len() {
            return Err(bad("the file is shorter than its table says".into()));
        }
        if xxhash_rust::xxh3::xxh3_64(&packed) != b.checksum {
            return Err(bad("checksum mismatch".into()));
        }
        let mut nodes = vec![BakedNode::default(); b.node_count as usize];
        let raw: &mut [u8] = bytemuck::cast_slice_mut(&mut nodes);
        match zstd::bulk::decompress_to_buffer(&packed, raw) {
            Ok(n) if n == raw.len() => {}
            Ok(n) => {
                return Err(bad(format!(
                    "{n} bytes after decompression, not {}",
                    b.raw_len
                )))
            }
            Err(e) => return Err(bad(format!("does not decompress: {e}"))),
        }
        for (k, n) in nodes.iter().enumerate() {
            let ok = |v: f32| v.is_finite() && v >= 0.0;
            if !n.area.iter().copied().all(ok) || !n.power.iter().flatten().copied().all(ok) {
                return Err(bad(format!("node {k}: a negative or non-finite value")));
            }
        }
        Ok(nodes)
    }
}

/// Reads up to `buf.len()` bytes at `offset` of a file `len` long; returns how many.
fn read_at(file: &File, buf: &mut [u8], offset: u64, len: u64) -> usize {
    use std::os::unix::fs::FileExt;
    let n = (len.saturating_sub(offset)).min(buf.len() as u64) as usize;
    match file.read_exact_at(&mut buf[..n], offset) {
        Ok(()) => n,
        Err(_) => 0,
    }
}

fn check_header(h: &RadianceHeader) -> std::result::Result<(), String> {
    let table = h.pages as u64 * std::mem::size_of::<BlockEntry>() as u64;
    if h.header_size != 128 {
        return Err(format!("header size {}, not 128", h.header_size));
    }
    if h.record_size as usize != std::mem::size_of::<BakedNode>() {
        return Err(format!("record size {}, not 96", h.record_size));
    }
    if h.flags != 0 || h.coef_bytes != 0 || h.reserved != [0; 24] {
        return Err("flags, coefficient bytes or reserved bytes set (version 1.0 has none)".into());
    }
    if h.blocks_offset < 128 || h.blocks_offset.checked_add(table) != Some(h.file_len) {
        return Err(format!(
            "the block table at {} for {} pages does not end the file",
            h.blocks_offset, h.pages
        ));
    }
    Ok(())
}

fn read_blocks(file: &File, h: &RadianceHeader) -> std::result::Result<Vec<BlockEntry>, String> {
    let mut blocks = vec![BlockEntry::default(); h.pages as usize];
    let raw: &mut [u8] = bytemuck::cast_slice_mut(&mut blocks);
    if read_at(file, raw, h.blocks_offset, h.file_len) < raw.len() {
        return Err("the block table cannot be read".into());
    }
    if xxhash_rust::xxh3::xxh3_64(raw) != h.blocks_checksum {
        return Err("block table checksum mismatch".into());
    }
    Ok(blocks)
}

fn check_block(b: &BlockEntry, end: u64, nodes: u32) -> std::result::Result<(), String> {
    if b.node_count != nodes {
        return Err(format!(
            "{} nodes, the archive's page has {nodes}",
            b.node_count
        ));
    }
    if b.raw_len as u64 != nodes as u64 * std::mem::size_of::<BakedNode>() as u64 {
        return Err(format!("raw length {} for {nodes} nodes", b.raw_len));
    }
    if b.offset < 128 || b.offset + b.compressed_len as u64 > end || b.reserved != 0 {
        return Err(format!(
            "bytes {}..{} outside the block area 128..{end}",
            b.offset,
            b.offset + b.compressed_len as u64
        ));
    }
    Ok(())
}
