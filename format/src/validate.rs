//! Structural checks of what an archive claims, beyond its checksums: a file whose checksums
//! were recomputed after it was altered must still be refused before any value reaches the
//! renderer. `check_header`, `check_table_ranges` and `check_tables` run at open (they cost
//! O(materials + cameras + lights), nothing per page); `check_entry` runs on every page-table
//! entry read and `check_page` on every decoded page, linear in its size. What only the
//! whole page table shows (nodes numbered consecutively, every page linked once) is
//! `verify`'s.

use crate::records::*;
pub use crate::validate_page::{check_entry, check_page};

/// Most triangles a leaf may hold in a version-1 archive (the node's cluster slots and the
/// renderer's per-leaf keys assume it).
pub const MAX_LEAF_TRIANGLES: u32 = 8;
/// Most nodes a page may hold (a page's local indices and the converter's limit).
pub const MAX_PAGE_NODES: u32 = 1 << 16;
/// Longest root-to-leaf path accepted, in edges.
pub const MAX_TREE_DEPTH: u32 = 250;
/// Largest camera resolution a record may ask for.
pub const MAX_SIDE: u32 = 32768;

pub(crate) fn finite(v: &[f32]) -> bool {
    v.iter().all(|x| x.is_finite())
}

fn in_unit(v: &[f32]) -> bool {
    v.iter().all(|x| (0.0..=1.0).contains(x))
}

pub(crate) fn non_negative(v: &[f32]) -> bool {
    v.iter().all(|x| x.is_finite() && *x >= 0.0)
}

pub(crate) fn zeroed(b: &[u8]) -> bool {
    b.iter().all(|&x| x == 0)
}

/// A box with finite corners and min ≤ max on every axis.
pub fn box_ok(lo: &[f32; 3], hi: &[f32; 3]) -> bool {
    finite(lo) && finite(hi) && (0..3).all(|a| lo[a] <= hi[a])
}

/// Header fields that do not depend on the tables.
pub fn check_header(h: &Header) -> Result<(), String> {
    if h.version_major != VERSION_MAJOR {
        return Err(format!(
            "format version {} is not {VERSION_MAJOR}",
            h.version_major
        ));
    }
    let unknown = h.features & Features::REQUIRED & !Features::ALL;
    if unknown != 0 {
        return Err(format!(
            "required feature bits {unknown:#x} unknown to this reader"
        ));
    }
    if h.features & Features::TEXCOORDS2 != 0
        && (h.features & Features::TEXCOORDS == 0 || h.version_minor < 6)
    {
        return Err("a second texture-coordinate stream without the first, or before 2.6".into());
    }
    if paged_instances(h) {
        let t = h.instances;
        if h.features & Features::INSTANCES == 0 || h.version_minor < 7 {
            return Err("paged instance records without instances, or before 2.7".into());
        }
        if t.record_size != 0 || t.count == 0 || t.count > MAX_INSTANCES {
            return Err(format!(
                "{} paged instances with a table of {}-byte records (1 to {MAX_INSTANCES}, no bytes: the records are in the pages)",
                t.count, t.record_size
            ));
        }
    }
    if h.node_size < NODE_SIZE || !h.node_size.is_multiple_of(8) || h.node_size > 4096 {
        return Err(format!(
            "node records of {} bytes (at least {NODE_SIZE}, a multiple of 8)",
            h.node_size
        ));
    }
    // Instanced triangles are stored once per prototype; anything else is stored as read.
    let instanced = h.features & Features::INSTANCES != 0;
    if h.input_triangles != h.triangles && !(instanced && h.input_triangles > h.triangles) {
        return Err(format!(
            "{} input triangles but {} stored",
            h.input_triangles, h.triangles
        ));
    }
    if !box_ok(&h.bounds_min, &h.bounds_max) {
        return Err(format!(
            "scene bounds {:?}..{:?} are not a finite box",
            h.bounds_min, h.bounds_max
        ));
    }
    if h.depth > MAX_TREE_DEPTH {
        return Err(format!("tree depth {} (at most {MAX_TREE_DEPTH})", h.depth));
    }
    if !(1..=MAX_LEAF_TRIANGLES).contains(&h.max_leaf_triangles) {
        return Err(format!(
            "{} triangles per leaf (1 to {MAX_LEAF_TRIANGLES})",
            h.max_leaf_triangles
        ));
    }
    if !(1..=MAX_PAGE_NODES).contains(&h.page_nodes_max) {
        return Err(format!(
            "{} nodes per page (1 to {MAX_PAGE_NODES})",
            h.page_nodes_max
        ));
    }
    // Every page holds at least one node and at most `page_nodes_max`: readers size
    // per-node tables by `nodes`, so it must be bounded by what the pages can hold.
    let pages = h.pages.count as u64;
    if h.nodes < pages || h.nodes > pages * h.page_nodes_max as u64 {
        return Err(format!(
            "{} nodes in {pages} pages of at most {} nodes",
            h.nodes, h.page_nodes_max
        ));
    }
    // A newer minor version may give the reserved bytes a meaning; 2.0 had no instances,
    // 2.1 no textures, 2.2 no environment, 2.3 no notes.
    if h.version_minor <= 3 && h.notes != 0
        || h.version_minor == 0 && h.instances != TableRef::default()
        || h.version_minor <= 1
            && (h.textures != TableRef::default() || h.tiles != TableRef::default())
        || h.version_minor <= 2 && h.environment != TableRef::default()
    {
        return Err("reserved header bytes are not zero".into());
    }
    Ok(())
}

/// The tables after the pages, in file order, with their known record sizes: the instance
/// table exists from version 2.1.
pub fn small_tables(h: &Header) -> Vec<(&'static str, TableRef, usize)> {
    let mut t = vec![
        ("material", h.materials, material_record_size(h)),
        ("camera", h.cameras, std::mem::size_of::<CameraRecord>()),
        ("light", h.lights, std::mem::size_of::<LightRecord>()),
    ];
    if h.version_minor >= 1 {
        let known = match paged_instances(h) {
            true => 0,
            false => std::mem::size_of::<InstanceRecord>(),
        };
        t.push(("instance", h.instances, known));
    }
    if h.version_minor >= 2 {
        t.push(("texture", h.textures, std::mem::size_of::<TextureRecord>()));
        t.push(("tile", h.tiles, std::mem::size_of::<TileEntry>()));
    }
    if h.version_minor >= 3 {
        let known = std::mem::size_of::<EnvironmentRecord>();
        t.push(("environment", h.environment, known));
    }
    if h.version_minor >= 4 {
        t.push(("note", notes_table(h), std::mem::size_of::<NoteRecord>()));
    }
    t
}

/// The material record's known size in `h`'s minor version.
pub fn material_record_size(h: &Header) -> usize {
    match h.version_minor {
        0..=3 => MATERIAL_RECORD_2_3,
        4 => MATERIAL_RECORD_2_4,
        5 => MATERIAL_RECORD_2_5,
        _ => std::mem::size_of::<MaterialRecord>(),
    }
}

/// The note table (2.4): `notes` records of 256 bytes right after the environment table.
pub fn notes_table(h: &Header) -> TableRef {
    let e = &h.environment;
    TableRef {
        offset: e.offset + e.count as u64 * e.record_size as u64,
        count: h.notes,
        record_size: std::mem::size_of::<NoteRecord>() as u32,
    }
}

/// Each note is UTF-8 up to its first zero byte, and zero after it.
pub fn check_notes(notes: &[NoteRecord]) -> Result<Vec<String>, String> {
    notes
        .iter()
        .enumerate()
        .map(|(i, n)| {
            let end = n.text.iter().position(|&b| b == 0).unwrap_or(n.text.len());
            if !zeroed(&n.text[end..]) {
                return Err(format!("note {i}: bytes after its end are not zero"));
            }
            std::str::from_utf8(&n.text[..end])
                .map(str::to_string)
                .map_err(|_| format!("note {i} is not UTF-8"))
        })
        .collect()
}

/// At most one environment, of a known kind, with finite non-negative factors, a sky's
/// values in the model's range and a map's path UTF-8, not empty, zero after its end.
pub fn check_environment(all: &[EnvironmentRecord]) -> Result<(), String> {
    if all.len() > 1 {
        return Err(format!("{} environments (at most one)", all.len()));
    }
    let Some(e) = all.first() else { return Ok(()) };
    let end = e.path.iter().position(|&b| b == 0).unwrap_or(e.path.len());
    first_bad(&[
        (
            "the kind",
            e.kind == EnvironmentRecord::MAP || e.kind == EnvironmentRecord::SKY,
        ),
        ("the strength", non_negative(&[e.strength, e.sun_strength])),
        ("the rotation", e.rotate_degrees.is_finite()),
        (
            "the sky",
            e.kind != EnvironmentRecord::SKY
                || (0.0..=90.0).contains(&e.sun_elevation)
                    && e.sun_azimuth.is_finite()
                    && (1.0..=10.0).contains(&e.turbidity)
                    && (0.0..=1.0).contains(&e.ground_albedo),
        ),
        (
            "the map's path",
            (e.kind != EnvironmentRecord::MAP || end > 0 && !e.path().is_empty())
                && zeroed(&e.path[end..]),
        ),
    ])
}

/// Where the tables the tables checksum covers end.
pub fn small_tables_end(h: &Header) -> u64 {
    let (_, t, _) = *small_tables(h).last().expect("three tables at least");
    t.offset + t.count as u64 * t.record_size as u64
}

/// The material, camera, light (and instance) tables back to back from an aligned offset
/// after the pages; the page table at the next aligned offset, ending at `file_len`. Records at least
/// their known size, a multiple of 8 (readers skip bytes a later minor version adds).
pub fn check_table_ranges(h: &Header) -> Result<(), String> {
    let mut at = h.materials.offset as u128;
    if at < 256 || !at.is_multiple_of(ALIGN as u128) {
        return Err(format!(
            "tables start at {at}, not an aligned offset after the header"
        ));
    }
    let mut tables = small_tables(h);
    tables.push(("page", h.pages, std::mem::size_of::<PageEntry>()));
    for (name, t, known) in tables {
        if name == "page" {
            at = at.next_multiple_of(ALIGN as u128);
        }
        if t.offset as u128 != at {
            return Err(format!(
                "{name} table at {}, expected at {at} (tables are back to back)",
                t.offset
            ));
        }
        if (t.record_size as usize) < known
            || !t.record_size.is_multiple_of(8)
            || t.record_size > 4096
        {
            return Err(format!(
                "{name} records of {} bytes (at least {known}, a multiple of 8)",
                t.record_size
            ));
        }
        at += t.count as u128 * t.record_size as u128;
    }
    if at != h.file_len as u128 {
        return Err(format!(
            "tables end at {at}, the file at {} (the page table is last)",
            h.file_len
        ));
    }
    if h.materials.count > u16::MAX as u32 + 1 {
        return Err(format!(
            "{} materials (a triangle addresses at most 65536)",
            h.materials.count
        ));
    }
    Ok(())
}

/// The first field named in `fields` whose check failed, as an error.
fn first_bad(fields: &[(&str, bool)]) -> Result<(), String> {
    match fields.iter().find(|(_, ok)| !ok) {
        Some((name, _)) => Err(format!("{name} is NaN, infinite or outside its range")),
        None => Ok(()),
    }
}

pub fn check_material(m: &MaterialRecord) -> Result<(), String> {
    first_bad(&[
        ("base colour", in_unit(&m.base_color)),
        ("emission", non_negative(&m.emission)),
        ("metallic", in_unit(&[m.metallic])),
        ("roughness", in_unit(&[m.roughness])),
        ("transmission", in_unit(&[m.transmission])),
        ("specular", in_unit(&[m.specular])),
        ("specular colour", non_negative(&m.specular_color)),
        (
            "ior",
            m.ior.is_finite() && (m.ior >= 1.0 || m.ior == 0.0) && m.ior <= 1e3,
        ),
        ("attenuation colour", in_unit(&m.attenuation_color)),
        ("clearcoat", in_unit(&[m.clearcoat, m.clearcoat_roughness])),
        (
            "sheen",
            in_unit(&m.sheen_color) && in_unit(&[m.sheen_roughness]),
        ),
        (
            "attenuation distance",
            m.attenuation_distance.is_finite() && m.attenuation_distance >= 0.0,
        ),
    ])?;
    let known = MaterialRecord::DOUBLE_SIDED
        | MaterialRecord::TEXTURED
        | MaterialRecord::ALPHA_MASK
        | MaterialRecord::ALPHA_BLEND;
    if m.flags & !known != 0 {
        return Err(format!("unknown flags {:#x}", m.flags));
    }
    let alpha = MaterialRecord::ALPHA_MASK | MaterialRecord::ALPHA_BLEND;
    if m.flags & alpha == alpha {
        return Err("both alpha mask and alpha blend".into());
    }
    first_bad(&[("alpha cutoff", in_unit(&[m.alpha_cutoff]))])?;
    let normal = m.textures[MaterialRecord::NORMAL] != MaterialRecord::NO_TEXTURE;
    if !(m.normal_scale.is_finite() && (normal || m.normal_scale == 0.0)) {
        return Err(format!(
            "normal scale {} (finite with a normal texture, 0 without)",
            m.normal_scale
        ));
    }
    let coat_normal = m.coat_normal_texture != MaterialRecord::NO_TEXTURE;
    if !(m.coat_normal_scale.is_finite() && (coat_normal || m.coat_normal_scale == 0.0)) {
        return Err(format!(
            "clearcoat normal scale {} (finite with a clearcoat normal texture, 0 without)",
            m.coat_normal_scale
        ));
    }
    if m.uv_streams >> MaterialRecord::SLOTS != 0 {
        return Err(format!("texture-coordinate streams {:#x}", m.uv_streams));
    }
    if let Some(s) = (0..MaterialRecord::SLOTS).find(|&s| !finite(&m.uv_transforms[s])) {
        return Err(format!(
            "texture slot {s}: its coordinate map is not finite"
        ));
    }
    Ok(())
}

/// Largest texture accepted: fewer than 2³¹ texels in level 0.
pub const MAX_TEXELS: u64 = (1 << 31) - 1;

/// The texture and tile tables (version 2.2): each texture a full pyramid of at most
/// `MAX_TEXELS` texels whose tiles are the next run of the tile table (textures in order,
/// every tile used once); tiles inside the page area; every material's texture index in
/// range. `data_end` is where the page area ends.
pub fn check_textures(
    data_end: u64,
    materials: &[MaterialRecord],
    textures: &[TextureRecord],
    tiles: &[TileEntry],
) -> Result<(), String> {
    let mut next = 0u64;
    for (i, t) in textures.iter().enumerate() {
        let texels = t.width as u64 * t.height as u64;
        if t.width == 0 || t.height == 0 || texels > MAX_TEXELS {
            return Err(format!(
                "texture {i}: {}×{} texels (1 to {MAX_TEXELS})",
                t.width, t.height
            ));
        }
        if t.levels != TextureRecord::full_levels(t.width, t.height) {
            return Err(format!("texture {i}: {} MIP levels", t.levels));
        }
        if t.first_tile as u64 != next {
            return Err(format!(
                "texture {i}: tiles from {}, expected from {next}",
                t.first_tile
            ));
        }
        next += t.tile_count();
        if t.flags & !TextureRecord::ALL_FLAGS != 0 || t.wrap(0) > 2 || t.wrap(1) > 2 {
            return Err(format!("texture {i}: unknown flags {:#x}", t.flags));
        }
        first_bad(&[("mean", in_unit(&t.mean))]).map_err(|e| format!("texture {i}: {e}"))?;
        if !zeroed(&t.reserved) {
            return Err(format!("texture {i}: reserved bytes are not zero"));
        }
    }
    if next != tiles.len() as u64 {
        return Err(format!(
            "the textures use {next} tiles, the tile table holds {}",
            tiles.len()
        ));
    }
    for (i, e) in tiles.iter().enumerate() {
        let end = e.offset.checked_add(e.compressed_len as u64);
        if e.offset < 256 || end.is_none_or(|end| end > data_end) {
            return Err(format!(
                "tile {i}: bytes {}+{} outside the data area",
                e.offset, e.compressed_len
            ));
        }
        if e.raw_len != TILE_BYTES || !zeroed(&e.reserved) {
            return Err(format!(
                "tile {i}: raw length {} or reserved bytes",
                e.raw_len
            ));
        }
    }
    for (i, m) in materials.iter().enumerate() {
        if let Some(t) = m
            .slot_textures()
            .into_iter()
            .find(|&t| t != MaterialRecord::NO_TEXTURE && t as usize >= textures.len())
        {
            return Err(format!("material {i}: texture {t} of {}", textures.len()));
        }
    }
    Ok(())
}

pub fn check_camera(c: &CameraRecord) -> Result<(), String> {
    first_bad(&[
        (
            "the transform",
            finite(&c.to_world) && c.to_world[..9].iter().any(|&x| x != 0.0),
        ),
        ("the projection", c.projection <= CameraRecord::ORTHOGRAPHIC),
        (
            "yfov",
            match c.projection {
                CameraRecord::PERSPECTIVE => c.yfov > 0.0 && c.yfov < std::f32::consts::PI,
                _ => c.yfov == 0.0,
            },
        ),
        (
            "ymag",
            match c.projection {
                CameraRecord::PERSPECTIVE => c.ymag == 0.0,
                _ => c.ymag > 0.0 && c.ymag.is_finite(),
            },
        ),
        ("aspect", non_negative(&[c.aspect])),
        ("znear", non_negative(&[c.znear])),
        ("zfar", non_negative(&[c.zfar])),
        (
            "the resolution",
            c.width <= MAX_SIDE && c.height <= MAX_SIDE,
        ),
    ])?;
    if !zeroed(&c.reserved) {
        return Err("reserved bytes are not zero".into());
    }
    Ok(())
}

pub fn check_light(l: &LightRecord) -> Result<(), String> {
    if l.kind > LightRecord::DIRECTIONAL {
        return Err(format!("unknown kind {}", l.kind));
    }
    let d = l.direction;
    let len2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
    first_bad(&[
        ("colour", non_negative(&l.color)),
        ("intensity", non_negative(&[l.intensity])),
        ("range", non_negative(&[l.range])),
        ("position", finite(&l.position)),
        (
            "direction (a unit vector)",
            l.kind == LightRecord::POINT || (len2 - 1.0).abs() < 1e-3,
        ),
        (
            "the cone angles (0 ≤ inner ≤ outer ≤ π/2, a spot's outer > 0)",
            0.0 <= l.inner_cone
                && l.inner_cone <= l.outer_cone
                && l.outer_cone <= std::f32::consts::FRAC_PI_2 + 1e-6
                && (l.kind != LightRecord::SPOT || l.outer_cone > 0.0),
        ),
    ])?;
    if !zeroed(&l.reserved) {
        return Err("reserved bytes are not zero".into());
    }
    Ok(())
}

/// Checks each record of a table, naming the first bad one.
fn check_records<T>(
    records: &[T],
    what: &str,
    check: fn(&T) -> Result<(), String>,
) -> Result<(), String> {
    for (i, r) in records.iter().enumerate() {
        check(r).map_err(|e| format!("{what} {i}: {e}"))?;
    }
    Ok(())
}

/// Every material, camera and light record, and the features that describe the tables.
pub fn check_tables(
    h: &Header,
    materials: &[MaterialRecord],
    cameras: &[CameraRecord],
    lights: &[LightRecord],
) -> Result<(), String> {
    check_records(materials, "material", check_material)?;
    check_records(cameras, "camera", check_camera)?;
    check_records(lights, "light", check_light)?;
    if (h.features & Features::PUNCTUAL_LIGHTS != 0) == lights.is_empty() {
        return Err(format!(
            "the punctual-lights feature disagrees with the {} lights",
            lights.len()
        ));
    }
    let textured = materials
        .iter()
        .any(|m| m.flags & MaterialRecord::TEXTURED != 0);
    if (h.features & Features::TEXTURED_INPUT != 0) != textured {
        return Err("the textured-input feature disagrees with the materials".into());
    }
    Ok(())
}

/// Most instances an archive may hold (a node's instance link leaves room for a kind tag).
pub const MAX_INSTANCES: u32 = 1 << 29;

/// Whether the archive's instance records travel in its pages (2.7's PAGED_INSTANCES)
/// rather than in the instance table.
pub fn paged_instances(h: &Header) -> bool {
    h.features & Features::PAGED_INSTANCES != 0
}

/// The instance table (archives before 2.7): each record as `check_instance`, and the
/// INSTANCES feature set exactly when there are some. With PAGED_INSTANCES the table holds
/// no records (the header's check) and each page's are checked when it is read. That each
/// prototype page is a tree's root page is `Archive::open`'s check (it reads entries).
pub fn check_instances(h: &Header, instances: &[InstanceRecord]) -> Result<(), String> {
    if paged_instances(h) {
        return Ok(());
    }
    if (h.features & Features::INSTANCES != 0) == instances.is_empty() {
        return Err(format!(
            "the instances feature disagrees with the {} instances",
            instances.len()
        ));
    }
    if instances.len() > MAX_INSTANCES as usize {
        return Err(format!(
            "{} instances (at most {MAX_INSTANCES})",
            instances.len()
        ));
    }
    for (i, r) in instances.iter().enumerate() {
        check_instance(h, r).map_err(|e| format!("instance {i}: {e}"))?;
    }
    Ok(())
}

/// One instance record: a finite, invertible transform, a prototype page in range, zero
/// reserved bytes.
pub fn check_instance(h: &Header, r: &InstanceRecord) -> Result<(), String> {
    check_transform(r)?;
    if r.prototype_page >= h.pages.count {
        return Err(format!(
            "prototype page {} of {} pages",
            r.prototype_page, h.pages.count
        ));
    }
    if !zeroed(&r.reserved) {
        return Err("reserved bytes are not zero".into());
    }
    Ok(())
}

/// An instance's transform is finite and invertible: |det| above 10⁻¹² of its largest
/// entry cubed (and above 10⁻³⁰), so the inverse the renderer takes is usable.
pub fn check_transform(r: &InstanceRecord) -> Result<(), String> {
    let m = r.matrix();
    let det = r.det();
    let scale = m
        .iter()
        .flat_map(|row| &row[..3])
        .fold(0f64, |a, x| a.max(x.abs()));
    if !finite(&r.to_world) || det.abs() <= 1e-12 * scale.powi(3) || det.abs() < 1e-30 {
        return Err("the transform is not finite and invertible".into());
    }
    Ok(())
}

#[cfg(test)]
#[path = "validate_tests.rs"]
mod tests;
