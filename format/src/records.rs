//! Fixed-size records of the archive: header, page table, page header, materials, cameras,
//! lights. All little-endian, `#[repr(C)]`, no implicit padding.

use bytemuck::{Pod, Zeroable};

pub const MAGIC: [u8; 8] = *b"CANOPY\x00\x1a";
pub const VERSION_MAJOR: u16 = 2;
pub const VERSION_MINOR: u16 = 7;
pub const PAGE_MAGIC: [u8; 4] = *b"PAGE";
/// Page frames and tables start at multiples of this many bytes, so records can be read in
/// place from the mapping.
pub const ALIGN: u64 = 64;
/// Bytes of a node record in this version (a later minor version may grow it; readers read
/// the first `NODE_SIZE` bytes of each `Header::node_size`).
pub const NODE_SIZE: u32 = 128;
/// Page-table value for "no parent".
pub const NONE: u32 = u32::MAX;

/// Scene features. Bits 0–31 are optional: they describe the scene so the renderer can skip
/// what it cannot use, and a reader ignores bits it does not know. Bits 32–63 are required:
/// they change how the archive must be read, and a reader refuses bits it does not know.
pub struct Features;
impl Features {
    pub const EMITTERS: u64 = 1;
    pub const GLOSSY: u64 = 2;
    pub const TRANSMISSIVE: u64 = 4;
    /// The input referenced textures; they are not stored (factors only), see FORMAT.md.
    pub const TEXTURED_INPUT: u64 = 8;
    pub const PUNCTUAL_LIGHTS: u64 = 32;
    /// Pages carry a per-vertex shading-normal stream (required: it changes the page layout).
    pub const SHADING_NORMALS: u64 = 1 << 32;
    /// The instance table is not empty: instance leaves name a prototype subtree and a
    /// transform (required: a reader that ignored them would lose geometry).
    pub const INSTANCES: u64 = 1 << 33;
    /// Pages carry a per-vertex texture-coordinate stream (required: it changes the page
    /// layout). Version 2.2.
    pub const TEXCOORDS: u64 = 1 << 34;
    /// Pages carry a per-vertex colour stream (required: it changes the page layout).
    /// Version 2.4.
    pub const COLOURS: u64 = 1 << 35;
    /// Pages carry a second per-vertex texture-coordinate stream after the first (required:
    /// it changes the page layout; only with TEXCOORDS). Version 2.6.
    pub const TEXCOORDS2: u64 = 1 << 36;
    /// The instance records travel in the pages that hold their leaves, not in a table
    /// (required: it changes the page layout and what an instance leaf's link means; only
    /// with INSTANCES). Version 2.7.
    pub const PAGED_INSTANCES: u64 = 1 << 37;
    pub const REQUIRED: u64 = 0xFFFF_FFFF_0000_0000;
    pub const ALL: u64 = Self::EMITTERS
        | Self::GLOSSY
        | Self::TRANSMISSIVE
        | Self::TEXTURED_INPUT
        | Self::PUNCTUAL_LIGHTS
        | Self::SHADING_NORMALS
        | Self::INSTANCES
        | Self::TEXCOORDS
        | Self::COLOURS
        | Self::TEXCOORDS2
        | Self::PAGED_INSTANCES;

    pub fn names(bits: u64) -> Vec<&'static str> {
        [
            (Self::EMITTERS, "emitters"),
            (Self::GLOSSY, "glossy"),
            (Self::TRANSMISSIVE, "transmissive"),
            (Self::TEXTURED_INPUT, "textured-input"),
            (Self::SHADING_NORMALS, "shading-normals"),
            (Self::PUNCTUAL_LIGHTS, "punctual-lights"),
            (Self::INSTANCES, "instances"),
            (Self::TEXCOORDS, "texcoords"),
            (Self::COLOURS, "vertex-colours"),
            (Self::TEXCOORDS2, "texcoords2"),
            (Self::PAGED_INSTANCES, "paged-instances"),
        ]
        .iter()
        .filter(|(b, _)| bits & b != 0)
        .map(|(_, n)| *n)
        .collect()
    }
}

/// Location of a table in the file.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct TableRef {
    pub offset: u64,
    pub count: u32,
    pub record_size: u32,
}

/// The 256-byte file header at offset 0.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct Header {
    pub magic: [u8; 8],
    pub version_major: u16,
    pub version_minor: u16,
    pub header_size: u32,
    pub features: u64,
    pub input_triangles: u64,
    pub triangles: u64,
    pub nodes: u64,
    pub vertices: u64,
    pub file_len: u64,
    pub bounds_min: [f32; 3],
    pub bounds_max: [f32; 3],
    pub root_page: u32,
    pub depth: u32,
    pub max_leaf_triangles: u32,
    pub page_nodes_max: u32,
    pub materials: TableRef,
    pub cameras: TableRef,
    pub lights: TableRef,
    pub pages: TableRef,
    /// xxh3-64 of the material, camera and light tables (each page entry has its own).
    pub tables_checksum: u64,
    /// xxh3-64 of this header with this field zeroed.
    pub header_checksum: u64,
    /// Bytes per node record (`NODE_SIZE` or more).
    pub node_size: u32,
    /// Version 2.4: how many `NoteRecord`s follow the environment table (zero before).
    pub notes: u32,
    /// Version 2.1: the instance table, right after the lights (all zero in 2.0 files).
    pub instances: TableRef,
    /// Version 2.2: the texture table and the texture-tile table, after the instances (all
    /// zero before 2.2).
    pub textures: TableRef,
    pub tiles: TableRef,
    /// 2.3: the environment table (0 or 1 records) after the tiles; zero before 2.3.
    pub environment: TableRef,
}

const _: () = assert!(std::mem::size_of::<Header>() == 256);
const _: () = assert!(std::mem::offset_of!(Header, instances) == 192);
const _: () = assert!(std::mem::offset_of!(Header, textures) == 208);

/// Texels on a side of a texture tile.
pub const TILE: u32 = 64;
/// Bytes of a decoded tile: `TILE`² texels of RGBA8.
pub const TILE_BYTES: u32 = TILE * TILE * 4;

/// One texture (64 bytes): a MIP pyramid of RGBA8 tiles, level 0 the image as read. Level
/// l is max(1, width >> l) × max(1, height >> l) texels; its tiles follow level l − 1's in
/// row-major order, `TILE` × `TILE` texels each (texels past the level's edge are zero).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct TextureRecord {
    pub name: [u8; 24],
    pub width: u32,
    pub height: u32,
    /// ⌊log2 max(width, height)⌋ + 1.
    pub levels: u32,
    /// This texture's first entry in the tile table.
    pub first_tile: u32,
    /// `SRGB`, and the wrap modes of s (bits 8–9) and t (bits 10–11).
    pub flags: u32,
    /// Mean of level 0 in linear RGBA (sRGB decoded when `SRGB`).
    pub mean: [f32; 4],
    pub reserved: [u8; 4],
}

const _: () = assert!(std::mem::size_of::<TextureRecord>() == 64);

impl TextureRecord {
    /// RGB texels hold sRGB-encoded values (alpha is always linear).
    pub const SRGB: u32 = 1;
    pub const WRAP_REPEAT: u32 = 0;
    pub const WRAP_CLAMP: u32 = 1;
    pub const WRAP_MIRROR: u32 = 2;
    pub const ALL_FLAGS: u32 = 1 | 0xF00;

    /// Wrap mode of s (axis 0) or t (axis 1).
    pub fn wrap(&self, axis: usize) -> u32 {
        self.flags >> (8 + 2 * axis) & 3
    }

    /// Size of level `l` in texels.
    pub fn level_size(&self, l: u32) -> (u32, u32) {
        ((self.width >> l).max(1), (self.height >> l).max(1))
    }

    /// Tiles across and down level `l`.
    pub fn level_tiles(&self, l: u32) -> (u32, u32) {
        let (w, h) = self.level_size(l);
        (w.div_ceil(TILE), h.div_ceil(TILE))
    }

    /// Tile-table index of each level's first tile, and one past the last level's tiles
    /// (`levels + 1` entries). For a record `check_textures` accepted.
    pub fn level_first_tiles(&self) -> Vec<u32> {
        let mut at = self.first_tile;
        let mut out = vec![at];
        for l in 0..self.levels {
            let (x, y) = self.level_tiles(l);
            at += x * y;
            out.push(at);
        }
        out
    }

    /// Tiles of the whole pyramid (u64: a corrupt record may claim absurd sizes).
    pub fn tile_count(&self) -> u64 {
        (0..self.levels.min(32))
            .map(|l| {
                let (x, y) = self.level_tiles(l);
                x as u64 * y as u64
            })
            .sum()
    }

    /// Levels of a full pyramid of a width × height image.
    pub fn full_levels(width: u32, height: u32) -> u32 {
        32 - width.max(height).max(1).leading_zeros()
    }
}

/// Where one compressed tile sits (32 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct TileEntry {
    pub offset: u64,
    pub compressed_len: u32,
    /// `TILE_BYTES`.
    pub raw_len: u32,
    /// xxh3-64 of the compressed bytes.
    pub checksum: u64,
    pub reserved: [u8; 8],
}

const _: () = assert!(std::mem::size_of::<TileEntry>() == 32);

/// One placement of a prototype subtree (64 bytes): instance leaves of the tree name it.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct InstanceRecord {
    /// Object-to-world, column-major 3×4 (images of the x, y, z axes, then the translation);
    /// finite and invertible.
    pub to_world: [f32; 12],
    /// The page whose node 0 is the prototype's root (no parent page, one root).
    pub prototype_page: u32,
    pub reserved: [u8; 12],
}

const _: () = assert!(std::mem::size_of::<InstanceRecord>() == 64);

impl InstanceRecord {
    /// The transform as rows of f64 (`m[row][col]`, column 3 the translation).
    pub fn matrix(&self) -> [[f64; 4]; 3] {
        let t = &self.to_world;
        [0, 1, 2].map(|r| [0, 1, 2, 3].map(|c| t[c * 3 + r] as f64))
    }

    /// The transform's 3×3 part, rows.
    pub fn linear(&self) -> [[f64; 3]; 3] {
        self.matrix().map(|row| [row[0], row[1], row[2]])
    }

    /// The determinant of the transform's 3×3 part, in f64.
    pub fn det(&self) -> f64 {
        det3(&self.linear())
    }

    /// A box holding the image of box `lo..hi` under the transform in every IEEE-correct
    /// evaluation order: the eight corners mapped in f64 (exact to 2⁻⁵³ relative), then
    /// widened outward by 4 ulps of the largest coordinate magnitude of the result before
    /// rounding to f32 (f32 evaluation of one output coordinate errs by at most
    /// γ₃ Σ|m·x| < 4 ulps of that sum).
    pub fn world_box(&self, lo: [f32; 3], hi: [f32; 3]) -> ([f32; 3], [f32; 3]) {
        let m = self.matrix();
        let mut out_lo = [f64::INFINITY; 3];
        let mut out_hi = [f64::NEG_INFINITY; 3];
        let mut mag = [0f64; 3];
        for corner in 0..8 {
            let p = [0, 1, 2].map(|a| if corner >> a & 1 == 0 { lo[a] } else { hi[a] } as f64);
            for r in 0..3 {
                let v = m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3];
                let s = (m[r][0] * p[0]).abs()
                    + (m[r][1] * p[1]).abs()
                    + (m[r][2] * p[2]).abs()
                    + m[r][3].abs();
                out_lo[r] = out_lo[r].min(v);
                out_hi[r] = out_hi[r].max(v);
                mag[r] = mag[r].max(s);
            }
        }
        let pad = |r: usize| 4.0 * mag[r] * f32::EPSILON as f64;
        (
            [0, 1, 2].map(|r| round_down(out_lo[r] - pad(r))),
            [0, 1, 2].map(|r| round_up(out_hi[r] + pad(r))),
        )
    }
}

/// The cofactor matrix of `a`: cof[r][c] = (−1)^(r+c) × the minor of a[r][c], so that
/// det a = Σ_c a[0][c]·cof[0][c] and a⁻¹ = cofᵀ / det a.
pub fn cofactors3(a: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    std::array::from_fn(|r| {
        std::array::from_fn(|c| {
            let (r1, r2, c1, c2) = ((r + 1) % 3, (r + 2) % 3, (c + 1) % 3, (c + 2) % 3);
            a[r1][c1] * a[r2][c2] - a[r1][c2] * a[r2][c1]
        })
    })
}

/// The determinant of `a`.
pub fn det3(a: &[[f64; 3]; 3]) -> f64 {
    let cof = cofactors3(a);
    (0..3).map(|c| a[0][c] * cof[0][c]).sum()
}

/// The largest f32 ≤ x.
fn round_down(x: f64) -> f32 {
    let f = x as f32;
    if f as f64 > x {
        f.next_down()
    } else {
        f
    }
}

/// The smallest f32 ≥ x.
fn round_up(x: f64) -> f32 {
    let f = x as f32;
    if (f as f64) < x {
        f.next_up()
    } else {
        f
    }
}

/// One page-table entry (96 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct PageEntry {
    pub offset: u64,
    pub compressed_len: u32,
    pub raw_len: u32,
    /// xxh3-64 of the compressed bytes.
    pub checksum: u64,
    /// Global index of this page's node 0; nodes are numbered page by page.
    pub first_node: u64,
    pub node_count: u32,
    pub tri_count: u32,
    pub vert_count: u32,
    /// 2.7 with PAGED_INSTANCES: instance records in the page (zero before: version 1's
    /// never-written coefficient bytes).
    pub instance_count: u32,
    /// Page holding the node whose children are this page's roots (NONE for the root page).
    pub parent_page: u32,
    /// Local index of that node in the parent page.
    pub parent_node: u32,
    /// Pages between this one and the root page.
    pub level: u16,
    /// 1 for the root page, 2 (a sibling pair) otherwise.
    pub root_count: u16,
    /// The quantization grid: the exact union of the root nodes' bounds.
    pub bounds_min: [f32; 3],
    pub bounds_max: [f32; 3],
    /// xxh3-64 of the entry's record with this field zero, as two little-endian words.
    pub entry_checksum: [u32; 2],
    /// 2.7 with PAGED_INSTANCES: the number of the page's first instance record; pages
    /// number instances consecutively in table order (zero before).
    pub first_instance: u32,
}

const _: () = assert!(std::mem::size_of::<PageEntry>() == 96);

impl PageEntry {
    /// The checksum a record of these bytes should carry (`entry_checksum` zeroed).
    pub fn checksum_of(record: &[u8]) -> u64 {
        let mut h = xxhash_rust::xxh3::Xxh3::new();
        h.update(&record[..84]);
        h.update(&[0; 8]);
        h.update(&record[92..]);
        h.digest()
    }

    pub fn entry_checksum(&self) -> u64 {
        self.entry_checksum[0] as u64 | (self.entry_checksum[1] as u64) << 32
    }

    /// Sets `entry_checksum` for a record of exactly this entry's 96 bytes.
    pub fn seal(&mut self) {
        let c = Self::checksum_of(bytemuck::bytes_of(self));
        self.entry_checksum = [c as u32, (c >> 32) as u32];
    }

    pub fn grid(&self) -> crate::codec::Grid {
        crate::codec::Grid {
            lo: self.bounds_min,
            hi: self.bounds_max,
        }
    }
}

/// The 32-byte header at the start of each decompressed page.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct PageHeader {
    pub magic: [u8; 4],
    pub node_count: u32,
    pub tri_count: u32,
    pub vert_count: u32,
    /// Instance records after the vertex streams (2.7 with PAGED_INSTANCES; zero before).
    pub instance_count: u32,
    /// 1 when a shading-normal stream follows the vertices.
    pub has_normals: u32,
    /// How many texture-coordinate streams follow (version 2.2: 0 or 1; 2.6: or 2).
    pub has_uvs: u32,
    /// 1 when a vertex-colour stream follows (version 2.4; reserved zero before).
    pub has_colours: u32,
}

const _: () = assert!(std::mem::size_of::<PageHeader>() == 32);

/// A fixed-length UTF-8 name, zero padded; longer names are cut at a char boundary.
pub fn name_bytes<const N: usize>(s: &str) -> [u8; N] {
    let mut out = [0u8; N];
    let mut end = s.len().min(N);
    while !s.is_char_boundary(end) {
        end -= 1;
    }
    out[..end].copy_from_slice(&s.as_bytes()[..end]);
    out
}

pub fn name_str(b: &[u8]) -> String {
    let end = b.iter().position(|&c| c == 0).unwrap_or(b.len());
    String::from_utf8_lossy(&b[..end]).into_owned()
}

/// glTF metallic-roughness material in full precision (400 bytes; 176 in version 2.5, 144
/// in 2.4, 128 before).
/// Leaves shade with these.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct MaterialRecord {
    pub name: [u8; 48],
    pub base_color: [f32; 4],
    /// emissiveFactor × KHR_materials_emissive_strength.
    pub emission: [f32; 3],
    pub metallic: f32,
    pub roughness: f32,
    pub ior: f32,
    pub transmission: f32,
    /// KHR_materials_specular specularFactor and specularColorFactor.
    pub specular: f32,
    pub specular_color: [f32; 3],
    pub flags: u32,
    /// Version 2.2: texture indices of base colour, metallic-roughness, emission and normal
    /// (`NO_TEXTURE`: none).
    pub textures: [u16; 4],
    /// With `ALPHA_MASK`: texels whose alpha is below this are holes.
    pub alpha_cutoff: f32,
    /// glTF normalTexture.scale on the tangent-space normal's x and y (with a normal
    /// texture; 0 otherwise).
    pub normal_scale: f32,
    /// Version 2.4, KHR_materials_volume: the colour white light takes after
    /// `attenuation_distance` inside the mesh (zero before 2.4).
    pub attenuation_color: [f32; 3],
    /// Version 2.4: the distance (scene units) at which light inside the mesh takes
    /// `attenuation_color`; 0 for no attenuation (a thin wall, or no volume).
    pub attenuation_distance: f32,
    /// Version 2.5, KHR_materials_clearcoat: the coat's clearcoatFactor and
    /// clearcoatRoughnessFactor (zero before 2.5: no coat).
    pub clearcoat: f32,
    pub clearcoat_roughness: f32,
    /// Version 2.5, KHR_materials_sheen: sheenColorFactor (zero: no sheen) and
    /// sheenRoughnessFactor.
    pub sheen_color: [f32; 3],
    pub sheen_roughness: f32,
    /// Version 2.5: texture indices of the clearcoat (R), clearcoat roughness (G), sheen
    /// colour (RGB) and sheen roughness (A) textures (`NO_TEXTURE`: none).
    pub layer_textures: [u16; 4],
    /// Version 2.6: texture index of KHR_materials_clearcoat's clearcoatNormalTexture
    /// (`NO_TEXTURE`: the coat takes the base's shading normal).
    pub coat_normal_texture: u16,
    /// Version 2.6: bit s set when texture slot s (`SLOTS`) reads the second
    /// texture-coordinate stream, clear when it reads the first.
    pub uv_streams: u16,
    /// Version 2.6: clearcoatNormalTexture.scale (finite with a coat normal texture, 0
    /// without).
    pub coat_normal_scale: f32,
    /// Version 2.6: per texture slot (`SLOTS`), the 2×3 affine map (rows (a, b, c) and
    /// (d, e, f): u' = a·u + b·v + c, v' = d·u + e·v + f) from the stream's coordinates to
    /// the texture's (KHR_texture_transform; the identity when there is none).
    pub uv_transforms: [[f32; 6]; 9],
}

const _: () = assert!(std::mem::size_of::<MaterialRecord>() == 400);

/// A material record's size before version 2.4 (no volume fields).
pub const MATERIAL_RECORD_2_3: usize = 128;
/// A material record's size in version 2.4 (no clearcoat or sheen).
pub const MATERIAL_RECORD_2_4: usize = 144;
/// A material record's size in version 2.5 (no per-slot texture coordinates).
pub const MATERIAL_RECORD_2_5: usize = 176;

impl MaterialRecord {
    pub const DOUBLE_SIDED: u32 = 1;
    pub const TEXTURED: u32 = 2;
    /// glTF alphaMode MASK: alpha below `alpha_cutoff` is a hole.
    pub const ALPHA_MASK: u32 = 4;
    /// glTF alphaMode BLEND: alpha is the probability a ray stops (stochastic opacity).
    pub const ALPHA_BLEND: u32 = 8;
    pub const NO_TEXTURE: u16 = u16::MAX;
    pub const BASE_COLOR: usize = 0;
    pub const METALLIC_ROUGHNESS: usize = 1;
    pub const EMISSIVE: usize = 2;
    pub const NORMAL: usize = 3;
    pub const CLEARCOAT: usize = 0;
    pub const CLEARCOAT_ROUGHNESS: usize = 1;
    pub const SHEEN_COLOR: usize = 2;
    pub const SHEEN_ROUGHNESS: usize = 3;
    /// Texture slots, in the order of `uv_streams` and `uv_transforms`: `textures`, then
    /// `layer_textures`, then `coat_normal_texture`.
    pub const SLOTS: usize = 9;
    /// The slot of `coat_normal_texture`.
    pub const COAT_NORMAL: usize = 8;
    /// The identity texture-coordinate map.
    pub const IDENTITY_UV: [f32; 6] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0];

    /// Which of a vertex's texture-coordinate streams slot `s` reads (0 or 1).
    pub fn slot_stream(&self, s: usize) -> usize {
        (self.uv_streams >> s & 1) as usize
    }

    /// Slot `s`'s texture coordinates at a point whose streams read `uv`: the slot's stream
    /// under its coordinate map.
    pub fn slot_uv(&self, s: usize, uv: [[f32; 2]; 2]) -> [f32; 2] {
        self.map_uv(s, uv[self.slot_stream(s)])
    }

    /// Slot `s`'s coordinate map applied to coordinates `uv` of the stream it reads.
    pub fn map_uv(&self, s: usize, [u, v]: [f32; 2]) -> [f32; 2] {
        let m = &self.uv_transforms[s];
        [m[0] * u + m[1] * v + m[2], m[3] * u + m[4] * v + m[5]]
    }

    /// The texture index of each slot (`SLOTS`).
    pub fn slot_textures(&self) -> [u16; 9] {
        let [b, mr, e, n] = self.textures;
        let [c, cr, s, sr] = self.layer_textures;
        [b, mr, e, n, c, cr, s, sr, self.coat_normal_texture]
    }
}

/// Perspective or orthographic camera (128 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct CameraRecord {
    pub name: [u8; 48],
    /// Camera-to-world, column-major 3×4 (x axis, y axis, z axis, position); looks down −z.
    pub to_world: [f32; 12],
    /// Vertical field of view in radians (perspective); 0 for an orthographic camera.
    pub yfov: f32,
    /// Width / height; 0 when the input left it open.
    pub aspect: f32,
    pub znear: f32,
    /// 0 for infinite.
    pub zfar: f32,
    pub width: u32,
    pub height: u32,
    /// `PERSPECTIVE` or `ORTHOGRAPHIC` (version 2.3; reserved, so perspective, before).
    pub projection: u8,
    pub reserved: [u8; 3],
    /// Orthographic: half the view's height in world units (glTF `ymag`); 0 for perspective.
    pub ymag: f32,
}

impl CameraRecord {
    pub const PERSPECTIVE: u8 = 0;
    pub const ORTHOGRAPHIC: u8 = 1;
}

const _: () = assert!(std::mem::size_of::<CameraRecord>() == 128);

/// KHR_lights_punctual light (96 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct LightRecord {
    pub name: [u8; 32],
    /// 0 point, 1 spot, 2 directional.
    pub kind: u32,
    pub color: [f32; 3],
    /// Candela for point and spot, lux for directional (glTF units).
    pub intensity: f32,
    pub position: [f32; 3],
    /// Direction the light shines in (world space, unit).
    pub direction: [f32; 3],
    /// 0 for infinite.
    pub range: f32,
    pub inner_cone: f32,
    pub outer_cone: f32,
    pub reserved: [u8; 8],
}

const _: () = assert!(std::mem::size_of::<LightRecord>() == 96);

impl LightRecord {
    pub const POINT: u32 = 0;
    pub const SPOT: u32 = 1;
    pub const DIRECTIONAL: u32 = 2;
}

/// What the converter said of its input (256 bytes, version 2.4): a feature it does not
/// read, where, and what it did instead. UTF-8, zero padded (a longer note is cut at a
/// character boundary).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct NoteRecord {
    pub text: [u8; 256],
}

impl NoteRecord {
    pub fn new(text: &str) -> NoteRecord {
        NoteRecord {
            text: name_bytes(text),
        }
    }
}

/// The scene's environment light (256 bytes, version 2.3): a map file or a sky.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct EnvironmentRecord {
    /// `MAP` or `SKY`.
    pub kind: u32,
    /// Factor on the radiance.
    pub strength: f32,
    /// Degrees about +Y.
    pub rotate_degrees: f32,
    /// Sky: the sun's elevation and compass azimuth in degrees.
    pub sun_elevation: f32,
    pub sun_azimuth: f32,
    /// Sky: Hosek–Wilkie turbidity, ground albedo, factor on the sun.
    pub turbidity: f32,
    pub ground_albedo: f32,
    pub sun_strength: f32,
    /// Map: the file's path, UTF-8, zero-padded; relative to the archive's directory unless
    /// absolute.
    pub path: [u8; 224],
}

impl EnvironmentRecord {
    pub const MAP: u32 = 1;
    pub const SKY: u32 = 2;

    /// The map's path as recorded.
    pub fn path(&self) -> &str {
        let end = self
            .path
            .iter()
            .position(|&b| b == 0)
            .unwrap_or(self.path.len());
        std::str::from_utf8(&self.path[..end]).unwrap_or("")
    }
}

const _: () = assert!(std::mem::size_of::<EnvironmentRecord>() == 256);
