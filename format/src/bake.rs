//! The bake file (`canopy bake`): per node of an archive, the light it reflects,
//! stored as one zstd block per archive page so a renderer pages it with the nodes. The
//! header names the archive by its header checksum (which covers, through the table
//! checksum, every page's checksum), so a bake never pairs with another archive. Layout in
//! `FORMAT.md`, "The bake file".

use crate::atomic::{io, AtomicFile};
use crate::error::{FormatError, Result};
use crate::reader::Archive;
use crate::records::PageEntry;
use bytemuck::{Pod, Zeroable};
use std::fs::File;
use std::path::{Path, PathBuf};

pub const RADIANCE_MAGIC: [u8; 8] = *b"CNPYRAD\x1a";
pub const RADIANCE_VERSION_MAJOR: u16 = 1;
pub const RADIANCE_VERSION_MINOR: u16 = 2;

/// What a node shows along each cube axis (+x, −x, +y, −y, +z, −z): projected area and
/// reflected power (radiance times projected area) over its triangles.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct BakedNode {
    pub area: [f32; 6],
    pub power: [[f32; 3]; 6],
}

const _: () = assert!(std::mem::size_of::<BakedNode>() == 96);

/// Deepest subdivision of a triangle into patches (4^6 = 4096 at the finest level).
pub const MAX_PATCH_DEPTH: u32 = 6;

/// Largest cube-face side of the glossy maps a file may declare (what `canopy bake` writes
/// at most).
pub const MAX_WAVELET_N: u32 = 32;

/// Values in a pyramid of depth k: levels 0..=k, 4^j at level j (level 0: the triangle).
pub fn pyramid_len(k: u32) -> u32 {
    ((1u32 << (2 * k + 2)) - 1) / 3
}

/// A node's stored coefficient vector (16 bytes): an average G or a detail D (000 §3.1),
/// its values `values[first..first + count]`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct CoefRecord {
    pub node: u32,
    pub kind: u32,
    pub first: u32,
    pub count: u32,
}

impl CoefRecord {
    pub const AVERAGE: u32 = 0;
    pub const DETAIL: u32 = 1;
}

/// One Haar coefficient (16 bytes): its index in the node's vector (face·n² + Haar
/// layout index) and its RGB value.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct CoefValue {
    pub index: u32,
    pub rgb: [f32; 3],
}

/// A page's wavelet coefficients (empty unless the bake stored glossy light).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CoefBlock {
    /// By node, ascending.
    pub records: Vec<CoefRecord>,
    pub values: Vec<CoefValue>,
}

impl CoefBlock {
    /// Bytes in a block: two counts, then the records and the values.
    pub fn bytes(&self) -> u64 {
        8 + 16 * (self.records.len() + self.values.len()) as u64
    }
}

/// One page's baked light.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BakedBlock {
    /// Per node, in page order.
    pub nodes: Vec<BakedNode>,
    /// Per triangle of the page: its subdivision depth k (0..=`MAX_PATCH_DEPTH`) in the
    /// top 4 bits and the offset of its pyramid in `patches` in the low 28.
    pub patch_of: Vec<u32>,
    /// Reflected radiance (RGB) per patch: each triangle's levels 0..=k in order, level j
    /// holding its 4^j midpoint-split patches by index (children of patch i are
    /// 4i..4i+3 of the next level).
    pub patches: Vec<[f32; 3]>,
    /// Glossy light, when the file has coefficients (`BakeHeader::wavelet_n` > 0).
    pub coefs: CoefBlock,
}

impl BakedBlock {
    /// Depth and pyramid offset of triangle `t`'s patches.
    pub fn patches_of(&self, t: usize) -> Option<(u32, usize)> {
        self.patch_of
            .get(t)
            .map(|&v| (v >> 28, (v & 0x0FFF_FFFF) as usize))
    }

    pub fn bytes(&self) -> u64 {
        (self.nodes.len() * 96 + self.patch_of.len() * 4 + self.patches.len() * 12) as u64
            + self.coefs.bytes()
    }
}

/// The 128-byte header at offset 0.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct BakeHeader {
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
    /// Bounces the records hold; `ALL_BOUNCES`: every one (walks ended by roulette).
    pub bounces: u32,
    pub samples_per_triangle: u32,
    pub seed: u32,
    pub patch_size: f32,
    pub file_len: u64,
    pub blocks_offset: u64,
    /// xxh3-64 of the block table.
    pub blocks_checksum: u64,
    /// Bytes of the blocks' coefficient sections, decompressed (0 without coefficients).
    pub coef_bytes: u64,
    /// xxh3-64 of this header with this field zeroed.
    pub header_checksum: u64,
    /// Texels per cube-face side of the glossy radiance maps; 0: no coefficients (1.1).
    pub wavelet_n: u32,
    /// The truncation threshold, relative per page (1.1).
    pub wavelet_threshold: f32,
    /// The environment the bake was lit by (1.2): `NO_ENVIRONMENT`, or an identity of the
    /// map as stored; 0 in files that record none (1.0, 1.1).
    pub environment: u64,
    pub reserved: [u8; 8],
}

/// `BakeHeader::bounces` of a bake holding every bounce.
pub const ALL_BOUNCES: u32 = 0;

/// `BakeHeader::environment` of a bake lit by no environment.
pub const NO_ENVIRONMENT: u64 = 1;

const _: () = assert!(std::mem::size_of::<BakeHeader>() == 128);

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
    pub patch_count: u32,
}

const _: () = assert!(std::mem::size_of::<BlockEntry>() == 32);

/// How the light was baked, recorded in the header.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BakeInfo {
    pub bounces: u32,
    pub samples_per_triangle: u32,
    pub seed: u32,
    /// Finest patch side as a fraction of the scene's diagonal.
    pub patch_size: f32,
    /// Texels per cube-face side of glossy radiance (0: none) and the relative threshold.
    pub wavelet_n: u32,
    pub wavelet_threshold: f32,
    /// The environment's identity (`BakeHeader::environment`).
    pub environment: u64,
}

/// Writes a bake file block by block, in any page order; like the archive writer it
/// leaves nothing at the output path unless `finish` succeeds.
pub struct RadianceWriter {
    out: AtomicFile,
    path: PathBuf,
    header: BakeHeader,
    blocks: Vec<BlockEntry>,
    tri_counts: Vec<u32>,
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
        let entries = archive.entries()?;
        let header = BakeHeader {
            magic: RADIANCE_MAGIC,
            version_major: RADIANCE_VERSION_MAJOR,
            version_minor: RADIANCE_VERSION_MINOR,
            header_size: 128,
            archive_checksum: archive.header.header_checksum,
            archive_len: archive.header.file_len,
            nodes: archive.header.nodes,
            pages: entries.len() as u32,
            record_size: std::mem::size_of::<BakedNode>() as u32,
            bounces: info.bounces,
            samples_per_triangle: info.samples_per_triangle,
            seed: info.seed,
            patch_size: info.patch_size,
            file_len: 0,
            blocks_offset: 0,
            blocks_checksum: 0,
            coef_bytes: 0,
            header_checksum: 0,
            wavelet_n: info.wavelet_n,
            wavelet_threshold: info.wavelet_threshold,
            environment: info.environment,
            reserved: [0; 8],
        };
        let blocks = entries
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
            tri_counts: entries.iter().map(|p| p.tri_count).collect(),
            written: vec![false; entries.len()],
        })
    }

    fn misuse(&self, what: String) -> FormatError {
        FormatError::BadRadiance {
            path: self.path.clone(),
            what,
        }
    }

    /// Appends page `page`'s block.
    pub fn push(&mut self, page: u32, block: &BakedBlock) -> Result<()> {
        let i = page as usize;
        let coefs_fit = self.header.wavelet_n > 0 || block.coefs == CoefBlock::default();
        match (self.blocks.get(i), self.tri_counts.get(i)) {
            (Some(b), Some(&t))
                if b.node_count as usize == block.nodes.len()
                    && t as usize == block.patch_of.len()
                    && coefs_fit
                    && !self.written[i] => {}
            _ => {
                return Err(self.misuse(format!(
                    "block for page {page} ({} nodes, {} triangles) does not fit the archive or the file, or was written twice",
                    block.nodes.len(),
                    block.patch_of.len()
                )))
            }
        }
        let mut raw = Vec::with_capacity(block.bytes() as usize);
        raw.extend_from_slice(bytemuck::cast_slice(&block.nodes));
        raw.extend_from_slice(bytemuck::cast_slice(&block.patch_of));
        raw.extend_from_slice(bytemuck::cast_slice(&block.patches));
        if self.header.wavelet_n > 0 {
            let c = &block.coefs;
            raw.extend_from_slice(&(c.records.len() as u32).to_le_bytes());
            raw.extend_from_slice(&(c.values.len() as u32).to_le_bytes());
            raw.extend_from_slice(bytemuck::cast_slice(&c.records));
            raw.extend_from_slice(bytemuck::cast_slice(&c.values));
            self.header.coef_bytes += c.bytes();
        }
        let packed = crate::writer::compress(&raw, 3).map_err(io(&self.path))?;
        self.blocks[i] = BlockEntry {
            offset: self.out.len(),
            compressed_len: packed.len() as u32,
            raw_len: raw.len() as u32,
            checksum: xxhash_rust::xxh3::xxh3_64(&packed),
            node_count: block.nodes.len() as u32,
            patch_count: block.patches.len() as u32,
        };
        self.written[i] = true;
        self.out.write_all(&packed)
    }

    /// Bytes of the blocks written, decompressed.
    pub fn decoded_bytes(&self) -> u64 {
        self.blocks.iter().map(|b| b.raw_len as u64).sum()
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

/// An open bake file checked against its archive; blocks are read on demand.
pub struct BakeFile {
    path: PathBuf,
    file: File,
    pub header: BakeHeader,
    pub blocks: Vec<BlockEntry>,
    tri_counts: Vec<u32>,
}

impl BakeFile {
    pub fn open(path: &Path, archive: &Archive) -> Result<BakeFile> {
        let meta = std::fs::metadata(path).map_err(io(path))?;
        if !meta.is_file() {
            return Err(FormatError::BadRadiance {
                path: path.to_path_buf(),
                what: "not a regular file".into(),
            });
        }
        let file = File::open(path).map_err(io(path))?;
        BakeFile::from_file(file, path, archive)
    }

    /// Checks the header, the identity, the table and every block's checksum (one read of
    /// the file, a block at a time); blocks are decoded and their values checked on demand.
    pub fn from_file(file: File, path: &Path, archive: &Archive) -> Result<BakeFile> {
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
        let h: BakeHeader = bytemuck::pod_read_unaligned(&head);
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
        if (h.nodes, h.pages) != (a.nodes, archive.page_count()) {
            return Err(wrong(format!(
                "{} nodes in {} pages, not {} in {}",
                h.nodes,
                h.pages,
                a.nodes,
                archive.page_count()
            )));
        }
        let entries = archive.entries()?;
        let blocks = read_blocks(&file, &h).map_err(bad)?;
        let mut packed = Vec::new();
        let mut coef_bytes = 0;
        for (i, (b, p)) in blocks.iter().zip(&entries).enumerate() {
            coef_bytes += check_block(b, h.blocks_offset, p, h.wavelet_n)
                .map_err(|what| bad(format!("block {i}: {what}")))?;
            packed.resize(b.compressed_len as usize, 0);
            if read_at(&file, &mut packed, b.offset, len) < packed.len()
                || xxhash_rust::xxh3::xxh3_64(&packed) != b.checksum
            {
                return Err(bad(format!("block {i}: checksum mismatch")));
            }
        }
        if coef_bytes != h.coef_bytes {
            return Err(bad(format!(
                "the blocks hold {coef_bytes} coefficient bytes, the header says {}",
                h.coef_bytes
            )));
        }
        Ok(BakeFile {
            path: path.to_path_buf(),
            file,
            header: h,
            blocks,
            tri_counts: entries.iter().map(|p| p.tri_count).collect(),
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Page `page`'s block: checksum, exact decompressed size, finite non-negative values,
    /// patch pyramids inside the patch list.
    pub fn read_block(&self, page: u32) -> Result<BakedBlock> {
        let bad = |what: String| FormatError::BadRadiance {
            path: self.path.clone(),
            what: format!("block {page}: {what}"),
        };
        let (b, tris) = match (
            self.blocks.get(page as usize),
            self.tri_counts.get(page as usize),
        ) {
            (Some(b), Some(&t)) => (b, t as usize),
            _ => return Err(bad("no such page".into())),
        };
        let mut packed = vec![0u8; b.compressed_len as usize];
        if read_at(&self.file, &mut packed, b.offset, self.header.file_len) < packed.len() {
            return Err(bad("the file is shorter than its table says".into()));
        }
        if xxhash_rust::xxh3::xxh3_64(&packed) != b.checksum {
            return Err(bad("checksum mismatch".into()));
        }
        match zstd::zstd_safe::get_frame_content_size(&packed) {
            Ok(Some(n)) if n != b.raw_len as u64 => {
                return Err(bad(format!(
                    "raw_len {} declared, its frame holds {n} bytes",
                    b.raw_len
                )))
            }
            _ => {}
        }
        let block = decode_block(&packed, b, tris).map_err(&bad)?;
        check_values(&block).map_err(&bad)?;
        check_coefs(&block, self.header.wavelet_n).map_err(bad)?;
        Ok(block)
    }
}

/// A block inflated section by section, each into a buffer of the size the archive's page
/// and the sections before it allow: nodes and `patch_of` first, then exactly the patches
/// the triangles' pyramids need, then the coefficient section; nothing past `raw_len`.
fn decode_block(
    packed: &[u8],
    b: &BlockEntry,
    tris: usize,
) -> std::result::Result<BakedBlock, String> {
    let broken = |e: std::io::Error| match e.kind() {
        std::io::ErrorKind::UnexpectedEof => {
            format!("the frame ends before raw_len {} bytes", b.raw_len)
        }
        _ => format!("does not decompress: {e}"),
    };
    let mut z = zstd::stream::read::Decoder::new(packed)
        .map_err(broken)?
        .single_frame();
    let nodes: Vec<BakedNode> = read_pod(&mut z, b.node_count as usize).map_err(broken)?;
    let patch_of: Vec<u32> = read_pod(&mut z, tris).map_err(broken)?;
    let mut need = 0u64;
    for (t, &v) in patch_of.iter().enumerate() {
        let (k, off) = (v >> 28, (v & 0x0FFF_FFFF) as u64);
        if k > MAX_PATCH_DEPTH {
            return Err(format!(
                "triangle {t}: patch depth {k} (at most {MAX_PATCH_DEPTH})"
            ));
        }
        need = need.max(off + pyramid_len(k) as u64);
    }
    if tris > 0 && need != b.patch_count as u64 {
        return Err(format!(
            "patch_count {}, the triangles' pyramids end at {need}",
            b.patch_count
        ));
    }
    let patches: Vec<[f32; 3]> = read_pod(&mut z, b.patch_count as usize).map_err(broken)?;
    let fixed = b.node_count as u64 * 96 + tris as u64 * 4 + b.patch_count as u64 * 12;
    let section: Vec<u8> = read_pod(&mut z, (b.raw_len as u64 - fixed) as usize).map_err(broken)?;
    let mut more = [0u8; 1];
    if std::io::Read::read(&mut z, &mut more).map_err(broken)? > 0 {
        return Err(format!(
            "more than raw_len {} bytes after decompression",
            b.raw_len
        ));
    }
    Ok(BakedBlock {
        nodes,
        patch_of,
        patches,
        coefs: read_coefs(&section)?,
    })
}

/// `count` values read whole from `r`; an error if it ends first.
fn read_pod<T: Pod>(r: &mut impl std::io::Read, count: usize) -> std::io::Result<Vec<T>> {
    let mut v = vec![T::zeroed(); count];
    r.read_exact(bytemuck::cast_slice_mut(&mut v))?;
    Ok(v)
}

/// Every value finite and ≥ 0; every pyramid of a known depth and inside the patch list.
fn check_values(b: &BakedBlock) -> std::result::Result<(), String> {
    let ok = |v: &f32| v.is_finite() && *v >= 0.0;
    for (k, n) in b.nodes.iter().enumerate() {
        if !n.area.iter().all(ok) || !n.power.iter().flatten().all(ok) {
            return Err(format!("node {k}: a negative or non-finite value"));
        }
    }
    if let Some(k) = b.patches.iter().position(|p| !p.iter().all(ok)) {
        return Err(format!("patch {k}: a negative or non-finite value"));
    }
    for t in 0..b.patch_of.len() {
        if let Some((k, off)) = b.patches_of(t) {
            if k > MAX_PATCH_DEPTH || off + pyramid_len(k) as usize > b.patches.len() {
                return Err(format!(
                    "triangle {t}: patches of depth {k} at {off} outside the {} stored",
                    b.patches.len()
                ));
            }
        }
    }
    Ok(())
}

/// A block's coefficient section: two counts, records, values; empty when absent.
fn read_coefs(raw: &[u8]) -> std::result::Result<CoefBlock, String> {
    if raw.is_empty() {
        return Ok(CoefBlock::default());
    }
    let count = |at: usize| u32::from_le_bytes(raw[at..at + 4].try_into().unwrap()) as u64;
    let (r, v) = (count(0), count(4));
    if 8 + 16 * (r + v) != raw.len() as u64 {
        return Err(format!(
            "{r} coefficient records and {v} values do not fill the {} bytes after the patches",
            raw.len()
        ));
    }
    let (records, values) = raw[8..].split_at(16 * r as usize);
    Ok(CoefBlock {
        records: bytemuck::pod_collect_to_vec(records),
        values: bytemuck::pod_collect_to_vec(values),
    })
}

/// Records by ascending node inside the page, each a known kind with its values next in
/// line; indices ascending inside the 6·n² of a vector; values finite.
fn check_coefs(b: &BakedBlock, n: u32) -> std::result::Result<(), String> {
    let c = &b.coefs;
    let texels = 6 * n * n;
    let mut next = 0u64;
    let mut last_node = None;
    for (k, r) in c.records.iter().enumerate() {
        let fits = (r.node as usize) < b.nodes.len()
            && last_node.is_none_or(|l| r.node > l)
            && r.kind <= CoefRecord::DETAIL
            && r.count > 0
            && r.first as u64 == next;
        if !fits {
            return Err(format!(
                "coefficient record {k} (node {}, kind {}, values {}+{}) out of order or place",
                r.node, r.kind, r.first, r.count
            ));
        }
        next += r.count as u64;
        let Some(vals) = c.values.get(r.first as usize..next as usize) else {
            return Err(format!(
                "coefficient record {k}: values past the {} stored",
                c.values.len()
            ));
        };
        if !vals.windows(2).all(|w| w[0].index < w[1].index)
            || vals
                .iter()
                .any(|v| v.index >= texels || !v.rgb.iter().all(|x| x.is_finite()))
        {
            return Err(format!(
                "coefficient record {k}: indices not ascending below {texels} or a non-finite value"
            ));
        }
        last_node = Some(r.node);
    }
    if next != c.values.len() as u64 {
        return Err(format!(
            "{} coefficient values, the records use {next}",
            c.values.len()
        ));
    }
    Ok(())
}

/// Most bytes a block's coefficient section can take: its two counts, a record per node and
/// every texel of each node's vector.
pub fn coef_section_bound(nodes: u32, wavelet_n: u32) -> u64 {
    8 + 16 * nodes as u64 * (1 + 6 * wavelet_n as u64 * wavelet_n as u64)
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

fn check_header(h: &BakeHeader) -> std::result::Result<(), String> {
    let table = h.pages as u64 * std::mem::size_of::<BlockEntry>() as u64;
    if h.header_size != 128 {
        return Err(format!("header size {}, not 128", h.header_size));
    }
    if h.record_size as usize != std::mem::size_of::<BakedNode>() {
        return Err(format!("record size {}, not 96", h.record_size));
    }
    if !(h.patch_size.is_finite() && h.patch_size > 0.0) {
        return Err(format!("patch size {}", h.patch_size));
    }
    if h.reserved != [0; 8] {
        return Err("reserved bytes set".into());
    }
    if h.wavelet_n == 0 && (h.coef_bytes != 0 || h.wavelet_threshold != 0.0) {
        return Err("coefficients without a cube-map resolution".into());
    }
    if h.wavelet_n != 0 && !(h.wavelet_n.is_power_of_two() && h.wavelet_n <= MAX_WAVELET_N) {
        return Err(format!(
            "wavelet_n {}, not a power of two up to {MAX_WAVELET_N}",
            h.wavelet_n
        ));
    }
    if !(h.wavelet_threshold.is_finite() && h.wavelet_threshold >= 0.0) {
        return Err(format!("wavelet threshold {}", h.wavelet_threshold));
    }
    if h.blocks_offset < 128 || h.blocks_offset.checked_add(table) != Some(h.file_len) {
        return Err(format!(
            "the block table at {} for {} pages does not end the file",
            h.blocks_offset, h.pages
        ));
    }
    Ok(())
}

fn read_blocks(file: &File, h: &BakeHeader) -> std::result::Result<Vec<BlockEntry>, String> {
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

/// Checks an entry against its archive page; returns its coefficient section's bytes.
fn check_block(
    b: &BlockEntry,
    end: u64,
    page: &PageEntry,
    wavelet_n: u32,
) -> std::result::Result<u64, String> {
    let nodes = page.node_count;
    if b.node_count != nodes {
        return Err(format!(
            "node_count {}, the archive's page has {nodes}",
            b.node_count
        ));
    }
    let most = page.tri_count as u64 * pyramid_len(MAX_PATCH_DEPTH) as u64;
    if b.patch_count as u64 > most {
        return Err(format!(
            "patch_count {} for {} triangles (at most {most}: depth {MAX_PATCH_DEPTH} each)",
            b.patch_count, page.tri_count
        ));
    }
    let coefs = wavelet_n > 0;
    let fixed = nodes as u64 * 96 + page.tri_count as u64 * 4 + b.patch_count as u64 * 12;
    let extra = (b.raw_len as u64).wrapping_sub(fixed);
    let fits = match coefs {
        false => extra == 0,
        true => b.raw_len as u64 >= fixed + 8 && (extra - 8).is_multiple_of(16),
    };
    if !fits {
        return Err(format!(
            "raw_len {} for {nodes} nodes, {} triangles and {} patches",
            b.raw_len, page.tri_count, b.patch_count
        ));
    }
    let coef_most = coef_section_bound(nodes, wavelet_n);
    if coefs && extra > coef_most {
        return Err(format!(
            "raw_len {} leaves {extra} coefficient bytes for {nodes} nodes (at most {coef_most} at wavelet_n {wavelet_n})",
            b.raw_len
        ));
    }
    if b.offset < 128 || b.offset + b.compressed_len as u64 > end {
        return Err(format!(
            "bytes {}..{} outside the block area 128..{end}",
            b.offset,
            b.offset + b.compressed_len as u64
        ));
    }
    Ok(extra)
}

#[cfg(test)]
#[path = "bake_tests.rs"]
mod tests;
