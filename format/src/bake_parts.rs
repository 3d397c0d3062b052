//! A bake file taken apart and put back, for tools that craft damaged files (the fuzz
//! harness, tests): what they edit stays wrong, and every offset and checksum around it is
//! recomputed, so the damage reaches the decoder instead of stopping at a checksum.

use crate::bake::{BakeHeader, BlockEntry};

/// The header, the block table, and each block's bytes decompressed.
#[derive(Clone)]
pub struct BakeParts {
    pub header: BakeHeader,
    pub entries: Vec<BlockEntry>,
    pub blocks: Vec<Vec<u8>>,
}

impl BakeParts {
    /// Takes apart a well-formed file (as `canopy bake` writes it); None otherwise.
    pub fn read(bytes: &[u8]) -> Option<BakeParts> {
        let header: BakeHeader = bytemuck::pod_read_unaligned(bytes.get(..128)?);
        let at = header.blocks_offset as usize;
        let table = bytes.get(at..at + 32 * header.pages as usize)?;
        let entries: Vec<BlockEntry> = bytemuck::pod_collect_to_vec(table);
        let blocks = entries
            .iter()
            .map(|e| {
                let from = e.offset as usize;
                zstd::decode_all(bytes.get(from..from + e.compressed_len as usize)?).ok()
            })
            .collect::<Option<Vec<_>>>()?;
        Some(BakeParts {
            header,
            entries,
            blocks,
        })
    }

    /// The file with every block's offset, compressed length and checksum, the table's
    /// place and checksum, the file's length and the header's checksum recomputed; the
    /// declared sizes (`raw_len`, the counts, `coef_bytes`) are kept as they are.
    pub fn write(&self) -> Vec<u8> {
        let mut out = vec![0u8; 128];
        let mut entries = self.entries.clone();
        for (e, raw) in entries.iter_mut().zip(&self.blocks) {
            let z = zstd::bulk::compress(raw, 3).expect("zstd compresses");
            e.offset = out.len() as u64;
            e.compressed_len = z.len() as u32;
            e.checksum = xxhash_rust::xxh3::xxh3_64(&z);
            out.extend(z);
        }
        let table: &[u8] = bytemuck::cast_slice(&entries);
        let mut h = self.header;
        h.blocks_offset = out.len() as u64;
        h.file_len = h.blocks_offset + table.len() as u64;
        h.blocks_checksum = xxhash_rust::xxh3::xxh3_64(table);
        h.header_checksum = 0;
        h.header_checksum = xxhash_rust::xxh3::xxh3_64(bytemuck::bytes_of(&h));
        out.extend_from_slice(table);
        out[..128].copy_from_slice(bytemuck::bytes_of(&h));
        out
    }
}
