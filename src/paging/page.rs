//! A page decoded for traversal: its nodes as 32-byte `TNode`s with their links read once
//! (`NodeRef`), its triangles four to a block, shading normals, texture coordinates, and
//! the baked light of an attached bake file.

use super::instance::Instance;
use super::*;
use canopy_format::PageContents;

/// Traversal view of a node: decoded bounds and links. The link is packed (kind in the top
/// two bits of `a`; a leaf's count in the low four bits of `b`, its first block of
/// `Page::tri4` above them) so the node is 32 bytes; read it through `link` and `tri4`.
#[derive(Clone, Copy, Debug, Default)]
#[repr(C, align(32))]
pub struct TNode {
    pub lo: [f32; 3],
    pub(super) a: u32,
    pub hi: [f32; 3],
    pub(super) b: u32,
}
const _: () = assert!(std::mem::size_of::<TNode>() == 32);

pub(super) const KIND_MASK: u32 = 3 << 30;
pub(super) const LEAF: u32 = 1 << 30;
pub(super) const CHILD_PAGE: u32 = 2 << 30;
pub(super) const INSTANCE: u32 = 3 << 30;

/// Where a node leads: the one reading of the page encoding's links.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NodeRef {
    /// Two children in the same page, by index.
    Inner(u32, u32),
    /// Triangles `first..first + count` of the page.
    Leaf { first: u32, count: u32 },
    /// The subtree continues in this page, whose roots 0 and 1 are the node's children.
    ChildPage(u32),
    /// A leaf whose geometry is this instance's prototype.
    Instance(u32),
}

impl TNode {
    /// `link`'s indices must be below 2^30 (the decoder checks).
    pub(super) fn new(lo: [f32; 3], hi: [f32; 3], link: NodeRef) -> TNode {
        let (a, b) = match link {
            NodeRef::Inner(l, r) => (l, r),
            NodeRef::Leaf { first, count } => (LEAF | first, count),
            NodeRef::ChildPage(p) => (CHILD_PAGE | p, 0),
            NodeRef::Instance(i) => (INSTANCE | i, 0),
        };
        TNode { lo, a, hi, b }
    }

    #[inline]
    pub fn link(&self) -> NodeRef {
        let x = self.a & !KIND_MASK;
        match self.a & KIND_MASK {
            LEAF => NodeRef::Leaf {
                first: x,
                count: self.b & 15,
            },
            CHILD_PAGE => NodeRef::ChildPage(x),
            INSTANCE => NodeRef::Instance(x),
            _ => NodeRef::Inner(x, self.b),
        }
    }

    /// A leaf's first block of `Page::tri4`.
    #[inline]
    pub fn tri4(&self) -> u32 {
        self.b >> 4
    }

    /// Sets a leaf's first block of `Page::tri4` (below 2^28; counts are at most 8).
    pub(super) fn set_tri4(&mut self, block: u32) {
        debug_assert!(self.a & KIND_MASK == LEAF && block < 1 << 28);
        self.b = (self.b & 15) | block << 4;
    }
}

/// `pages` ordered deepest level first and grouped by level: a page's children come before
/// it, and the pages of one group are independent of each other.
pub fn deepest_first(entries: &[PageEntry], mut pages: Vec<u32>) -> Vec<Vec<u32>> {
    let level = |i: &u32| entries[*i as usize].level;
    pages.sort_by_key(|i| std::cmp::Reverse(level(i)));
    pages
        .chunk_by(|a, b| level(a) == level(b))
        .map(<[u32]>::to_vec)
        .collect()
}

/// For each page, whether it lies in the scene's tree (its chain of parents ends at
/// `root`) rather than in a prototype's, which instances place. A chain that loops or runs
/// past every page counts as outside (decoding such a page then fails its checks).
pub fn in_scene_tree(entries: &[PageEntry], root: u32) -> Vec<bool> {
    let mut known: Vec<Option<bool>> = vec![None; entries.len()];
    for start in 0..entries.len() {
        let mut chain = Vec::new();
        let mut p = start as u32;
        let answer = loop {
            if let Some(k) = known.get(p as usize).copied().flatten() {
                break k;
            }
            let Some(e) = entries.get(p as usize) else {
                break false;
            };
            if chain.len() > entries.len() {
                break false;
            }
            chain.push(p);
            if e.parent_page == canopy_format::NONE {
                break p == root;
            }
            p = e.parent_page;
        };
        for q in chain {
            known[q as usize] = Some(answer);
        }
    }
    known.into_iter().map(|k| k == Some(true)).collect()
}

/// A triangle with its vertices expanded, as intersection wants it.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TriW {
    pub p: [[f32; 3]; 3],
    pub material: u32,
}

/// One decoded page.
pub struct Page {
    pub id: u32,
    /// Global number of node 0.
    pub first_node: u64,
    pub roots: u32,
    pub nodes: Vec<Node>,
    pub bvh: Vec<TNode>,
    /// The same tree four-wide, for exact rays.
    pub wide: Vec<wide::Wide>,
    /// Each leaf's triangles four to a block, from the leaf's `TNode::tri4` on: the
    /// page's only copy of its triangles (read one through `tri`).
    pub tri4: Vec<wide::Tri4>,
    /// Per triangle, its place in `tri4` (block × 4 + lane, or `wide::NO_SLOT`).
    pub(super) tri_slot: Vec<u32>,
    /// Per triangle, octahedral shading normals of its vertices (empty without normals).
    pub shading: Vec<[u32; 3]>,
    /// Per triangle, its vertices' texture coordinates (empty without TEXCOORDS).
    pub uvs: Vec<[[f32; 2]; 3]>,
    /// Per triangle, its vertices' second texture coordinates (empty without TEXCOORDS2).
    pub uvs2: Vec<[[f32; 2]; 3]>,
    /// Per triangle, its vertices' linear unorm16 RGBA colours (empty without COLOURS).
    pub colours: Vec<[[u16; 4]; 3]>,
    /// The instances the page's instance leaves place, by the leaves' links.
    pub instances: Vec<Instance>,
    /// The page's baked light (empty unless a bake file is attached).
    pub baked: BakedBlock,
    /// Per node, its glossy light decoded from `baked.coefs` (empty unless the bake
    /// stored glossy light).
    pub glossy: coefs::GlossyTexels,
    pub bytes: u64,
}

pub use canopy_format::codec::WHITE;

/// A per-vertex stream as each triangle's three values (empty for an absent stream).
fn by_triangle<T: Copy>(tris: &[Tri], per_vertex: &[T]) -> Vec<[T; 3]> {
    if per_vertex.is_empty() {
        return Vec::new();
    }
    tris.iter()
        .map(|t| t.v.map(|v| per_vertex[v as usize]))
        .collect()
}

/// What a triangle's vertices carry besides their positions, for shading: two streams of
/// texture coordinates (zero without TEXCOORDS and TEXCOORDS2) and colours (`WHITE`
/// without COLOURS).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Corners {
    pub uv: [[[f32; 2]; 3]; 2],
    pub colour: [[u16; 4]; 3],
}

impl Default for Corners {
    fn default() -> Self {
        Corners {
            uv: [[[0.0; 2]; 3]; 2],
            colour: [WHITE; 3],
        }
    }
}

impl Corners {
    /// The linear RGBA vertex colour at barycentrics `b`, None where every vertex is white.
    #[inline]
    pub fn colour_at(&self, b: [f32; 3]) -> Option<[f32; 4]> {
        if self.colour == [WHITE; 3] {
            return None;
        }
        let c = self.colour.map(|c| c.map(|x| x as f32 / 65535.0));
        Some(std::array::from_fn(|k| {
            b[0] * c[0][k] + b[1] * c[1][k] + b[2] * c[2][k]
        }))
    }

    /// The mean colour over the triangle (the vertices' mean), None where all are white.
    pub fn mean_colour(&self) -> Option<[f32; 4]> {
        self.colour_at([1.0 / 3.0; 3])
    }
}

impl Page {
    /// Triangle `i` of the page, if a leaf holds it.
    #[inline]
    pub fn tri(&self, i: u32) -> Option<TriW> {
        let slot = *self.tri_slot.get(i as usize)?;
        let block = self.tri4.get(slot as usize / 4)?;
        Some(block.tri(slot as usize % 4))
    }

    /// What triangle `i`'s vertices carry for shading (defaults where the page has none).
    #[inline]
    pub fn corners(&self, i: u32) -> Corners {
        Corners {
            uv: [&self.uvs, &self.uvs2].map(|s| s.get(i as usize).copied().unwrap_or_default()),
            colour: self.colours.get(i as usize).copied().unwrap_or([WHITE; 3]),
        }
    }

    /// The page's triangles, whether a leaf holds them or not.
    pub fn tri_count(&self) -> u32 {
        self.tri_slot.len() as u32
    }

    pub fn decode(archive: &Archive, id: u32) -> Result<Page> {
        let mut c = archive.read_page(id)?;
        let e = &archive.entry(id)?;
        let instances = placed(archive, e, &mut c);
        let grid = e.grid();
        if c.nodes.iter().any(|n| n.link[0] >= 1 << 30) {
            bail!(
                "{}: page {id}: a link does not fit 30 bits",
                archive.path().display()
            );
        }
        let mut bvh = c
            .nodes
            .iter()
            .map(|n| {
                let (lo, hi) = grid.dequant_box(&n.bounds);
                let link = if n.flags & NodeFlags::INSTANCE != 0 {
                    NodeRef::Instance(n.link[0])
                } else if n.flags & NodeFlags::LEAF != 0 {
                    NodeRef::Leaf {
                        first: n.link[0],
                        count: n.link[1],
                    }
                } else if n.flags & NodeFlags::CHILD_PAGE != 0 {
                    NodeRef::ChildPage(n.link[0])
                } else {
                    NodeRef::Inner(n.link[0], n.link[1])
                };
                TNode::new(lo, hi, link)
            })
            .collect::<Vec<_>>();
        let tris: Vec<TriW> = c
            .tris
            .iter()
            .map(|t: &Tri| TriW {
                p: t.v.map(|v| c.verts[v as usize]),
                material: t.material as u32,
            })
            .collect();
        let shading = by_triangle(&c.tris, &c.normals);
        let uvs = by_triangle(&c.tris, &c.uvs);
        let uvs2 = by_triangle(&c.tris, &c.uvs2);
        let colours = by_triangle(&c.tris, &c.colours);
        let (tri4, tri_slot) = wide::tri4s(&mut bvh, &tris).ok_or_else(|| {
            anyhow::anyhow!(
                "{}: page {id}: {} triangles are more than a page can index",
                archive.path().display(),
                tris.len()
            )
        })?;
        let wide = wide::build(&bvh, e.root_count as u32);
        // Capacities, not lengths: vectors built by pushing hold up to twice their length,
        // which the budget must see (200 M triangles at 1 GiB: RSS 1.27 GiB with lengths).
        // Shrinking them instead cost 50% more render time in reallocation.
        let bytes = (std::mem::size_of::<Page>()
            + c.nodes.capacity() * std::mem::size_of::<Node>()
            + bvh.capacity() * std::mem::size_of::<TNode>()
            + wide.capacity() * std::mem::size_of::<wide::Wide>()
            + tri4.capacity() * std::mem::size_of::<wide::Tri4>()
            + tri_slot.capacity() * 4
            + shading.capacity() * 12
            + (uvs.capacity() + uvs2.capacity()) * 24
            + colours.capacity() * 24
            + instances.capacity() * std::mem::size_of::<Instance>()) as u64;
        Ok(Page {
            id,
            first_node: e.first_node,
            roots: e.root_count as u32,
            nodes: c.nodes,
            bvh,
            wide,
            tri4,
            tri_slot,
            shading,
            uvs,
            uvs2,
            colours,
            instances,
            baked: BakedBlock::default(),
            glossy: coefs::GlossyTexels::default(),
            bytes,
        })
    }

    /// The instance that the instance leaf `via` (a global node number of this page)
    /// places.
    pub fn instance_of(&self, via: u64) -> Option<&Instance> {
        let node = self.bvh.get(via.checked_sub(self.first_node)? as usize)?;
        match node.link() {
            NodeRef::Instance(k) => self.instances.get(k as usize),
            _ => None,
        }
    }

    /// Adds the page's block of baked light from `r`.
    pub fn with_baked(mut self, r: &BakeFile) -> Result<Page> {
        self.baked = r.read_block(self.id)?;
        self.bytes += self.baked.bytes();
        let n = r.header.wavelet_n as usize;
        let glossy = coefs::decode(&self.bvh, self.roots, &self.baked, n)
            .map_err(|e| anyhow::anyhow!("{}: block {}: {e}", r.path().display(), self.id))?;
        if let Some(g) = glossy {
            self.bytes += g.bytes();
            self.glossy = g;
        }
        Ok(self)
    }

    pub(super) fn empty(id: u32) -> Page {
        Page {
            id,
            first_node: 0,
            roots: 0,
            nodes: Vec::new(),
            bvh: Vec::new(),
            wide: Vec::new(),
            tri4: Vec::new(),
            tri_slot: Vec::new(),
            shading: Vec::new(),
            uvs: Vec::new(),
            uvs2: Vec::new(),
            colours: Vec::new(),
            instances: Vec::new(),
            baked: BakedBlock::default(),
            glossy: coefs::GlossyTexels::default(),
            bytes: 0,
        }
    }
}

/// The instances page `e`'s leaves place: its own records (PAGED_INSTANCES), numbered from
/// the entry's `first_instance`; or, in an archive with an instance table, the records its
/// leaves name, the leaves' links rewritten to index them here.
fn placed(archive: &Archive, e: &PageEntry, c: &mut PageContents) -> Vec<Instance> {
    if !c.instances.is_empty() {
        return (e.first_instance..)
            .zip(&c.instances)
            .map(|(number, r)| Instance::new(number, r))
            .collect();
    }
    let mut out = Vec::new();
    for n in c.nodes.iter_mut().filter(|n| n.is_instance()) {
        // The table was checked at open and the links against it when the page was read.
        let number = n.link[0];
        out.push(Instance::new(number, &archive.instances[number as usize]));
        n.link[0] = out.len() as u32 - 1;
    }
    out
}
