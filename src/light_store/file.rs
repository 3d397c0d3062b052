//! The light store file (`render --integrator cone --store-out`, `--store-in`): the cone
//! integrator's stored light, written once by a pre-pass and read by every tile of a frame,
//! so tiles start from the same light instead of learning it apart (which shows as seams).
//! Specified in `format/FORMAT.md` ("The light store file"); paired with one archive.

use super::keys::Keys;
use super::{Entry, RadianceStore};
use anyhow::{bail, Context, Result};
use bytemuck::{Pod, Zeroable};
use canopy_format::atomic::AtomicFile;
use canopy_format::Header;
use std::io::Read;
use std::path::Path;

const MAGIC: [u8; 8] = *b"CNPYSTOR";
const VERSION: u16 = 3;

/// The 128-byte header.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub struct StoreHeader {
    magic: [u8; 8],
    version_major: u16,
    version_minor: u16,
    header_size: u32,
    /// The archive's `header_checksum`, `file_len` and `nodes`.
    archive_checksum: u64,
    archive_len: u64,
    archive_nodes: u64,
    pub entries: u64,
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

impl StoreHeader {
    fn checksum(&self) -> u64 {
        let mut c = *self;
        c.header_checksum = 0;
        xxhash_rust::xxh3::xxh3_64(bytemuck::bytes_of(&c))
    }

    /// Sets the body's length and checksum, then the header's own checksum.
    fn seal(&mut self, body: &[u8]) {
        self.body_len = body.len() as u64;
        self.body_checksum = xxhash_rust::xxh3::xxh3_64(body);
        self.header_checksum = self.checksum();
    }
}

/// Recomputes a store file's body length and both checksums in place, so that only what
/// was edited is wrong (for tools that craft damaged stores: the fuzz harness, tests).
pub fn reseal(file: &mut [u8]) {
    if file.len() < 128 {
        return;
    }
    let (head, body) = file.split_at_mut(128);
    let mut h: StoreHeader = bytemuck::pod_read_unaligned(head);
    h.seal(body);
    head.copy_from_slice(bytemuck::bytes_of(&h));
}

/// Reads a store file's header (at least 128 bytes), for tools that edit it.
pub fn header_of(file: &[u8]) -> Option<StoreHeader> {
    file.get(..128).map(bytemuck::pod_read_unaligned)
}

/// Writes a header back into a store file's first 128 bytes.
pub fn set_header(file: &mut [u8], h: &StoreHeader) {
    file[..128].copy_from_slice(bytemuck::bytes_of(h));
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
        ..Zeroable::zeroed()
    };
    h.seal(&body);
    // The archive writer's atomic file: the header goes in last, the name only once whole.
    let mut out = AtomicFile::create(path, 128)?;
    out.write_all(&body)?;
    out.commit(bytemuck::bytes_of(&h))?;
    Ok(records.len() as u64)
}

/// Fills `store` from `path`, which must belong to the archive of header `a` and have been
/// counted under the same sample limit. Every declared size is checked before anything is
/// allocated or inflated: the entry count against the key space and the budget's share of
/// the store, the body's length against what that many entries can compress to; the body
/// is inflated one record at a time, and every value is checked before any is used.
pub fn load(store: &RadianceStore, a: &Header, path: &Path) -> Result<u64> {
    let name = path.display();
    crate::import::check_regular(path, u64::MAX, "light store")?;
    let mut file = std::fs::File::open(path).with_context(|| format!("{name}: cannot open"))?;
    let len = file
        .metadata()
        .with_context(|| format!("{name}: cannot stat"))?
        .len();
    let mut head = [0u8; 128];
    if len < 128 || file.read_exact(&mut head).is_err() || head[..8] != MAGIC {
        bail!("{name}: not a canopy light store (bad magic or shorter than its header)");
    }
    let h: StoreHeader = bytemuck::pod_read_unaligned(&head);
    let keys = Keys::new(a).map_or(0, |k| k.count());
    check_header(&h, a, store, (keys, len)).map_err(|e| anyhow::anyhow!("{name}: {e}"))?;
    // The body streams through its checksum and the decoder: no buffer of its size.
    let mut body = std::io::BufReader::new(Hashed::new(file.take(h.body_len)));
    let entries = read_records(&mut body, &h, keys).map_err(|e| anyhow::anyhow!("{name}: {e}"));
    std::io::copy(&mut body, &mut std::io::sink())
        .with_context(|| format!("{name}: cannot read the body"))?;
    let hashed = body.into_inner();
    if hashed.len != h.body_len || hashed.digest() != h.body_checksum {
        bail!("{name}: the light store's body is truncated or corrupt (checksum mismatch)");
    }
    let entries = entries?;
    let n = entries.len() as u64;
    if store.restore(entries, h.photons).is_none() {
        bail!(
            "{name}: {n} entries, more than the memory budget's share holds ({})",
            store.capacity()
        );
    }
    Ok(n)
}

/// The header's own checks, its identity against the archive, and its sizes against the
/// archive's `keys`, the budget's share of the store and the file's length `len`.
fn check_header(
    h: &StoreHeader,
    a: &Header,
    store: &RadianceStore,
    (keys, len): (u64, u64),
) -> Result<()> {
    if h.checksum() != h.header_checksum {
        bail!("the light store's header is corrupt (checksum mismatch)");
    }
    if h.version_major != VERSION {
        bail!(
            "light store version {}.{} (this canopy reads {VERSION}.x)",
            h.version_major,
            h.version_minor
        );
    }
    if h.header_size != 128 {
        bail!("header_size {}, not 128", h.header_size);
    }
    if h.reserved0 != 0 || h.reserved != [0; 40] {
        bail!("reserved header bytes are not zero");
    }
    if (h.archive_checksum, h.archive_len, h.archive_nodes)
        != (a.header_checksum, a.file_len, a.nodes)
    {
        bail!("the light store belongs to another archive (its checksum {:016x}, this archive's {:016x})", h.archive_checksum, a.header_checksum);
    }
    if h.limit != store.limit {
        let flag = |n: u32| match n {
            u32::MAX => "no --cone-samples".to_string(),
            n => format!("--cone-samples {n}"),
        };
        bail!(
            "stored under {}, this render uses {}",
            flag(h.limit),
            flag(store.limit)
        );
    }
    if h.entries > keys {
        bail!(
            "entries {} is more than the archive has keys ({keys})",
            h.entries
        );
    }
    if h.entries > store.capacity() as u64 {
        bail!(
            "entries {}, more than the memory budget's share of the store holds ({})",
            h.entries,
            store.capacity()
        );
    }
    let most = zstd::zstd_safe::compress_bound(
        h.entries.saturating_mul(RECORD).min(usize::MAX as u64 / 2) as usize,
    ) as u64;
    if h.body_len > most {
        bail!(
            "body_len {} for {} entries (at most {most} bytes)",
            h.body_len,
            h.entries
        );
    }
    if len != 128 + h.body_len {
        bail!(
            "the light store is truncated or corrupt: the file has {len} bytes, its header says {} (128 + body_len)",
            128 + h.body_len
        );
    }
    Ok(())
}

/// Bytes of one record.
const RECORD: u64 = size_of::<Record>() as u64;

/// The body's records, inflated one at a time and each checked: exactly `entries` of them,
/// keys increasing below `keys`, values finite, counts within the limit.
fn read_records(
    body: &mut impl std::io::BufRead,
    h: &StoreHeader,
    keys: u64,
) -> Result<Vec<(u64, Entry)>> {
    let want = h.entries.saturating_mul(RECORD);
    let head = body.fill_buf().context("cannot read the body")?;
    if let Ok(Some(size)) = zstd::zstd_safe::get_frame_content_size(head) {
        if size != want {
            bail!(
                "entries {} declared ({want} bytes), the body's frame holds {size} bytes",
                h.entries
            );
        }
    }
    let mut z = zstd::stream::read::Decoder::with_buffer(body)
        .context("the light store's body does not decompress")?
        .single_frame();
    let mut entries = Vec::with_capacity(h.entries.min(1 << 16) as usize);
    let mut last = None;
    for i in 0..h.entries {
        let mut r: Record = Zeroable::zeroed();
        let got = read_full(&mut z, bytemuck::bytes_of_mut(&mut r))
            .context("the light store's body does not decompress")?;
        if got < RECORD as usize {
            bail!("entries {} declared, {i} stored", h.entries);
        }
        check_record(&r, h.limit, keys, last)
            .map_err(|e| anyhow::anyhow!("entry {i} (key {}): {e}", r.key))?;
        last = Some(r.key);
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
    let mut more = [0u8; 1];
    if read_full(&mut z, &mut more).context("the light store's body does not decompress")? > 0 {
        bail!(
            "the body holds more than the {} entries declared",
            h.entries
        );
    }
    Ok(entries)
}

/// A reader that hashes (xxh3-64) and counts what passes through it.
struct Hashed<R> {
    inner: R,
    hash: xxhash_rust::xxh3::Xxh3,
    len: u64,
}

impl<R> Hashed<R> {
    fn new(inner: R) -> Hashed<R> {
        Hashed {
            inner,
            hash: xxhash_rust::xxh3::Xxh3::new(),
            len: 0,
        }
    }

    fn digest(&self) -> u64 {
        self.hash.digest()
    }
}

impl<R: Read> Read for Hashed<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.hash.update(&buf[..n]);
        self.len += n as u64;
        Ok(n)
    }
}

/// Reads until `buf` is full or the stream ends; returns the bytes read.
fn read_full(r: &mut impl Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut at = 0;
    while at < buf.len() {
        match r.read(&mut buf[at..])? {
            0 => break,
            n => at += n,
        }
    }
    Ok(at)
}

/// One record against FORMAT.md's rules; `last` is the previous record's key.
fn check_record(r: &Record, limit: u32, keys: u64, last: Option<u64>) -> Result<()> {
    let finite = r
        .sum
        .iter()
        .chain(&r.pulled)
        .chain(&r.caustic)
        .chain([&r.weight])
        .all(|v| v.is_finite());
    if !finite {
        bail!("a non-finite value");
    }
    if last.is_some_and(|l| l >= r.key) {
        bail!("keys not increasing");
    }
    if r.key >= keys {
        bail!("key outside the archive's {keys} keys");
    }
    if r.weight < 0.0 || (r.n > 0 && r.weight <= 0.0) {
        bail!("weight {} for n {}", r.weight, r.n);
    }
    if r.n > limit {
        bail!("n {} over the limit {limit}", r.n);
    }
    if !(0.0..=1.0).contains(&r.visible) {
        bail!("visible {} outside [0, 1]", r.visible);
    }
    if r.reserved != 0 {
        bail!("reserved bytes are not zero");
    }
    Ok(())
}
