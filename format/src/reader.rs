//! Reading an archive over a memory map. Every length and offset is checked against the file
//! size before any mapped byte is touched, so a truncated or corrupt file is an error, never
//! a SIGBUS or a panic. (A file truncated by another process *while* mapped is outside what a
//! reader can defend against.)

use crate::codec::Grid;
use crate::error::{FormatError, Result};
use crate::node::{Node, Tri};
use crate::records::*;
use crate::validate::*;
use crate::writer::PageContents;
use std::path::{Path, PathBuf};

pub struct Archive {
    path: PathBuf,
    map: memmap2::Mmap,
    pub header: Header,
    pub materials: Vec<MaterialRecord>,
    pub cameras: Vec<CameraRecord>,
    pub lights: Vec<LightRecord>,
    pub pages: Vec<PageEntry>,
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
        if header.version_major > VERSION_MAJOR {
            return Err(FormatError::NewerVersion {
                path: p,
                major: header.version_major,
                minor: header.version_minor,
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
        let tables_start = header.materials.offset;
        if tables_start < 256 || tables_start > len {
            return Err(corrupt(format!(
                "table offset {tables_start} outside the file"
            )));
        }
        if xxhash_rust::xxh3::xxh3_64(&map[tables_start as usize..]) != header.tables_checksum {
            return Err(corrupt("table checksum mismatch".into()));
        }
        check_table_ranges(&header).map_err(&corrupt)?;
        let materials =
            read_table::<MaterialRecord>(&map, &header.materials, "material table", &p)?;
        let cameras = read_table::<CameraRecord>(&map, &header.cameras, "camera table", &p)?;
        let lights = read_table::<LightRecord>(&map, &header.lights, "light table", &p)?;
        let pages = read_table::<PageEntry>(&map, &header.pages, "page table", &p)?;
        if pages.is_empty() || header.root_page as usize >= pages.len() {
            return Err(corrupt(format!(
                "root page {} of {} pages",
                header.root_page,
                pages.len()
            )));
        }
        check_tables(&header, &materials, &cameras, &lights).map_err(&corrupt)?;
        check_page_tree(&header, &pages).map_err(|(page, what)| FormatError::BadPage {
            path: p.clone(),
            page,
            what,
        })?;
        check_page_extents(&header, &pages, tables_start).map_err(|e| match e {
            (Some(page), what) => FormatError::BadPage {
                path: p.clone(),
                page,
                what,
            },
            (None, what) => corrupt(what),
        })?;
        Ok(Self {
            path: p,
            map,
            header,
            materials,
            cameras,
            lights,
            pages,
        })
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
        let e = self
            .pages
            .get(page as usize)
            .ok_or_else(|| self.page_err(page, "no such page"))?;
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
        let e = &self.pages[page as usize];
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
        let has_normals = self.header.features & Features::SHADING_NORMALS != 0;
        if h.magic != PAGE_MAGIC
            || (h.node_count, h.tri_count, h.vert_count, h.coef_bytes)
                != (e.node_count, e.tri_count, e.vert_count, e.coef_bytes)
            || (h.has_normals != 0) != has_normals
        {
            return Err(self.page_err(page, "page header disagrees with the page table"));
        }
        let mut at = 32;
        let mut take = |n: usize| {
            let s = &raw[at..at + n];
            at += n;
            s
        };
        let nodes: Vec<Node> = bytemuck::pod_collect_to_vec(take(h.node_count as usize * 128));
        let tris: Vec<Tri> = bytemuck::pod_collect_to_vec(take(h.tri_count as usize * 8));
        let verts: Vec<[f32; 3]> = bytemuck::pod_collect_to_vec(take(h.vert_count as usize * 12));
        let normals: Vec<u32> = if has_normals {
            bytemuck::pod_collect_to_vec(take(h.vert_count as usize * 4))
        } else {
            Vec::new()
        };
        let coefs = take(h.coef_bytes as usize).to_vec();
        let contents = PageContents {
            nodes,
            tris,
            verts,
            normals,
            coefs,
        };
        self.check_indices(page, &contents)?;
        Ok(contents)
    }

    fn check_indices(&self, page: u32, c: &PageContents) -> Result<()> {
        check_page(&self.header, self.materials.len(), &self.pages, page, c)
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
    pub fn grid(&self, page: u32) -> Grid {
        self.pages[page as usize].grid()
    }
}

fn read_table<T: bytemuck::Pod>(map: &[u8], t: &TableRef, what: &str, p: &Path) -> Result<Vec<T>> {
    let size = std::mem::size_of::<T>() as u32;
    if t.record_size != size {
        return Err(FormatError::Corrupt {
            path: p.to_path_buf(),
            what: format!("{what}: record size {} (expected {size})", t.record_size),
        });
    }
    let end = t
        .offset
        .checked_add(t.count as u64 * size as u64)
        .filter(|&e| e <= map.len() as u64);
    let Some(end) = end else {
        return Err(FormatError::Truncated {
            path: p.to_path_buf(),
            what: what.into(),
            needed: t.offset + t.count as u64 * size as u64,
            len: map.len() as u64,
        });
    };
    Ok(bytemuck::pod_collect_to_vec(
        &map[t.offset as usize..end as usize],
    ))
}
