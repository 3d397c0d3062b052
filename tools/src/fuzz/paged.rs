//! Instance records where an archive keeps them: in the pages that hold their leaves (2.7,
//! `PAGED_INSTANCES`), read and edited in place; and an archive rewritten as 2.6 wrote it,
//! the records in the instance table, so readers of both layouts are exercised.

use super::Parts;
use canopy_format::records::*;
use canopy_format::Node;

const RECORD: usize = std::mem::size_of::<InstanceRecord>();

/// The page holding instance `k` and the byte offset of its record in the page: records are
/// the page's last stream.
fn locate(p: &Parts, k: u32) -> Option<(usize, usize)> {
    let page = p
        .entries
        .iter()
        .position(|e| (e.first_instance..e.first_instance + e.instance_count).contains(&k))?;
    let e = &p.entries[page];
    let from_end = (e.first_instance + e.instance_count - k) as usize * RECORD;
    Some((page, p.pages[page].len() - from_end))
}

/// Instance `k`'s record, wherever the archive keeps it.
pub fn record(p: &Parts, k: u32) -> Option<InstanceRecord> {
    if !p.instances.is_empty() {
        return p.instances.get(k as usize).copied();
    }
    let (page, at) = locate(p, k)?;
    Some(bytemuck::pod_read_unaligned(
        &p.pages[page][at..at + RECORD],
    ))
}

/// Changes instance `k`'s record in place (nothing if there is no such instance).
pub fn edit_record(p: &mut Parts, k: u32, f: impl FnOnce(&mut InstanceRecord)) {
    if !p.instances.is_empty() {
        if let Some(r) = p.instances.get_mut(k as usize) {
            f(r);
        }
        return;
    }
    let Some((page, at)) = locate(p, k) else {
        return;
    };
    let mut r: InstanceRecord = bytemuck::pod_read_unaligned(&p.pages[page][at..at + RECORD]);
    f(&mut r);
    p.pages[page][at..at + RECORD].copy_from_slice(bytemuck::bytes_of(&r));
}

/// The archive as version 2.6 wrote it: every page's records moved, in instance order, to
/// the instance table, its instance leaves naming them by number, and the
/// `PAGED_INSTANCES` feature and page counts cleared. Unchanged without paged instances.
pub fn unpaged(p: &Parts) -> Parts {
    let mut out = p.clone();
    if p.header.features & Features::PAGED_INSTANCES == 0 {
        return out;
    }
    out.header.version_minor = 6;
    out.header.features &= !Features::PAGED_INSTANCES;
    let node_size = p.header.node_size as usize;
    for (raw, e) in out.pages.iter_mut().zip(&mut out.entries) {
        let keep = raw.len() - e.instance_count as usize * RECORD;
        out.instances
            .extend(bytemuck::pod_collect_to_vec::<u8, InstanceRecord>(
                &raw[keep..],
            ));
        raw.truncate(keep);
        for n in 0..e.node_count as usize {
            let at = 32 + n * node_size;
            let mut node: Node = bytemuck::pod_read_unaligned(&raw[at..at + 128]);
            if node.is_instance() {
                node.link[0] += e.first_instance;
                raw[at..at + 128].copy_from_slice(bytemuck::bytes_of(&node));
            }
        }
        raw[16..20].fill(0);
        e.raw_len = keep as u32;
        (e.instance_count, e.first_instance) = (0, 0);
    }
    out
}
