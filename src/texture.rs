//! Texture lookups through the page cache, which holds the tiles under the render's budget.
//!
//! Filtering is pbrt-v4's trilinear `MIPMap::Filter` (§10.4.3): the level is
//! `levels − 1 + log2(width)` for a filter `width` in texture space, bilinear within a
//! level, linear between the two nearest. The width comes from a world-space footprint at
//! the hit: ray differentials for the path tracer (pbrt-v4 §10.1, with its camera-based
//! approximation `Approximate_dp_dxy` at every bounce and its scale
//! max(1/8, 1/√spp)), the cone's diameter for the cone integrator. The footprint is moved
//! into texture space by least squares through ∂p/∂u, ∂p/∂v (pbrt-v4
//! `SurfaceInteraction::ComputeDifferentials`).

use crate::material::Material;
use crate::paging::{Corners, PageCache, TileData};
use canopy_format::codec::{bilinear, texel_to_linear};
use canopy_format::{MaterialRecord, TextureRecord, TILE};
use glam::Vec3A as V;

/// How texture lookups filter.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum TextureFilter {
    /// MIP levels blended over the sample's footprint.
    Trilinear,
    /// Level 0 at the sample's point, bilinear.
    Point,
}

impl TextureFilter {
    /// The factor on a pixel's footprint for `spp` samples per pixel (None: a time limit):
    /// 1/√spp, pbrt-v4's scale, which shrinks the filter as samples average the pixel, so
    /// the image converges to the unfiltered texture's. pbrt-v4 stops at 1/8; we do not, as
    /// its floor leaves a blur (RMSE 8.8e-3 against 4096 point samples on the grazing
    /// checkerboard, 100× the noise). 0 for point sampling.
    pub fn footprint_scale(self, spp: Option<u32>) -> f32 {
        match self {
            TextureFilter::Point => 0.0,
            TextureFilter::Trilinear => 1.0 / (spp.unwrap_or(64).max(1) as f32).sqrt(),
        }
    }
}

/// A material's textures, by `MaterialRecord` slot (`SLOTS` order), and its record, which
/// says how each slot reads its texture coordinates.
#[derive(Clone, Copy, Debug)]
struct Binding {
    slots: [Option<u32>; MaterialRecord::SLOTS],
    rec: MaterialRecord,
    /// How many texture-coordinate streams the slots read: 2 when one reads the second.
    streams: usize,
    /// `ALPHA_MASK` cutoff, or None.
    mask: Option<f32>,
    /// `ALPHA_BLEND`.
    blend: bool,
}

impl Binding {
    fn of(m: &MaterialRecord, textures: usize) -> Binding {
        let index = |t: u16| {
            (t != MaterialRecord::NO_TEXTURE && (t as usize) < textures).then_some(t as u32)
        };
        let slots = m.slot_textures().map(index);
        let second =
            (0..MaterialRecord::SLOTS).any(|s| slots[s].is_some() && m.slot_stream(s) == 1);
        Binding {
            slots,
            rec: *m,
            streams: 1 + second as usize,
            mask: (m.flags & MaterialRecord::ALPHA_MASK != 0).then_some(m.alpha_cutoff),
            blend: m.flags & MaterialRecord::ALPHA_BLEND != 0,
        }
    }

    /// Slot `slot`'s coordinates and filter width at footprint `fp`: the stream's point and
    /// axes under the slot's map (its linear part carries the axes).
    fn at(&self, slot: usize, fp: &Footprint) -> ([f32; 2], f32) {
        let k = self.rec.slot_stream(slot);
        let m = &self.rec.uv_transforms[slot];
        let width = fp.axes[k].iter().fold(0.0f32, |w, &[du, dv]| {
            let (a, b) = (m[0] * du + m[1] * dv, m[3] * du + m[4] * dv);
            w.max(a.abs()).max(b.abs())
        });
        (self.rec.map_uv(slot, fp.at[k]), 2.0 * width)
    }

    /// Slot `slot`'s coordinates at a triangle's three corners.
    fn corners(&self, slot: usize, c: &Corners) -> [[f32; 2]; 3] {
        c.uv[self.rec.slot_stream(slot)].map(|uv| self.rec.map_uv(slot, uv))
    }
}

/// A material as shaded at one point of a surface (its opacity apart: `Textures::opacity`).
pub struct Shaded {
    pub m: Material,
    /// The normal texture's shading normal there (world space, unit, on the side of the
    /// triangle's front normal), if it has one.
    pub normal: Option<V>,
    /// The clearcoat normal texture's, likewise.
    pub coat_normal: Option<V>,
}

impl Shaded {
    /// A material that does not vary over its surface.
    pub fn plain(m: Material) -> Shaded {
        Shaded {
            m,
            normal: None,
            coat_normal: None,
        }
    }
}

/// A point of a triangle in texture space, per texture-coordinate stream: its coordinates
/// and the two axes of its footprint (texture-space vectors; zero for a point).
#[derive(Clone, Copy, Debug, Default)]
pub struct Footprint {
    at: [[f32; 2]; 2],
    axes: [[[f32; 2]; 2]; 2],
}

impl Footprint {
    /// A point of no extent at barycentrics `b` of a triangle whose corners are `c`.
    pub fn point(c: &Corners, b: [f32; 3]) -> Footprint {
        Footprint {
            at: c.uv.map(|uv| uv_at(uv, b)),
            axes: [[[0.0; 2]; 2]; 2],
        }
    }

    /// The footprint `spread` wide (world units, across a ray of direction `d`) at
    /// barycentrics `b` of a triangle with positions `p` and corners `c`, in the first
    /// `streams` streams (`footprint_axes`).
    fn new(p: [V; 3], c: &Corners, b: [f32; 3], d: V, spread: f32, streams: usize) -> Footprint {
        let mut fp = Footprint::point(c, b);
        for k in 0..streams {
            fp.axes[k] = footprint_axes(p, c.uv[k], d, spread);
        }
        fp
    }
}

/// The archive's textures and which materials use them.
#[derive(Default)]
pub struct Textures {
    records: Vec<TextureRecord>,
    /// Per texture, the first tile of each level (tile-table indices; one more at the end).
    level_first: Vec<Vec<u32>>,
    bindings: Vec<Binding>,
    /// Some material has an alpha mode.
    alpha: bool,
}

impl Textures {
    pub fn new(records: &[TextureRecord], materials: &[MaterialRecord]) -> Textures {
        let level_first = records.iter().map(|t| t.level_first_tiles()).collect();
        let bindings: Vec<Binding> = materials
            .iter()
            .map(|m| Binding::of(m, records.len()))
            .collect();
        Textures {
            records: records.to_vec(),
            level_first,
            alpha: bindings.iter().any(|b| b.mask.is_some() || b.blend),
            bindings,
        }
    }

    /// Whether material `m` varies over its surface (a texture or an alpha mode).
    #[inline]
    pub fn varies(&self, m: u32) -> bool {
        self.bindings
            .get(m as usize)
            .is_some_and(|b| b.mask.is_some() || b.blend || b.slots.iter().any(Option::is_some))
    }

    /// Whether material `m` tilts its shading normal by a normal texture.
    #[inline]
    pub fn bumped(&self, m: u32) -> bool {
        self.slot(m, MaterialRecord::NORMAL).is_some()
    }

    /// Material `index`'s texture footprint `spread` wide (world units, across a ray of
    /// direction `d`) at barycentrics `b` of a triangle with positions `p` and corners `c`.
    pub fn footprint(
        &self,
        index: u32,
        p: [V; 3],
        c: &Corners,
        b: [f32; 3],
        d: V,
        spread: f32,
    ) -> Footprint {
        let streams = self.bindings.get(index as usize).map_or(1, |b| b.streams);
        Footprint::new(p, c, b, d, spread, streams)
    }

    /// Material `m`'s texture in `slot`, if it has one.
    fn slot(&self, m: u32, slot: usize) -> Option<u32> {
        self.bindings.get(m as usize).and_then(|b| b.slots[slot])
    }

    /// Where material `m`'s emission texture reads at a triangle's corners `c`, if its
    /// emission comes from a texture: the point a light sample reads is interpolated
    /// from these (`emission_ratio`).
    pub fn emission_corners(&self, m: u32, c: &Corners) -> Option<[[f32; 2]; 3]> {
        let b = self.bindings.get(m as usize)?;
        b.slots[MaterialRecord::EMISSIVE]?;
        Some(b.corners(MaterialRecord::EMISSIVE, c))
    }

    /// Material `m`'s emission texel at `uv` (its emission slot's coordinates) over the
    /// texture's mean, per channel (0 where the mean is 0): what turns a lamp's mean
    /// radiance, by which lights are chosen, into its radiance at that point. Read at
    /// level 0 (a light sample is a point).
    pub fn emission_ratio(&self, look: &mut Lookup, m: u32, uv: [f32; 2]) -> V {
        let Some(t) = self.slot(m, MaterialRecord::EMISSIVE) else {
            return V::ONE;
        };
        let c = look.trilinear(self, t, uv, 0.0);
        let mean = self.records[t as usize].mean;
        V::from(std::array::from_fn::<f32, 3, _>(|k| {
            if mean[k] > 0.0 {
                c[k] / mean[k]
            } else {
                0.0
            }
        }))
    }

    /// Whether some material cuts holes (alpha mask or blend): rays must then test alpha.
    pub fn has_alpha(&self) -> bool {
        self.alpha
    }

    /// Material `index` with its textures' means in place of texels: what a baked or
    /// clustered value over its whole surface sees.
    pub fn mean_shade(&self, m: &Material, index: u32) -> Material {
        self.apply(m, index, |_, t| self.records[t as usize].mean)
    }

    /// Material `index` as shaded at footprint `fp` of a triangle with positions `p` and
    /// corners `c` (each slot read at its coordinates, filtered over its width).
    pub fn shade(
        &self,
        look: &mut Lookup,
        m: &Material,
        index: u32,
        fp: &Footprint,
        p: [V; 3],
        c: &Corners,
    ) -> Shaded {
        let Some(b) = self.bindings.get(index as usize) else {
            return Shaded::plain(*m);
        };
        let shaded = self.apply(m, index, |slot, t| {
            let (uv, width) = b.at(slot, fp);
            look.trilinear(self, t, uv, width)
        });
        // glTF 2.0 §3.9.3: n = normalize((2·texel − 1) · (scale, scale, 1)). Read at level 0,
        // bilinear, as pbrt-v4's NormalMap reads the full-resolution image: shading is not
        // linear in the normal, so a normal averaged over a footprint biases it (a cone's
        // wide footprint after a bounce most). The coat's normal texture
        // (KHR_materials_clearcoat) reads the same way in its own slot.
        let mut bump = |slot: usize, scale: f32| {
            let t = b.slots[slot]?;
            let (uv, _) = b.at(slot, fp);
            let c = look.trilinear(self, t, uv, 0.0);
            let tn = V::new(
                (2.0 * c[0] - 1.0) * scale,
                (2.0 * c[1] - 1.0) * scale,
                2.0 * c[2] - 1.0,
            )
            .normalize();
            (tn.is_finite() && tn.z > 0.0).then_some(tn)
        };
        let normal = bump(MaterialRecord::NORMAL, b.rec.normal_scale);
        let coat = bump(MaterialRecord::COAT_NORMAL, b.rec.coat_normal_scale);
        let world = |slot: usize, tn: V| {
            let ng = (p[1] - p[0]).cross(p[2] - p[0]).normalize_or_zero();
            perturb(p, b.corners(slot, c), ng, tn)
        };
        Shaded {
            m: shaded,
            normal: normal.map(|tn| world(MaterialRecord::NORMAL, tn)),
            coat_normal: coat.map(|tn| world(MaterialRecord::COAT_NORMAL, tn)),
        }
    }

    /// `m` with each of material `index`'s textures multiplying its factor (glTF 2.0
    /// §3.9: base colour RGB; roughness from G, metalness from B; emission RGB; and the
    /// extensions': clearcoat R, clearcoat roughness G, sheen colour RGB, sheen roughness
    /// A), `texel(slot, t)` giving texture t's linear RGBA as slot `slot` reads it.
    fn apply(
        &self,
        m: &Material,
        index: u32,
        mut texel: impl FnMut(usize, u32) -> [f32; 4],
    ) -> Material {
        let mut out = *m;
        let Some(b) = self.bindings.get(index as usize) else {
            return out;
        };
        let mut read = |slot: usize| b.slots[slot].map(|t| texel(slot, t));
        if let Some(c) = read(MaterialRecord::BASE_COLOR) {
            out.base = (m.base * V::new(c[0], c[1], c[2])).clamp(V::ZERO, V::ONE);
        }
        if let Some(c) = read(MaterialRecord::METALLIC_ROUGHNESS) {
            out.metallic = (m.metallic * c[2]).clamp(0.0, 1.0);
            let r = (m.alpha.sqrt() * c[1]).clamp(0.0, 1.0);
            out.alpha = r * r;
        }
        if let Some(c) = read(MaterialRecord::EMISSIVE) {
            out.emission = (m.emission * V::new(c[0], c[1], c[2])).max(V::ZERO);
        }
        const LAYERS: usize = 4;
        if let Some(c) = read(LAYERS + MaterialRecord::CLEARCOAT) {
            out.clearcoat = (m.clearcoat * c[0]).clamp(0.0, 1.0);
        }
        if let Some(c) = read(LAYERS + MaterialRecord::CLEARCOAT_ROUGHNESS) {
            let r = (m.coat_alpha.sqrt() * c[1]).clamp(0.0, 1.0);
            out.coat_alpha = r * r;
        }
        if let Some(c) = read(LAYERS + MaterialRecord::SHEEN_COLOR) {
            out.sheen = (m.sheen * V::new(c[0], c[1], c[2])).clamp(V::ZERO, V::ONE);
        }
        if let Some(c) = read(LAYERS + MaterialRecord::SHEEN_ROUGHNESS) {
            out.sheen_roughness = (m.sheen_roughness * c[3]).clamp(0.0, 1.0);
        }
        out
    }

    /// Material `index`'s opacity at `uv`: 0 or 1 under a mask, alpha under blend (alpha
    /// the factor's times the base-colour texel's times `colour_alpha`, the vertex
    /// colour's), 1 otherwise. Alpha is read at the
    /// point, unfiltered (level 0): a cut-out's coverage must not fade with the footprint,
    /// as thresholding a filtered alpha thins distant chains and leaves, and differently for
    /// each integrator's footprint.
    pub fn opacity(
        &self,
        look: &mut Lookup,
        m: &Material,
        index: u32,
        at: &Footprint,
        colour_alpha: f32,
    ) -> f32 {
        let Some(b) = self.bindings.get(index as usize) else {
            return 1.0;
        };
        if b.mask.is_none() && !b.blend {
            return 1.0;
        }
        let base = MaterialRecord::BASE_COLOR;
        let texel = |t: u32| look.trilinear(self, t, b.at(base, at).0, 0.0)[3];
        let alpha = m.opacity * colour_alpha * b.slots[base].map_or(1.0, texel);
        match b.mask {
            Some(cut) => (alpha >= cut) as u32 as f32,
            None => alpha.clamp(0.0, 1.0),
        }
    }
}

/// A thread's texture reader: remembers the last tile it read.
pub struct Lookup<'a> {
    cache: &'a PageCache,
    last: Option<(u32, TileData)>,
}

impl<'a> Lookup<'a> {
    pub fn new(cache: &'a PageCache) -> Lookup<'a> {
        Lookup { cache, last: None }
    }

    fn tile(&mut self, index: u32) -> &TileData {
        if self.last.as_ref().is_none_or(|(i, _)| *i != index) {
            self.last = Some((index, self.cache.tile(index)));
        }
        &self.last.as_ref().expect("set above").1
    }

    /// Texel (x, y) of `level` (in range), in linear RGBA.
    fn texel(&mut self, tex: &Textures, t: u32, level: u32, x: u32, y: u32) -> [f32; 4] {
        let r = &tex.records[t as usize];
        let (tx, _) = r.level_tiles(level);
        let index = tex.level_first[t as usize][level as usize] + (y / TILE) * tx + x / TILE;
        let at = (((y % TILE) * TILE + x % TILE) * 4) as usize;
        let srgb = r.flags & TextureRecord::SRGB != 0;
        texel_to_linear(&self.tile(index)[at..at + 4], srgb)
    }

    /// Bilinear interpolation of `level` at `uv`.
    fn bilinear(&mut self, tex: &Textures, t: u32, level: u32, uv: [f32; 2]) -> [f32; 4] {
        let r = &tex.records[t as usize];
        bilinear(uv, r.level_size(level), [r.wrap(0), r.wrap(1)], |x, y| {
            self.texel(tex, t, level, x, y)
        })
    }

    /// Trilinear filtering of texture `t` at `uv` over a filter `width` (texture space).
    pub fn trilinear(&mut self, tex: &Textures, t: u32, uv: [f32; 2], width: f32) -> [f32; 4] {
        if !(uv[0].is_finite() && uv[1].is_finite()) {
            return [0.0; 4];
        }
        let levels = tex.records[t as usize].levels;
        let level = (levels - 1) as f32 + width.max(1e-8).log2();
        if level <= 0.0 {
            return self.bilinear(tex, t, 0, uv);
        }
        if level >= (levels - 1) as f32 {
            return self.texel(tex, t, levels - 1, 0, 0);
        }
        let l0 = level.floor();
        let d = level - l0;
        let a = self.bilinear(tex, t, l0 as u32, uv);
        let b = self.bilinear(tex, t, l0 as u32 + 1, uv);
        std::array::from_fn(|k| a[k] + d * (b[k] - a[k]))
    }
}

/// The two texture-space axes of a footprint `spread` wide (world units, across a ray of
/// direction `d`) on the plane of a triangle with positions `p` and texture coordinates
/// `uv`; zero where either is degenerate. The filter width is twice their largest
/// component.
fn footprint_axes(p: [V; 3], uv: [[f32; 2]; 3], d: V, spread: f32) -> [[f32; 2]; 2] {
    let none = [[0.0; 2]; 2];
    let n = (p[1] - p[0]).cross(p[2] - p[0]);
    let Some((dpdu, dpdv)) = dp_duv(p, uv) else {
        return none;
    };
    if n == V::ZERO || spread.is_nan() || spread <= 0.0 {
        return none;
    }
    let n = n.normalize();
    let d = d.normalize();
    // The footprint's two axes across the ray (the first in the plane of ray and normal,
    // the one the slant stretches), carried along the ray onto the tangent plane (grazing
    // rays: capped at 1000 times the footprint).
    let dn = d.dot(n);
    let across = n - d * dn;
    let e1 = if across.length_squared() > 1e-12 {
        across.normalize()
    } else {
        d.any_orthonormal_vector()
    };
    let e2 = d.cross(e1);
    let dn = if dn.abs() < 1e-3 {
        1e-3f32.copysign(dn)
    } else {
        dn
    };
    let ata = [dpdu.dot(dpdu), dpdu.dot(dpdv), dpdv.dot(dpdv)];
    let inv = ata[0] * ata[2] - ata[1] * ata[1];
    if inv.is_nan() || inv == 0.0 {
        return none;
    }
    [e1, e2].map(|e| {
        let dp = spread * (e - d * (e.dot(n) / dn));
        let (bu, bv) = (dpdu.dot(dp), dpdv.dot(dp));
        [
            (ata[2] * bu - ata[1] * bv) / inv,
            (ata[0] * bv - ata[1] * bu) / inv,
        ]
    })
}

/// Texture coordinates at barycentrics `b` of a triangle whose vertices have `uv`.
pub fn uv_at(uv: [[f32; 2]; 3], b: [f32; 3]) -> [f32; 2] {
    std::array::from_fn(|k| b[0] * uv[0][k] + b[1] * uv[1][k] + b[2] * uv[2][k])
}

/// ∂p/∂u and ∂p/∂v of a triangle (pbrt-v4 `Triangle::InteractionFromIntersection`); None
/// where its texture coordinates are degenerate.
fn dp_duv(p: [V; 3], uv: [[f32; 2]; 3]) -> Option<(V, V)> {
    let (duv02, duv12) = (
        [uv[0][0] - uv[2][0], uv[0][1] - uv[2][1]],
        [uv[1][0] - uv[2][0], uv[1][1] - uv[2][1]],
    );
    let (dp02, dp12) = (p[0] - p[2], p[1] - p[2]);
    let det = duv02[0] * duv12[1] - duv02[1] * duv12[0];
    if det.abs() < 1e-12 {
        return None;
    }
    Some((
        (duv12[1] * dp02 - duv02[1] * dp12) / det,
        (duv02[0] * dp12 - duv12[0] * dp02) / det,
    ))
}

/// The world-space shading normal that tangent-space normal `tn` makes on a triangle with
/// positions `p`, texture coordinates `uv` and unit front normal `n`. The tangent runs along
/// ∂p/∂u; the bitangent is n × t (glTF's convention, as Khronos' sample viewer and Mitsuba's
/// `normalmap` build it), turned round where the texture is mirrored so that it always runs
/// against ∂p/∂v: glTF's v runs down the image, a normal map's +y up it. `n` where the
/// texture coordinates are degenerate.
pub fn perturb(p: [V; 3], uv: [[f32; 2]; 3], n: V, tn: V) -> V {
    let Some((dpdu, dpdv)) = dp_duv(p, uv) else {
        return n;
    };
    let t = (dpdu - n * n.dot(dpdu)).normalize_or_zero();
    if t == V::ZERO {
        return n;
    }
    let b = n.cross(t);
    let b = if b.dot(dpdv) > 0.0 { -b } else { b };
    let s = (t * tn.x + b * tn.y + n * tn.z).normalize();
    if s.is_finite() {
        s
    } else {
        n
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The filter width of a footprint in the first stream, read through `map`.
    fn width(p: [V; 3], uv: [[f32; 2]; 3], d: V, map: [f32; 6]) -> ([f32; 2], f32) {
        let mut m = crate::import::default_material("m");
        m.textures[0] = 0;
        m.uv_transforms[0] = map;
        let c = Corners {
            uv: [uv, [[0.0; 2]; 3]],
            ..Corners::default()
        };
        let b = Binding::of(&m, 1);
        b.at(0, &Footprint::new(p, &c, [0.5, 0.25, 0.25], d, 0.01, 1))
    }

    #[test]
    fn a_footprint_head_on_maps_to_its_texture_width() {
        // A unit square with uv = xy, seen head on: a footprint of 0.01 spans 0.01 along
        // each of its axes, whose larger u or v component lies between 0.01/√2 and 0.01.
        let p = [
            V::new(0.0, 0.0, 0.0),
            V::new(1.0, 0.0, 0.0),
            V::new(0.0, 1.0, 0.0),
        ];
        let uv = [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]];
        let id = MaterialRecord::IDENTITY_UV;
        let (at, w) = width(p, uv, V::new(0.0, 0.0, -1.0), id);
        assert!((at[0] - 0.25).abs() < 1e-6 && (at[1] - 0.25).abs() < 1e-6);
        assert!(
            (0.02 / 2f32.sqrt() - 1e-6..=0.02 * 1.0001).contains(&w),
            "width {w}"
        );
        // At 60° from the normal the footprint stretches by 1/cos along one axis.
        let d = V::new(0.0, 3f32.sqrt() / 2.0, -0.5);
        let (_, w) = width(p, uv, d, id);
        assert!((w - 0.04).abs() < 1e-5, "width {w}");
    }

    #[test]
    fn a_slot_s_map_moves_its_footprint_as_mapped_coordinates_would() {
        // A slot's map applied to the footprint must give what the footprint of the
        // triangle's corners mapped first gives: point and width, for rotations, scales,
        // shears and mirrors, head on and slanted.
        let p = [
            V::new(0.0, 0.0, 0.0),
            V::new(2.0, 0.3, 0.0),
            V::new(0.1, 1.0, 0.5),
        ];
        let uv = [[0.1, 0.2], [0.9, 0.3], [0.2, 0.7]];
        for map in [
            [0.0, -1.0, 0.5, 1.0, 0.0, 0.25],
            [4.0, 0.0, 0.0, 0.0, 0.5, -3.0],
            [0.6, 0.8, 0.0, -1.6, 1.2, 2.0],
            [-1.0, 0.3, 1.0, 0.0, 1.0, 0.0],
        ] {
            let mapped = uv.map(|[u, v]| {
                [
                    map[0] * u + map[1] * v + map[2],
                    map[3] * u + map[4] * v + map[5],
                ]
            });
            for d in [V::new(0.0, 0.0, -1.0), V::new(0.3, -0.6, -0.5).normalize()] {
                let (at, w) = width(p, uv, d, map);
                let (want_at, want) = width(p, mapped, d, MaterialRecord::IDENTITY_UV);
                assert!(
                    (at[0] - want_at[0]).abs() < 1e-5 && (at[1] - want_at[1]).abs() < 1e-5,
                    "{map:?}: {at:?} against {want_at:?}"
                );
                assert!(
                    (w - want).abs() <= 1e-4 * want,
                    "{map:?}: {w} against {want}"
                );
            }
        }
    }

    #[test]
    fn the_tangent_frame_follows_u_and_runs_against_v_also_when_mirrored() {
        // The unit square in the xy plane, front +z. Per mapping: where tangent-space +x
        // and +y land. +y runs up the image (against v), so a mirrored v turns it round.
        let p = [
            V::new(0.0, 0.0, 0.0),
            V::new(1.0, 0.0, 0.0),
            V::new(0.0, 1.0, 0.0),
        ];
        let n = V::Z;
        for (uv, t, b) in [
            ([[0.0, 1.0], [1.0, 1.0], [0.0, 0.0]], V::X, V::Y),
            ([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], V::X, -V::Y),
            ([[0.0, 0.0], [0.0, 1.0], [1.0, 0.0]], V::Y, -V::X),
        ] {
            assert!(perturb(p, uv, n, V::Z).distance(n) < 1e-6);
            let along_t = perturb(p, uv, n, V::new(0.6, 0.0, 0.8));
            assert!(
                along_t.distance(t * 0.6 + n * 0.8) < 1e-5,
                "{uv:?}: {along_t}"
            );
            let along_b = perturb(p, uv, n, V::new(0.0, 0.6, 0.8));
            assert!(
                along_b.distance(b * 0.6 + n * 0.8) < 1e-5,
                "{uv:?}: {along_b}"
            );
        }
        // Degenerate coordinates leave the normal alone.
        assert_eq!(perturb(p, [[0.5, 0.5]; 3], n, V::new(0.6, 0.0, 0.8)), n);
    }
}
