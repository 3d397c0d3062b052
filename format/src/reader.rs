//! Reading an archive over a memory map. Every length and offset is checked against the file
//! size before any mapped byte is touched, so a truncated or corrupt file is an error, never
//! a SIGBUS or a panic. (A file truncated by another process *while* mapped is outside what a
//! reader can defend against.)

use crate::codec::Grid;
use crate::error::{FormatError, Result};
use crate::node::{Node, Tri};
use crate::records::*;
use crate::validate::*;
use crate::writer::{PageContents, Streams};
use std::path::{Path, PathBuf};

pub struct Archive {
    path: PathBuf,
    map: memmap2::Mmap,
    pub header: Header,
    pub materials: Vec<MaterialRecord>,
    pub cameras: Vec<CameraRecord>,
    pub lights: Vec<LightRecord>,
    pub instances: Vec<InstanceRecord>,
    pub textures: Vec<TextureRecord>,
    tiles: Vec<TileEntry>,
    /// The scene's environment light, if its scene file gave one (2.3).
    pub environment: Option<EnvironmentRecord>,
    /// What the converter said of its input (2.4; empty before).
    pub notes: Vec<String>,
}

impl Archive {
    pub fn open(path: &Path) -> Result<Self> {
        let p = path.to_path_buf();
        // Stat before opening: opening a FIFO for reading would block until a writer came.
        let meta = std::fs::metadata(path).map_err(|source| FormatError::Io {
            path: p.clone(),
            error: source,
        })?;
        if !meta.is_file() {
            return Err(FormatError::NotAFile { path: p });
        }
        let io = |source| FormatError::Io {
            path: p.clone(),
            error: source,
        };
        let file = std::fs::File::open(path).map_err(io)?;
        // The length of what was opened, not of what was stat'ed.
        let len = file.metadata().map_err(io)?.len();
        if len < 8 {
            return Err(FormatError::Truncated {
                path: p,
                what: "the header".into(),
                needed: 256,
                len,
            });
        }
        // SAFETY: the map is read-only and every access below is bounds-checked against `len`.
        let map = unsafe { memmap2::Mmap::map(&file) }.map_err(|source| FormatError::Io {
            path: p.clone(),
            error: source,
        })?;
        if map[..8] != MAGIC {
            return Err(FormatError::BadMagic { path: p });
        }
        if len < 256 {
            return Err(FormatError::Truncated {
                path: p,
                what: "the header".into(),
                needed: 256,
                len,
            });
        }
        let header: Header = bytemuck::pod_read_unaligned(&map[..256]);
        let (major, minor) = (header.version_major, header.version_minor);
        if major > VERSION_MAJOR {
            return Err(FormatError::NewerVersion {
                path: p,
                major,
                minor,
            });
        }
        if (1..VERSION_MAJOR).contains(&major) {
            return Err(FormatError::OlderVersion {
                path: p,
                major,
                minor,
            });
        }
        let corrupt = |what: String| FormatError::Corrupt {
            path: p.clone(),
            what,
        };
        let mut check = header;
        check.header_checksum = 0;
        if xxhash_rust::xxh3::xxh3_64(bytemuck::bytes_of(&check)) != header.header_checksum {
            return Err(corrupt("header checksum mismatch".into()));
        }
        if header.header_size != 256 {
            return Err(corrupt(format!(
                "header size {} (expected 256)",
                header.header_size
            )));
        }
        check_header(&header).map_err(|what| corrupt(format!("header: {what}")))?;
        if header.file_len != len {
            return Err(FormatError::Truncated {
                path: p,
                what: "the archive".into(),
                needed: header.file_len,
                len,
            });
        }
        check_table_ranges(&header).map_err(&corrupt)?;
        let small = header.materials.offset as usize..header.pages.offset as usize;
        let end = small_tables_end(&header) as usize;
        if xxhash_rust::xxh3::xxh3_64(&map[small.start..end]) != header.tables_checksum
            || map[end..small.end].iter().any(|&b| b != 0)
        {
            return Err(corrupt("table checksum mismatch".into()));
        }
        let materials = read_table::<MaterialRecord>(&map, &header.materials);
        let cameras = read_table::<CameraRecord>(&map, &header.cameras);
        let lights = read_table::<LightRecord>(&map, &header.lights);
        // Paged instance records (2.7) are read with their pages; a table is read whole.
        let instances = match paged_instances(&header) {
            true => Vec::new(),
            false => read_released::<InstanceRecord>(&map, &header.instances),
        };
        let mut materials = materials;
        for m in &mut materials {
            fill_older_fields(header.version_minor, m);
        }
        let textures = read_table::<TextureRecord>(&map, &header.textures);
        let tiles = read_table::<TileEntry>(&map, &header.tiles);
        let environment = read_table::<EnvironmentRecord>(&map, &header.environment);
        let notes = match header.version_minor >= 4 {
            true => read_table::<NoteRecord>(&map, &notes_table(&header)),
            false => Vec::new(),
        };
        if header.pages.count == 0 || header.root_page >= header.pages.count {
            return Err(corrupt(format!(
                "root page {} of {} pages",
                header.root_page, header.pages.count
            )));
        }
        check_tables(&header, &materials, &cameras, &lights).map_err(&corrupt)?;
        check_instances(&header, &instances).map_err(&corrupt)?;
        check_textures(header.materials.offset, &materials, &textures, &tiles).map_err(&corrupt)?;
        check_environment(&environment).map_err(&corrupt)?;
        let notes = check_notes(&notes).map_err(&corrupt)?;
        let archive = Self {
            path: p,
            map,
            header,
            materials,
            cameras,
            lights,
            instances,
            textures,
            tiles,
            environment: environment.first().copied(),
            notes,
        };
        archive.entry(header.root_page)?;
        archive.check_prototypes()?;
        Ok(archive)
    }

    /// Every prototype page the instance table names is a tree's root page (no parent,
    /// level 0, one root): one entry read per distinct prototype. Paged records are
    /// checked with their page.
    fn check_prototypes(&self) -> Result<()> {
        let mut pages: Vec<u32> = self.instances.iter().map(|i| i.prototype_page).collect();
        pages.sort_unstable();
        pages.dedup();
        for p in pages {
            let e = self.entry(p)?;
            if p == self.header.root_page || e.parent_page != NONE || e.root_count != 1 {
                return Err(self.page_err(
                    p,
                    "an instance names it, but it is not a prototype's root page",
                ));
            }
        }
        Ok(())
    }

    /// Pages in the archive.
    pub fn page_count(&self) -> u32 {
        self.header.pages.count
    }

    /// Every page's entry, checked: for what needs the whole table (`verify`, a bake).
    pub fn entries(&self) -> Result<Vec<PageEntry>> {
        (0..self.page_count()).map(|i| self.entry(i)).collect()
    }

    /// Page `page`'s table entry, after checking its own checksum and what it claims
    /// (`check_entry`): constant time, so opening an archive costs the same at any size.
    pub fn entry(&self, page: u32) -> Result<PageEntry> {
        let t = &self.header.pages;
        if page >= t.count {
            return Err(self.page_err(page, format!("no such page ({} pages)", t.count)));
        }
        let at = (t.offset + page as u64 * t.record_size as u64) as usize;
        let record = &self.map[at..at + t.record_size as usize];
        let e: PageEntry = bytemuck::pod_read_unaligned(&record[..96]);
        if PageEntry::checksum_of(record) != e.entry_checksum() {
            return Err(self.page_err(page, "page-table entry checksum mismatch"));
        }
        check_entry(&self.header, page, &e).map_err(|what| self.page_err(page, what))?;
        Ok(e)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    fn page_err(&self, page: u32, what: impl Into<String>) -> FormatError {
        FormatError::BadPage {
            path: self.path.clone(),
            page,
            what: what.into(),
        }
    }

    /// The compressed bytes of a page, after checking its checksum.
    pub fn page_bytes(&self, page: u32) -> Result<&[u8]> {
        let e = self.entry(page)?;
        let bytes = &self.map[e.offset as usize..(e.offset + e.compressed_len as u64) as usize];
        if xxhash_rust::xxh3::xxh3_64(bytes) != e.checksum {
            return Err(self.page_err(page, "checksum mismatch (the page is corrupt)"));
        }
        Ok(bytes)
    }

    /// Decompresses a page and checks that every index in it is in range, so code that walks
    /// the page can index without further checks.
    pub fn read_page(&self, page: u32) -> Result<PageContents> {
        let bytes = self.page_bytes(page)?;
        let e = self.entry(page)?;
        let raw = zstd::bulk::decompress(bytes, e.raw_len as usize)
            .map_err(|err| self.page_err(page, format!("zstd: {err}")))?;
        self.release(e.offset as usize, e.compressed_len as usize);
        if raw.len() != e.raw_len as usize {
            return Err(self.page_err(
                page,
                format!(
                    "decompressed to {} bytes, page table says {}",
                    raw.len(),
                    e.raw_len
                ),
            ));
        }
        let h: PageHeader = bytemuck::pod_read_unaligned(&raw[..32]);
        let streams = Streams::of(self.header.features);
        if h.magic != PAGE_MAGIC
            || (h.node_count, h.tri_count, h.vert_count, h.instance_count)
                != (e.node_count, e.tri_count, e.vert_count, e.instance_count)
            || (h.has_normals != 0) != streams.normals
            || h.has_uvs != streams.uv_sets()
            || (h.has_colours != 0) != streams.colours
        {
            return Err(self.page_err(page, "page header disagrees with the page table"));
        }
        let mut at = 32;
        let mut take = |n: usize| {
            let s = &raw[at..at + n];
            at += n;
            s
        };
        let size = self.header.node_size as usize;
        let nodes: Vec<Node> = take(h.node_count as usize * size)
            .chunks_exact(size)
            .map(|r| bytemuck::pod_read_unaligned(&r[..NODE_SIZE as usize]))
            .collect();
        let tris: Vec<Tri> = bytemuck::pod_collect_to_vec(take(h.tri_count as usize * 8));
        let verts: Vec<[f32; 3]> = bytemuck::pod_collect_to_vec(take(h.vert_count as usize * 12));
        let normals: Vec<u32> = if streams.normals {
            bytemuck::pod_collect_to_vec(take(h.vert_count as usize * 4))
        } else {
            Vec::new()
        };
        let mut uv_stream = |on: bool| -> Vec<[f32; 2]> {
            match on {
                true => bytemuck::pod_collect_to_vec(take(h.vert_count as usize * 8)),
                false => Vec::new(),
            }
        };
        let uvs = uv_stream(streams.uvs);
        let uvs2 = uv_stream(streams.uvs2);
        let colours: Vec<[u16; 4]> = if streams.colours {
            bytemuck::pod_collect_to_vec(take(h.vert_count as usize * 8))
        } else {
            Vec::new()
        };
        let instances = bytemuck::pod_collect_to_vec(take(h.instance_count as usize * 64));
        let contents = PageContents {
            nodes,
            tris,
            verts,
            normals,
            uvs,
            uvs2,
            colours,
            instances,
        };
        self.check_indices(page, &contents)?;
        Ok(contents)
    }

    /// Decompresses texture tile `index` (`TILE_BYTES` of RGBA8), after checking its checksum.
    pub fn read_tile(&self, index: u32) -> Result<Vec<u8>> {
        let bad = |what: String| FormatError::Corrupt {
            path: self.path.clone(),
            what: format!("texture tile {index}: {what}"),
        };
        let e = self
            .tiles
            .get(index as usize)
            .ok_or_else(|| bad(format!("not among {} tiles", self.tiles.len())))?;
        let bytes = &self.map[e.offset as usize..(e.offset + e.compressed_len as u64) as usize];
        if xxhash_rust::xxh3::xxh3_64(bytes) != e.checksum {
            return Err(bad("checksum mismatch (the tile is corrupt)".into()));
        }
        let raw = zstd::bulk::decompress(bytes, TILE_BYTES as usize)
            .map_err(|err| bad(format!("zstd: {err}")))?;
        self.release(e.offset as usize, e.compressed_len as usize);
        if raw.len() != TILE_BYTES as usize {
            return Err(bad(format!("decompressed to {} bytes", raw.len())));
        }
        Ok(crate::codec::tile_unfilter(&raw, TILE as usize))
    }

    /// The tile table (each entry checked at open).
    pub fn tile_entries(&self) -> &[TileEntry] {
        &self.tiles
    }

    /// Entries of the tile table.
    pub fn tile_count(&self) -> u32 {
        self.tiles.len() as u32
    }

    /// Compressed bytes of all texture tiles.
    pub fn tile_bytes(&self) -> u64 {
        self.tiles.iter().map(|t| t.compressed_len as u64).sum()
    }

    fn check_indices(&self, page: u32, c: &PageContents) -> Result<()> {
        let entry = |i: u32| self.entry(i).map_err(|e| e.to_string());
        check_page(&self.header, self.materials.len(), &entry, page, c)
            .map_err(|what| self.page_err(page, what))
    }

    /// Drops the mapped file pages of a byte range from this process's resident set once
    /// decoded, so RSS follows the decoded-page cache rather than every page ever read.
    /// The kernel keeps them in its page cache; a later read faults them back in.
    fn release(&self, offset: usize, len: usize) {
        // A fault maps more than the touched page: up to 64 KiB around it (fault-around)
        // and, on kernels whose page cache holds large folios, the whole folio (up to 2 MiB
        // on a freshly written archive: RSS under a 472 MB budget measured 731 MiB with
        // 64 KiB blocks). Release whole aligned 2 MiB blocks, neighbours included.
        const BLOCK: usize = 2 << 20;
        let start = offset & !(BLOCK - 1);
        let end = (offset + len)
            .div_ceil(BLOCK)
            .saturating_mul(BLOCK)
            .min(self.map.len());
        let (offset, len) = (start, end.saturating_sub(start));
        #[cfg(unix)]
        // SAFETY: the mapping is read-only and shared; after MADV_DONTNEED a read faults
        // the same file bytes back in, so no reader can observe a change.
        unsafe {
            self.map
                .unchecked_advise_range(memmap2::UncheckedAdvice::DontNeed, offset, len)
                .ok();
        }
        #[cfg(not(unix))]
        let _ = (offset, len);
    }

    /// The quantization grid of a page.
    pub fn grid(&self, page: u32) -> Result<Grid> {
        Ok(self.entry(page)?.grid())
    }
}

/// What a material record of an earlier minor version means by the fields it lacks (or,
/// before 2.2, held reserved as zero).
fn fill_older_fields(minor: u16, m: &mut MaterialRecord) {
    if minor < 2 {
        // Before 2.2 these bytes were reserved (zero): no textures.
        m.textures = [MaterialRecord::NO_TEXTURE; 4];
    }
    if minor < 5 {
        // Records before 2.5 end before the layer textures: none.
        m.layer_textures = [MaterialRecord::NO_TEXTURE; 4];
    }
    if minor < 6 {
        // Records before 2.6 end before the coat normal and the per-slot coordinate maps:
        // every slot reads the one stream as stored.
        m.coat_normal_texture = MaterialRecord::NO_TEXTURE;
        m.uv_transforms = [MaterialRecord::IDENTITY_UV; MaterialRecord::SLOTS];
    }
}

/// `read_table`, letting the kernel drop each stretch of the table's mapped pages once it
/// is read: millions of instance records would otherwise be resident twice, as mapped file
/// pages and as records (were they touched again, they would be read back from the file).
fn read_released<T: bytemuck::Pod>(map: &memmap2::Mmap, t: &TableRef) -> Vec<T> {
    const STRETCH: u32 = 1 << 16;
    let mut out = Vec::with_capacity(t.count as usize);
    let mut first = 0;
    while first < t.count {
        let part = TableRef {
            offset: t.offset + first as u64 * t.record_size as u64,
            count: STRETCH.min(t.count - first),
            ..*t
        };
        out.extend(read_table::<T>(map, &part));
        let len = part.count as usize * part.record_size as usize;
        // SAFETY: the map is a read-only shared mapping of the file; dropping its pages
        // changes no byte anyone reads through it.
        let _ = unsafe {
            map.unchecked_advise_range(
                memmap2::UncheckedAdvice::DontNeed,
                part.offset as usize,
                len,
            )
        };
        first += part.count;
    }
    out
}

/// A table's records (its range is inside the file: `check_table_ranges`); bytes past the
/// known record size are a later minor version's and are skipped.
fn read_table<T: bytemuck::Pod>(map: &[u8], t: &TableRef) -> Vec<T> {
    if t.count == 0 {
        // A 2.0 file's instance table is all zero, record size included.
        return Vec::new();
    }
    let at = t.offset as usize;
    // A record of an earlier minor version may be shorter than `T`: its missing fields
    // read as zero.
    let take = (t.record_size as usize).min(std::mem::size_of::<T>());
    map[at..at + t.count as usize * t.record_size as usize]
        .chunks_exact(t.record_size as usize)
        .map(|r| {
            let mut v = T::zeroed();
            bytemuck::bytes_of_mut(&mut v)[..take].copy_from_slice(&r[..take]);
            v
        })
        .collect()
}
