//! The 128-byte node record (004 §4.2, adapted: exact triangles at the leaves, bounds quantized
//! on the page grid, illumination state kept as a zero block on disk). `FORMAT.md` documents
//! every field; offsets are asserted below.

use bytemuck::{Pod, Zeroable};

/// One node of the hierarchy, leaf or inner, as stored in a page.
#[repr(C, align(64))]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct Node {
    /// Conservative bounds on the page grid: min x, y, z then max x, y, z.
    pub bounds: [u16; 6],
    /// Leaf: first triangle (page-local) and triangle count. Inner: page-local indices of the
    /// two children, or with `CHILD_PAGE` the page index holding them as its roots 0 and 1.
    pub link: [u32; 2],
    /// Total triangle area of the subtree (scene units squared).
    pub area: f32,
    /// Bounding-sphere radius around `centroid`.
    pub radius: f32,
    /// Area-weighted mean face normal, *not* normalized (|n| measures coherence, 004 §4.4), snorm16.
    pub normal: [i16; 3],
    /// Area-weighted mean curvature, binary16.
    pub curvature: u16,
    /// Area-weighted mean index of refraction, binary16.
    pub ior: u16,
    /// `NodeFlags` bits.
    pub flags: u8,
    /// Area-weighted mean perceptual roughness, unorm8.
    pub roughness: u8,
    /// Area-weighted mean emitted radiance (front side), E8R19G19B18.
    pub emission: u64,
    /// Area-weighted diffuse albedo ρ, unorm8 RGB.
    pub diffuse: [u8; 3],
    /// Refractiveness: fraction of non-reflected light that is transmitted (004 eq. 4.1), unorm8.
    pub refractiveness: u8,
    /// Transmission tint, unorm8 RGB.
    pub translucency: [u8; 3],
    /// Fraction of `area` visible from outside, unorm8 (255 at conversion; 004 §4.7.1).
    pub visible_area: u8,
    /// p_reflect at cos θ = 0, 1/4, 1/2, 3/4, 1 (004 §4.3.1), unorm8.
    pub reflectiveness: [u8; 5],
    /// Specular reflection tint (F0 colour normalized to max 1), unorm8 RGB.
    pub specular_tint: [u8; 3],
    /// Area-weighted centroid, nearest code on the page grid.
    pub centroid: [u16; 3],
    pub reserved0: u16,
    /// Offset of this node's coefficient record in the page's coefficient stream, or u32::MAX.
    pub coef: u32,
    /// Sample counters NumRays, NumNewRays (004 §4.6.1). Zero on disk.
    pub rays: [u16; 2],
    /// Illumination block (004 §4.2): diffuse, caustic, received diffuse, received caustic
    /// radiance, E8R19G19B18. Zero in archives written by `convert`.
    pub illum: [u64; 4],
    pub reserved1: [u8; 16],
}

const _: () = assert!(std::mem::size_of::<Node>() == 128);
const _: () = assert!(std::mem::align_of::<Node>() == 64);
const _: () = assert!(std::mem::offset_of!(Node, emission) == 40);
const _: () = assert!(std::mem::offset_of!(Node, illum) == 80);
const _: () = assert!(std::mem::offset_of!(Node, rays) == 76);

pub struct NodeFlags;
impl NodeFlags {
    pub const LEAF: u8 = 1;
    /// Inner node whose children are the roots of page `link[0]`.
    pub const CHILD_PAGE: u8 = 2;
    /// The subtree contains emissive triangles.
    pub const EMISSIVE: u8 = 4;
    /// The subtree contains glossy (specular) surfaces.
    pub const GLOSSY: u8 = 8;
    /// The subtree contains transmissive surfaces.
    pub const TRANSMISSIVE: u8 = 16;
    /// A leaf whose `link[0]` is an instance: its subtree is the instance's prototype.
    pub const INSTANCE: u8 = 32;
    pub const ALL: u8 = 63;
}

impl Node {
    pub fn is_leaf(&self) -> bool {
        self.flags & NodeFlags::LEAF != 0
    }
    pub fn is_instance(&self) -> bool {
        self.flags & NodeFlags::INSTANCE != 0
    }
    pub fn has_child_page(&self) -> bool {
        self.flags & NodeFlags::CHILD_PAGE != 0
    }
}

/// A leaf triangle: page-local vertex indices and the material table index.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Pod, Zeroable)]
pub struct Tri {
    pub v: [u16; 3],
    pub material: u16,
}

const _: () = assert!(std::mem::size_of::<Tri>() == 8);
