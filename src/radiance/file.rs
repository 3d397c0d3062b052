//! The light store file (`render --integrator cone --store-out`, `--store-in`): the cone
//! integrator's stored light, written once by a pre-pass and read by every tile of a frame,
//! so tiles start from the same light instead of learning it apart (which shows as seams).
//! Specified in `format/FORMAT.md` ("The light store file"); paired with one archive.

use super::{Entry, RadianceStore};
use anyhow::{bail, Context, Result};
use bytemuck::{Pod, Zeroable};
use canopy_format::atomic::AtomicFile;
use canopy_format::Header;
use std::path::Path;

const MAGIC: [u8; 8] = *b"CNPYSTOR";
const VERSION: u16 = 3;

/// The 128-byte header.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct StoreHeader {
    magic: [u8; 8],
    version_major: u16,
    version_minor: u16,
    header_size: u32,
    /// The archive's `header_checksum`, `file_len` and `nodes`.
    archive_checksum: u64,
    archive_len: u64,
    archive_nodes: u64,
    entries: u64,
    photons: u64,
    /// The sample limit (`--cone-samples`) the entries were counted under.
    limit: u32,
    reserved0: u32,
    body_len: u64,
    body_checksum: u64,
    header_checksum: u64,
    reserved: [u8; 40],
}

const _: () = assert!(std::mem::size_of::<StoreHeader>() == 128);

/// One record of the body (64 bytes): the key and the entry's fields in order.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Record {
    key: u64,
    sum: [f32; 3],
    weight: f32,
    n: u32,
    pulled: [f32; 3],
    pulled_n: u32,
    caustic: [f32; 3],
    visible: f32,
    reserved: u32,
}

const _: () = assert!(std::mem::size_of::<Record>() == 64);

fn checksum(h: &StoreHeader) -> u64 {
    let mut c = *h;
    c.header_checksum = 0;
    xxhash_rust::xxh3::xxh3_64(bytemuck::bytes_of(&c))
}

/// Writes `store` for the archive of header `a` to `path`: the file appears only complete.
pub fn save(store: &RadianceStore, a: &Header, path: &Path) -> Result<u64> {
    let records: Vec<Record> = store
        .sorted()
        .into_iter()
        .map(|(key, e)| Record {
            key,
            sum: e.sum,
            weight: e.weight,
            n: e.n,
            pulled: e.pulled,
            pulled_n: e.pulled_n,
            caustic: e.caustic,
            visible: e.visible,
            reserved: 0,
        })
        .collect();
    let body = zstd::bulk::compress(bytemuck::cast_slice(&records), 1)?;
    let mut h = StoreHeader {
        magic: MAGIC,
        version_major: VERSION,
        version_minor: 0,
        header_size: 128,
        archive_checksum: a.header_checksum,
        archive_len: a.file_len,
        archive_nodes: a.nodes,
        entries: records.len() as u64,
        photons: store.photons(),
        limit: store.limit,
        body_len: body.len() as u64,
        body_checksum: xxhash_rust::xxh3::xxh3_64(&body),
        ..Zeroable::zeroed()
    };
    h.header_checksum = checksum(&h);
    // The archive writer's atomic file: the header goes in last, the name only once whole.
    let mut out = AtomicFile::create(path, 128)?;
    out.write_all(&body)?;
    out.commit(bytemuck::bytes_of(&h))?;
    Ok(records.len() as u64)
}

/// Fills `store` from `path`, which must belong to the archive of header `a` and have been
/// counted under the same sample limit; every value is checked before any is used.
pub fn load(store: &RadianceStore, a: &Header, path: &Path) -> Result<u64> {
    let name = path.display();
    let bytes = crate::import::read_regular(path, u64::MAX, "light store")?;
    if bytes.len() < 128 || bytes[..8] != MAGIC {
        bail!("{name}: not a canopy light store (bad magic or shorter than its header)");
    }
    let h: StoreHeader = bytemuck::pod_read_unaligned(&bytes[..128]);
    if checksum(&h) != h.header_checksum {
        bail!("{name}: the light store's header is corrupt (checksum mismatch)");
    }
    if h.version_major != VERSION || h.header_size != 128 {
        bail!(
            "{name}: light store version {} (this canopy reads {VERSION})",
            h.version_major
        );
    }
    if (h.archive_checksum, h.archive_len, h.archive_nodes)
        != (a.header_checksum, a.file_len, a.nodes)
    {
        bail!("{name}: the light store belongs to another archive (its checksum {:016x}, this archive's {:016x})", h.archive_checksum, a.header_checksum);
    }
    if h.limit != store.limit {
        let flag = |n: u32| match n {
            u32::MAX => "no --cone-samples".to_string(),
            n => format!("--cone-samples {n}"),
        };
        bail!(
            "{name}: stored under {}, this render uses {}",
            flag(h.limit),
            flag(store.limit)
        );
    }
    let body = &bytes[128..];
    if body.len() as u64 != h.body_len || xxhash_rust::xxh3::xxh3_64(body) != h.body_checksum {
        bail!("{name}: the light store is truncated or corrupt ({} body bytes, {} expected, or a checksum mismatch)", body.len(), h.body_len);
    }
    let want = h
        .entries
        .checked_mul(size_of::<Record>() as u64)
        .filter(|&n| n <= 1 << 40)
        .with_context(|| format!("{name}: {} entries is absurd", h.entries))?;
    let raw = zstd::bulk::decompress(body, want as usize)
        .with_context(|| format!("{name}: the light store's body does not decompress"))?;
    if raw.len() as u64 != want {
        bail!(
            "{name}: {} entries declared, {} bytes of them stored",
            h.entries,
            raw.len()
        );
    }
    let records: Vec<Record> = bytemuck::pod_collect_to_vec(&raw);
    let mut entries = Vec::with_capacity(records.len());
    for (i, r) in records.iter().enumerate() {
        let finite = r
            .sum
            .iter()
            .chain(&r.pulled)
            .chain(&r.caustic)
            .chain([&r.weight])
            .all(|v| v.is_finite());
        let sorted = i == 0 || records[i - 1].key < r.key;
        let weighed = r.weight >= 0.0 && (r.n == 0 || r.weight > 0.0);
        if !finite || !sorted || !weighed || r.n > h.limit || !(0.0..=1.0).contains(&r.visible) {
            bail!(
                "{name}: entry {i} (key {}) is not a valid stored value",
                r.key
            );
        }
        let e = Entry {
            sum: r.sum,
            weight: r.weight,
            n: r.n,
            pulled: r.pulled,
            pulled_n: r.pulled_n,
            caustic: r.caustic,
            visible: r.visible,
        };
        entries.push((r.key, e));
    }
    let n = entries.len() as u64;
    if store.restore(entries, h.photons).is_none() {
        bail!(
            "{name}: {n} entries, more than the memory budget's share holds ({})",
            store.capacity()
        );
    }
    Ok(n)
}
