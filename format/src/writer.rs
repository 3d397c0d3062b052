//! Writing an archive: pages are appended as they are produced, the tables and the header go
//! in last, and the file only appears at its final path once complete (write to a temporary
//! name in the same directory, fsync, rename).

use crate::atomic::AtomicFile;
use crate::error::Result;
use crate::node::{Node, Tri};
use crate::records::*;
use bytemuck::Zeroable;
use std::path::Path;
use xxhash_rust::xxh3::Xxh3;

/// The decoded contents of one page.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PageContents {
    pub nodes: Vec<Node>,
    pub tris: Vec<Tri>,
    pub verts: Vec<[f32; 3]>,
    /// Octahedral shading normals, one per vertex, or empty.
    pub normals: Vec<u32>,
    /// Texture coordinates, one per vertex, or empty.
    pub uvs: Vec<[f32; 2]>,
    /// The second set of texture coordinates, one per vertex, or empty.
    pub uvs2: Vec<[f32; 2]>,
    /// Linear RGBA colours (unorm16), one per vertex, or empty.
    pub colours: Vec<[u16; 4]>,
    /// The records of the page's instance leaves (PAGED_INSTANCES), in link order.
    pub instances: Vec<InstanceRecord>,
}

/// Which per-vertex streams follow the positions in every page of an archive.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Streams {
    /// SHADING_NORMALS.
    pub normals: bool,
    /// TEXCOORDS.
    pub uvs: bool,
    /// TEXCOORDS2.
    pub uvs2: bool,
    /// COLOURS.
    pub colours: bool,
}

impl Streams {
    pub fn of(features: u64) -> Streams {
        Streams {
            normals: features & Features::SHADING_NORMALS != 0,
            uvs: features & Features::TEXCOORDS != 0,
            uvs2: features & Features::TEXCOORDS2 != 0,
            colours: features & Features::COLOURS != 0,
        }
    }

    /// How many texture-coordinate sets each vertex carries: a page header's `has_uvs`.
    pub fn uv_sets(&self) -> u32 {
        self.uvs as u32 + self.uvs2 as u32
    }
}

/// A page compressed and checksummed, ready to append.
pub struct EncodedPage {
    pub bytes: Vec<u8>,
    pub raw_len: u32,
    pub checksum: u64,
    pub node_count: u32,
    pub tri_count: u32,
    pub vert_count: u32,
    pub instance_count: u32,
}

/// Where a page sits in the page tree.
#[derive(Clone, Copy, Debug)]
pub struct PageMeta {
    pub parent_page: u32,
    pub parent_node: u32,
    pub root_count: u16,
    pub bounds_min: [f32; 3],
    pub bounds_max: [f32; 3],
}

/// Serializes and compresses a page. Pure, so callers can encode pages in parallel.
/// `streams` are the archive's: every page of such an archive says so in its header, a page
/// without vertices too.
pub fn encode_page(
    p: &PageContents,
    streams: Streams,
    zstd_level: i32,
) -> std::io::Result<EncodedPage> {
    assert_eq!(
        p.normals.len(),
        if streams.normals { p.verts.len() } else { 0 }
    );
    assert_eq!(p.uvs.len(), if streams.uvs { p.verts.len() } else { 0 });
    assert_eq!(p.uvs2.len(), if streams.uvs2 { p.verts.len() } else { 0 });
    assert_eq!(
        p.colours.len(),
        if streams.colours { p.verts.len() } else { 0 }
    );
    let header = PageHeader {
        magic: PAGE_MAGIC,
        node_count: p.nodes.len() as u32,
        tri_count: p.tris.len() as u32,
        vert_count: p.verts.len() as u32,
        instance_count: p.instances.len() as u32,
        has_normals: streams.normals as u32,
        has_uvs: streams.uv_sets(),
        has_colours: streams.colours as u32,
    };
    let mut raw = Vec::with_capacity(raw_page_len(&header, NODE_SIZE));
    raw.extend_from_slice(bytemuck::bytes_of(&header));
    raw.extend_from_slice(bytemuck::cast_slice(&p.nodes));
    raw.extend_from_slice(bytemuck::cast_slice(&p.tris));
    raw.extend_from_slice(bytemuck::cast_slice(&p.verts));
    raw.extend_from_slice(bytemuck::cast_slice(&p.normals));
    raw.extend_from_slice(bytemuck::cast_slice(&p.uvs));
    raw.extend_from_slice(bytemuck::cast_slice(&p.uvs2));
    raw.extend_from_slice(bytemuck::cast_slice(&p.colours));
    raw.extend_from_slice(bytemuck::cast_slice(&p.instances));
    let bytes = compress(&raw, zstd_level)?;
    Ok(EncodedPage {
        checksum: xxhash_rust::xxh3::xxh3_64(&bytes),
        raw_len: raw.len() as u32,
        bytes,
        node_count: header.node_count,
        tri_count: header.tri_count,
        vert_count: header.vert_count,
        instance_count: header.instance_count,
    })
}

/// `raw` compressed at `level` by this thread's zstd context, kept between calls: a fresh
/// context per page would allocate and clear its tables every time. The output is the same
/// as a fresh context's: each call starts a new frame with the same parameters.
pub(crate) fn compress(raw: &[u8], level: i32) -> std::io::Result<Vec<u8>> {
    use std::cell::RefCell;
    thread_local! {
        static CONTEXT: RefCell<Option<(i32, zstd::bulk::Compressor<'static>)>> =
            const { RefCell::new(None) };
    }
    CONTEXT.with(|c| {
        let mut c = c.borrow_mut();
        let context = match &mut *c {
            Some((l, z)) if *l == level => z,
            slot => &mut slot.insert((level, zstd::bulk::Compressor::new(level)?)).1,
        };
        context.compress(raw)
    })
}

/// `page` with `by` added to the number of every child page its nodes name, as if its
/// pages had been numbered from `by` more when it was encoded: decompressed, changed and
/// compressed again at `zstd_level`, so its bytes are those `encode_page` gives the changed
/// contents. Pages built apart (a chunk per process, numbered from 0) move into place so.
pub fn renumber_page(page: &EncodedPage, by: u32, zstd_level: i32) -> std::io::Result<EncodedPage> {
    let bad = |what: &str| std::io::Error::new(std::io::ErrorKind::InvalidData, what.to_string());
    let mut raw = zstd::bulk::decompress(&page.bytes, page.raw_len as usize)?;
    let header = std::mem::size_of::<PageHeader>();
    let node = std::mem::size_of::<Node>();
    let end = header + page.node_count as usize * node;
    if raw.len() != page.raw_len as usize || raw.len() < end {
        return Err(bad("the page is shorter than its counts"));
    }
    for at in (header..end).step_by(node) {
        let mut n: Node = bytemuck::pod_read_unaligned(&raw[at..at + node]);
        if n.has_child_page() {
            n.link[0] = n.link[0]
                .checked_add(by)
                .ok_or_else(|| bad("a child page number overflows"))?;
            raw[at..at + node].copy_from_slice(bytemuck::bytes_of(&n));
        }
    }
    let bytes = compress(&raw, zstd_level)?;
    Ok(EncodedPage {
        checksum: xxhash_rust::xxh3::xxh3_64(&bytes),
        bytes,
        ..*page
    })
}

/// A texture tile compressed and checksummed, ready to append.
pub struct EncodedTile {
    pub bytes: Vec<u8>,
    pub checksum: u64,
}

/// Compresses one tile of `TILE_BYTES` RGBA8 texels. Pure, so tiles can be encoded in parallel.
pub fn encode_tile(texels: &[u8], zstd_level: i32) -> std::io::Result<EncodedTile> {
    assert_eq!(texels.len(), TILE_BYTES as usize);
    let stored = crate::codec::tile_filter(texels, TILE as usize);
    let bytes = compress(&stored, zstd_level)?;
    Ok(EncodedTile {
        checksum: xxhash_rust::xxh3::xxh3_64(&bytes),
        bytes,
    })
}

/// Decompressed size a page header implies, with node records of `node_size` bytes.
pub fn raw_page_len(h: &PageHeader, node_size: u32) -> usize {
    let per_vertex = 12
        + 4 * (h.has_normals != 0) as usize
        + 8 * h.has_uvs.min(2) as usize
        + 8 * (h.has_colours != 0) as usize;
    std::mem::size_of::<PageHeader>()
        + h.node_count as usize * node_size as usize
        + h.tri_count as usize * std::mem::size_of::<Tri>()
        + h.vert_count as usize * per_vertex
        + h.instance_count as usize * std::mem::size_of::<InstanceRecord>()
}

/// Scene-level values the header carries.
#[derive(Clone, Debug, Default)]
pub struct SceneInfo {
    pub features: u64,
    pub input_triangles: u64,
    pub bounds_min: [f32; 3],
    pub bounds_max: [f32; 3],
    pub root_page: u32,
    pub depth: u32,
    pub max_leaf_triangles: u32,
    pub page_nodes_max: u32,
    pub materials: Vec<MaterialRecord>,
    pub cameras: Vec<CameraRecord>,
    pub lights: Vec<LightRecord>,
    /// Textures whose tiles were appended with `push_tile`, numbered from 0.
    pub textures: Vec<TextureRecord>,
    /// The environment light its scene file gave, if any.
    pub environment: Option<EnvironmentRecord>,
    /// What the converter said of its input (features not read, and what was done).
    pub notes: Vec<NoteRecord>,
}

pub struct ArchiveWriter {
    out: AtomicFile,
    /// The page table, in blocks: growing it never copies what it holds (a million
    /// pages' entries are 96 MB).
    pages: Vec<Vec<PageEntry>>,
    page_count: usize,
    tiles: Vec<TileEntry>,
    nodes: u64,
    tris: u64,
    verts: u64,
    instances: u64,
}

impl ArchiveWriter {
    /// Starts an archive that will appear at `path` when `finish` succeeds (`AtomicFile`).
    pub fn create(path: &Path) -> Result<Self> {
        Ok(Self {
            out: AtomicFile::create(path, 256)?,
            pages: Vec::new(),
            page_count: 0,
            tiles: Vec::new(),
            nodes: 0,
            tris: 0,
            verts: 0,
            instances: 0,
        })
    }

    /// Where the archive will appear.
    pub fn path(&self) -> &Path {
        self.out.path()
    }

    pub fn node_count(&self) -> u64 {
        self.nodes
    }

    pub fn page_count(&self) -> u32 {
        self.page_count as u32
    }

    /// Appends a page; returns its index. Pages get global node numbers in append order.
    pub fn push(&mut self, page: &EncodedPage, meta: PageMeta) -> Result<u32> {
        self.pad()?;
        let offset = self.out.len();
        self.out.write_all(&page.bytes)?;
        if self.page_count.is_multiple_of(TABLE_BLOCK) {
            self.pages.push(Vec::with_capacity(TABLE_BLOCK));
        }
        self.page_count += 1;
        let block = self.pages.last_mut().expect("a block was pushed");
        block.push(PageEntry {
            offset,
            compressed_len: page.bytes.len() as u32,
            raw_len: page.raw_len,
            checksum: page.checksum,
            first_node: self.nodes,
            node_count: page.node_count,
            tri_count: page.tri_count,
            vert_count: page.vert_count,
            instance_count: page.instance_count,
            parent_page: meta.parent_page,
            parent_node: meta.parent_node,
            level: 0,
            root_count: meta.root_count,
            bounds_min: meta.bounds_min,
            bounds_max: meta.bounds_max,
            entry_checksum: [0; 2],
            first_instance: self.instances as u32,
        });
        self.nodes += page.node_count as u64;
        self.tris += page.tri_count as u64;
        self.verts += page.vert_count as u64;
        self.instances += page.instance_count as u64;
        if self.instances > crate::validate::MAX_INSTANCES as u64 {
            return Err(crate::error::FormatError::Corrupt {
                path: self.out.path().to_path_buf(),
                what: format!(
                    "{} instances are more than an archive holds ({})",
                    self.instances,
                    crate::validate::MAX_INSTANCES
                ),
            });
        }
        Ok(self.page_count as u32 - 1)
    }

    /// Reserves `count` consecutive tile-table entries (a texture's pyramid); returns the
    /// first. Each must then be filled by `put_tile`, in any order.
    pub fn reserve_tiles(&mut self, count: u64) -> Result<u32> {
        let first = self.tiles.len() as u64;
        if first + count > u32::MAX as u64 {
            return Err(crate::error::FormatError::Corrupt {
                path: self.out.path().to_path_buf(),
                what: format!(
                    "{} texture tiles are more than a tile table holds",
                    first + count
                ),
            });
        }
        self.tiles
            .resize((first + count) as usize, TileEntry::zeroed());
        Ok(first as u32)
    }

    /// Appends tile `index` (reserved by `reserve_tiles`), as `encode_tile` made it.
    pub fn put_tile(&mut self, index: u32, tile: &EncodedTile) -> Result<()> {
        self.pad()?;
        self.tiles[index as usize] = TileEntry {
            offset: self.out.len(),
            compressed_len: tile.bytes.len() as u32,
            raw_len: TILE_BYTES,
            checksum: tile.checksum,
            reserved: [0; 8],
        };
        self.out.write_all(&tile.bytes)
    }

    /// Compressed bytes of the tiles written so far.
    pub fn tile_bytes(&self) -> u64 {
        self.tiles.iter().map(|t| t.compressed_len as u64).sum()
    }

    /// Zeros up to the next multiple of `ALIGN`.
    fn pad(&mut self) -> Result<()> {
        let pad = self.out.len().next_multiple_of(ALIGN) - self.out.len();
        self.out.write_all(&[0; ALIGN as usize][..pad as usize])
    }

    /// Records a page's parent once it is known (pages below are often written first).
    pub fn set_parent(&mut self, page: u32, parent_page: u32, parent_node: u32) {
        let e = self.entry(page as usize);
        e.parent_page = parent_page;
        e.parent_node = parent_node;
    }

    /// Page levels from the parent links (parents may come after their children in the file).
    fn fill_levels(&mut self) {
        let n = self.page_count;
        let mut level: Vec<Option<u16>> = vec![None; n];
        for start in 0..n {
            let mut chain = Vec::new();
            let mut p = start;
            let mut base = loop {
                if let Some(l) = level[p] {
                    break l;
                }
                chain.push(p);
                match self.entry(p).parent_page {
                    NONE => break u16::MAX,
                    parent if (parent as usize) < n && chain.len() <= n => p = parent as usize,
                    _ => break u16::MAX,
                }
            };
            for &q in chain.iter().rev() {
                base = base.wrapping_add(1);
                level[q] = Some(base);
            }
        }
        for (e, l) in self.pages.iter_mut().flatten().zip(level) {
            e.level = l.unwrap_or(0);
        }
    }

    /// Writes the tables and header, syncs, and renames into place. The material, camera,
    /// light, texture and tile tables go back to back from an aligned offset; the page table, each entry
    /// sealed with its own checksum, from the next aligned offset to the end.
    pub fn finish(mut self, info: &SceneInfo) -> Result<()> {
        if let Some(i) = self.tiles.iter().position(|t| t.raw_len == 0) {
            return Err(crate::error::FormatError::Corrupt {
                path: self.out.path().to_path_buf(),
                what: format!("texture tile {i} was reserved but never written"),
            });
        }
        self.fill_levels();
        for e in self.pages.iter_mut().flatten() {
            e.seal();
        }
        self.pad()?;
        // The tables go straight to the file, hashed as they go: gathered into one buffer
        // first, millions of instance records were held twice.
        let mut hash = Xxh3::new();
        let out = &mut self.out;
        let materials = put_table(out, Some(&mut hash), &info.materials)?;
        let cameras = put_table(out, Some(&mut hash), &info.cameras)?;
        let lights = put_table(out, Some(&mut hash), &info.lights)?;
        // The instance records are in the pages: the table names how many, with no bytes
        // (an archive without instances has an empty table of the usual record size).
        let instances = TableRef {
            offset: out.len(),
            count: self.instances as u32,
            record_size: match self.instances {
                0 => std::mem::size_of::<InstanceRecord>() as u32,
                _ => 0,
            },
        };
        let textures = put_table(out, Some(&mut hash), &info.textures)?;
        let tiles = put_table(out, Some(&mut hash), &self.tiles)?;
        let environment = put_table(out, Some(&mut hash), info.environment.as_slice())?;
        put_table(out, Some(&mut hash), &info.notes)?;
        let tables_checksum = hash.digest();
        self.pad()?;
        let pages = TableRef {
            offset: self.out.len(),
            count: self.page_count as u32,
            record_size: std::mem::size_of::<PageEntry>() as u32,
        };
        for block in &self.pages {
            put_table(&mut self.out, None, block)?;
        }
        let mut header = Header {
            magic: MAGIC,
            version_major: VERSION_MAJOR,
            version_minor: VERSION_MINOR,
            header_size: 256,
            features: match self.instances {
                0 => info.features & !(Features::INSTANCES | Features::PAGED_INSTANCES),
                _ => info.features | Features::INSTANCES | Features::PAGED_INSTANCES,
            },
            input_triangles: info.input_triangles,
            triangles: self.tris,
            nodes: self.nodes,
            vertices: self.verts,
            file_len: self.out.len(),
            bounds_min: info.bounds_min,
            bounds_max: info.bounds_max,
            root_page: info.root_page,
            depth: info.depth,
            max_leaf_triangles: info.max_leaf_triangles,
            page_nodes_max: info.page_nodes_max,
            materials,
            cameras,
            lights,
            pages,
            tables_checksum,
            header_checksum: 0,
            node_size: NODE_SIZE,
            notes: info.notes.len() as u32,
            instances,
            textures,
            tiles,
            environment,
        };
        header.header_checksum = xxhash_rust::xxh3::xxh3_64(bytemuck::bytes_of(&header));
        self.out.commit(bytemuck::bytes_of(&header))?;
        Ok(())
    }
}

/// What an `ArchiveWriter` holds beside the bytes it wrote. `suspend` returns it and `resume`
/// takes it back, so one process can write the first part of an archive and another finish
/// it (the conversion stages of a cluster job).
#[derive(Clone, Debug, Default)]
pub struct WriterState {
    pub pages: Vec<PageEntry>,
    pub tiles: Vec<TileEntry>,
    pub nodes: u64,
    pub tris: u64,
    pub verts: u64,
    pub instances: u64,
    /// Bytes written, the reserved header included.
    pub len: u64,
}

impl ArchiveWriter {
    /// Names what was written so far at the writer's path (header zero, no tables: not an
    /// archive, only `resume` reads it) and returns the rest of the writer's state.
    pub fn suspend(self) -> Result<WriterState> {
        let len = self.out.len();
        self.out.commit(&[0; 256])?;
        Ok(WriterState {
            pages: self.pages.into_iter().flatten().collect(),
            tiles: self.tiles,
            nodes: self.nodes,
            tris: self.tris,
            verts: self.verts,
            instances: self.instances,
            len,
        })
    }

    /// A writer for `path` that continues the archive `suspend` left in `body` with `state`:
    /// the body's bytes are copied in and its tables taken back, after checking that they
    /// describe that body.
    pub fn resume(path: &Path, body: &Path, state: WriterState) -> Result<Self> {
        use std::io::{Read, Seek, SeekFrom};
        let corrupt = |what: String| crate::error::FormatError::Corrupt {
            path: body.to_path_buf(),
            what,
        };
        let io = |error| crate::error::FormatError::Io {
            path: body.to_path_buf(),
            error,
        };
        let mut file = std::fs::File::open(body).map_err(io)?;
        let len = file.metadata().map_err(io)?.len();
        if len != state.len || len < 256 {
            return Err(corrupt(format!(
                "{len} bytes where the writer's state says {}",
                state.len
            )));
        }
        let within = |offset: u64, bytes: u32| offset >= 256 && offset + bytes as u64 <= len;
        let sum = |f: fn(&PageEntry) -> u32| state.pages.iter().map(|e| f(e) as u64).sum::<u64>();
        if let Some(i) = state
            .pages
            .iter()
            .position(|e| !within(e.offset, e.compressed_len))
        {
            return Err(corrupt(format!("page {i} lies outside the body")));
        }
        if let Some(i) = state
            .tiles
            .iter()
            .position(|t| t.raw_len != 0 && !within(t.offset, t.compressed_len))
        {
            return Err(corrupt(format!("texture tile {i} lies outside the body")));
        }
        if sum(|e| e.node_count) != state.nodes
            || sum(|e| e.tri_count) != state.tris
            || sum(|e| e.vert_count) != state.verts
            || sum(|e| e.instance_count) != state.instances
        {
            return Err(corrupt(
                "the page counts disagree with the writer's totals".into(),
            ));
        }
        let mut w = Self::create(path)?;
        file.seek(SeekFrom::Start(256)).map_err(io)?;
        let mut buf = vec![0u8; 1 << 20];
        loop {
            let n = file.read(&mut buf).map_err(io)?;
            if n == 0 {
                break;
            }
            w.out.write_all(&buf[..n])?;
        }
        if w.out.len() != len {
            return Err(corrupt("the body changed while it was read".into()));
        }
        w.page_count = state.pages.len();
        w.pages = state
            .pages
            .chunks(TABLE_BLOCK)
            .map(|b| {
                let mut block = Vec::with_capacity(TABLE_BLOCK);
                block.extend_from_slice(b);
                block
            })
            .collect();
        w.tiles = state.tiles;
        w.nodes = state.nodes;
        w.tris = state.tris;
        w.verts = state.verts;
        w.instances = state.instances;
        Ok(w)
    }
}

/// Page-table entries a block holds.
const TABLE_BLOCK: usize = 1 << 16;

impl ArchiveWriter {
    fn entry(&mut self, page: usize) -> &mut PageEntry {
        &mut self.pages[page / TABLE_BLOCK][page % TABLE_BLOCK]
    }
}

/// Appends a table's records to `out`, adding them to `hash` if given, and returns where
/// they sit; the record size is the type's.
fn put_table<T: bytemuck::Pod>(
    out: &mut AtomicFile,
    hash: Option<&mut Xxh3>,
    records: &[T],
) -> Result<TableRef> {
    let t = TableRef {
        offset: out.len(),
        count: records.len() as u32,
        record_size: std::mem::size_of::<T>() as u32,
    };
    let bytes = bytemuck::cast_slice(records);
    if let Some(hash) = hash {
        hash.update(bytes);
    }
    out.write_all(bytes)?;
    Ok(t)
}
