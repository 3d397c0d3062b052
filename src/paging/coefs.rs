//! A page's glossy light as the bake codes it and a page load decodes it (WPBGI, 000 §3.1):
//! one Haar coefficient vector per node, coded along the page's tree with G/H
//! ([`crate::wavelet::tree`]). 000 codes the whole tree from its root; here each page is
//! coded alone under a virtual root above its roots, with bootstrap level m = 1: the page's
//! roots keep their average G and every deeper node its detail D, so a page decodes
//! without its ancestors, as paging needs.

use super::{NodeRef, TNode};
use crate::wavelet::tree::{decode_all, Kept, Shape, SparseVec};
use crate::wavelet::{cube, haar};
use canopy_format::bake::{BakedBlock, BakedNode, CoefRecord, CoefValue};
use glam::Vec3;
use half::f16;

/// The bootstrap level below the virtual root: the page's roots keep G.
pub const BOOTSTRAP: u32 = 1;

/// A page's tree as the coder sees it: nodes in page order, then the virtual root.
pub struct PageShape {
    pub children: Vec<Vec<usize>>,
    pub weight: Vec<f32>,
}

impl PageShape {
    /// Leaves and child-page links have no children here (a child page is coded alone);
    /// a node's weight is its summed projected areas, so a node's G is its children's
    /// weighted mean and weight × G adds up the tree.
    pub fn new(bvh: &[TNode], roots: u32, baked: &[BakedNode]) -> PageShape {
        let mut children: Vec<Vec<usize>> = bvh
            .iter()
            .map(|n| match n.link() {
                NodeRef::Inner(l, r) => vec![l as usize, r as usize],
                _ => Vec::new(),
            })
            .collect();
        children.push((0..(roots as usize).min(bvh.len())).collect());
        let mut weight: Vec<f32> = (0..bvh.len())
            .map(|i| baked.get(i).map_or(f32::MIN_POSITIVE, weight))
            .collect();
        weight.push(1.0);
        PageShape { children, weight }
    }

    pub fn root(&self) -> usize {
        self.children.len() - 1
    }

    pub fn shape(&self) -> Shape<'_> {
        Shape {
            children: &self.children,
            weight: &self.weight,
            root: self.root(),
        }
    }
}

/// A node's positive weight: its summed projected areas along the six axes.
pub fn weight(b: &BakedNode) -> f32 {
    b.area.iter().sum::<f32>().max(f32::MIN_POSITIVE)
}

/// A page's glossy light per node, decoded to texel values for O(1) lookups: half
/// floats scaled by a per-node maximum (6 bytes a texel; f16's range alone would overflow
/// under a bright lamp).
#[derive(Default)]
pub struct GlossyTexels {
    n: usize,
    /// Per node, its first texel in `texels` and its scale; `u32::MAX` when it sends no
    /// glossy light.
    at: Vec<(u32, f32)>,
    texels: Vec<[f16; 3]>,
}

impl GlossyTexels {
    /// Node i's G at the texel direction `w` points through (unit, node → viewer).
    pub fn get(&self, node: usize, w: Vec3) -> Option<Vec3> {
        let (at, scale) = *self.at.get(node)?;
        (at != u32::MAX).then(|| {
            let t = self.texels[at as usize + cube::texel_of(w, self.n)];
            Vec3::from(t.map(f32::from)) * scale
        })
    }

    pub fn bytes(&self) -> u64 {
        (self.at.len() * 8 + self.texels.len() * 6) as u64
    }
}

/// Every node's glossy light from the block's records, on cube maps of n×n texels a face;
/// `None` when the block has no coefficients.
pub fn decode(
    bvh: &[TNode],
    roots: u32,
    block: &BakedBlock,
    n: usize,
) -> Result<Option<GlossyTexels>, String> {
    let c = &block.coefs;
    if c.records.is_empty() {
        return Ok(None);
    }
    let shape = PageShape::new(bvh, roots, &block.nodes);
    let kept = |node: usize| {
        let k = c
            .records
            .binary_search_by_key(&(node as u32), |r| r.node)
            .ok()?;
        let r = c.records[k];
        let kind = if r.kind == CoefRecord::AVERAGE {
            Kept::Average
        } else {
            Kept::Detail
        };
        let values = &c.values[r.first as usize..(r.first + r.count) as usize];
        Some((
            kind,
            SparseVec(
                values
                    .iter()
                    .map(|v| (v.index, Vec3::from(v.rgb)))
                    .collect(),
            ),
        ))
    };
    let g = decode_all(&shape.shape(), BOOTSTRAP, &kept)?;
    let mut out = GlossyTexels {
        n,
        at: vec![(u32::MAX, 0.0); bvh.len()],
        texels: Vec::new(),
    };
    let nn = n * n;
    for (node, v) in g.iter().take(bvh.len()).enumerate() {
        if v.0.is_empty() {
            continue;
        }
        let mut dense = vec![Vec3::ZERO; 6 * nn];
        for &(i, x) in &v.0 {
            dense[i as usize] = x;
        }
        for face in dense.chunks_mut(nn) {
            haar::inverse(face, n);
        }
        let scale = dense
            .iter()
            .map(|t| t.abs().max_element())
            .fold(0.0, f32::max);
        if scale <= 0.0 || !scale.is_finite() {
            continue;
        }
        out.at[node] = (out.texels.len() as u32, scale);
        out.texels.extend(
            dense
                .iter()
                .map(|t| (*t / scale).to_array().map(f16::from_f32)),
        );
    }
    Ok(Some(out))
}

/// What each node keeps, as the block's records and values.
pub fn records(
    stored: impl Fn(usize) -> Option<(Kept, SparseVec<Vec3>)>,
    nodes: usize,
) -> (Vec<CoefRecord>, Vec<CoefValue>) {
    let (mut records, mut values) = (Vec::new(), Vec::new());
    for node in 0..nodes {
        let Some((kind, v)) = stored(node).filter(|(_, v)| !v.0.is_empty()) else {
            continue;
        };
        records.push(CoefRecord {
            node: node as u32,
            kind: match kind {
                Kept::Average => CoefRecord::AVERAGE,
                Kept::Detail => CoefRecord::DETAIL,
            },
            first: values.len() as u32,
            count: v.0.len() as u32,
        });
        values.extend(v.0.iter().map(|&(index, c)| CoefValue {
            index,
            rgb: c.into(),
        }));
    }
    (records, values)
}
