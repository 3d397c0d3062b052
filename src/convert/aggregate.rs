//! Cluster attributes aggregated bottom-up (004 §4.2–4.4): every parameter is the
//! area-weighted mean of the children, the normal is the area-weighted mean of unit face
//! normals and deliberately not normalized.

use super::textures::Coarse;
use crate::import::{SpillTri, WHITE};
use crate::material::coat_fresnel;
use canopy_format::codec::{f16_encode, rgbe64_encode, snorm16, unorm8};
use canopy_format::{cofactors3, det3};
use canopy_format::{MaterialRecord, Node, NodeFlags, TextureRecord};

/// cos θ at which the Fresnel table is sampled (004 §4.3.1, five samples).
pub const REFLECT_COS: [f32; 5] = [0.0, 0.25, 0.5, 0.75, 1.0];

/// What a material contributes to a node, per unit area.
#[derive(Clone, Copy, Debug, Default, serde::Serialize, serde::Deserialize)]
pub struct MatSummary {
    pub diffuse: [f32; 3],
    pub refractiveness: f32,
    pub translucency: [f32; 3],
    pub reflect: [f32; 5],
    pub tint: [f32; 3],
    pub roughness: f32,
    pub ior: f32,
    pub emission: [f32; 3],
    pub flags: u8,
}

fn schlick(f0: f32, cos: f32) -> f32 {
    f0 + (1.0 - f0) * (1.0 - cos).powi(5)
}

impl MatSummary {
    /// glTF metallic-roughness (spec Appendix B) reduced to the thesis' cluster BRDF:
    /// p_reflect(θ) from Schlick with the layer's F0 and weight, refraction and diffuse
    /// fractions from transmission and the base colour.
    ///
    /// A textured factor is scaled by its texture's mean over the whole image: a cluster's
    /// value is the mean over the texture, not yet over the texels under its triangles.
    pub fn of(m: &MaterialRecord, textures: &[TextureRecord]) -> Self {
        let mean = |slot: usize| {
            textures
                .get(m.textures[slot] as usize)
                .map_or([1.0; 4], |t| t.mean)
        };
        let (tex_base, tex_emit) = (
            mean(MaterialRecord::BASE_COLOR),
            mean(MaterialRecord::EMISSIVE),
        );
        let base = [0, 1, 2].map(|c| (m.base_color[c] * tex_base[c]).clamp(0.0, 1.0));
        let coverage = coverage(m, tex_base[3]);
        let hole = 1.0 - coverage;
        let mut m = *m;
        m.emission = [0, 1, 2].map(|c| m.emission[c] * tex_emit[c] * coverage);
        let m = &m;
        let metal = m.metallic.clamp(0.0, 1.0);
        let trans = m.transmission.clamp(0.0, 1.0) * (1.0 - metal);
        let r0 = ((m.ior - 1.0) / (m.ior + 1.0)).powi(2);
        let spec = m.specular.clamp(0.0, 1.0);
        let f0_d = m.specular_color.map(|c| (r0 * c).clamp(0.0, 1.0));
        let f0 = [0, 1, 2].map(|i| f0_d[i] * (1.0 - metal) + base[i] * metal);
        let f0_max = f0[0].max(f0[1]).max(f0[2]);
        let f0d_max = f0_d[0].max(f0_d[1]).max(f0_d[2]);
        let bmax = base[0].max(base[1]).max(base[2]);
        // A clearcoat reflects coat·F(cos θ) above the rest, which it scales by 1 − that
        // (KHR_materials_clearcoat); a sheen's albedo scales the layer below it.
        let coat = m.clearcoat.clamp(0.0, 1.0);
        let sheen = sheen_albedo(m);
        let below = |c: f32| (1.0 - coat * coat_fresnel(c)) * (1.0 - sheen.1);
        let base_at =
            |c: f32| (1.0 - metal) * spec * schlick(f0d_max, c) + metal * schlick(bmax, c);
        let reflect =
            REFLECT_COS.map(|c| coverage * (base_at(c) * below(c) + coat * coat_fresnel(c)));
        // The base's reflectance at normal incidence, against the coat's 0.04.
        let base_normal = base_at(1.0);
        // The layers over the diffuse lobe at their hemispherical means: the coat's
        // Fresnel 0.04 + 0.96·2/42, the sheen's albedo (reflected as if diffuse).
        let diffuse_below = (1.0 - coat * COAT_FRESNEL_MEAN) * (1.0 - sheen.1);
        // What passes: light refracted by the material, and through alpha holes untinted.
        let passing = hole + coverage * trans;
        let mut flags = 0;
        if m.emission.iter().any(|&e| e > 0.0) {
            flags |= NodeFlags::EMISSIVE;
        }
        if reflect.iter().any(|&r| r > 0.0) {
            flags |= NodeFlags::GLOSSY;
        }
        if passing > 0.0 {
            flags |= NodeFlags::TRANSMISSIVE;
        }
        Self {
            diffuse: [0, 1, 2].map(|i| {
                let d = base[i] * (1.0 - metal) * (1.0 - trans) * diffuse_below;
                (d + sheen.0[i]) * coverage
            }),
            refractiveness: passing,
            translucency: base.map(|c| hole + coverage * trans * c),
            reflect,
            tint: if f0_max > 0.0 {
                f0.map(|c| c / f0_max)
            } else {
                [0.0; 3]
            },
            // The stronger reflection's at normal incidence.
            roughness: match coat * 0.04 >= base_normal {
                true => m.clearcoat_roughness.clamp(0.0, 1.0),
                false => m.roughness.clamp(0.0, 1.0),
            },
            ior: m.ior,
            emission: m.emission.map(|e| e.max(0.0)),
            flags,
        }
    }
}

/// The clearcoat's Schlick Fresnel (`material::coat_fresnel`) averaged over the hemisphere,
/// weighted by cos θ: 0.04 + 0.96·2/42.
const COAT_FRESNEL_MEAN: f32 = 0.04 + 0.96 * 2.0 / 42.0;

/// A sheen's hemispherical-mean albedo per channel and the largest channel's: what it
/// reflects of uniform light, and what it takes from the layer below.
fn sheen_albedo(m: &MaterialRecord) -> ([f32; 3], f32) {
    let c = m.sheen_color.map(|c| c.clamp(0.0, 1.0));
    if c == [0.0; 3] {
        return ([0.0; 3], 0.0);
    }
    let e = crate::material::sheen_mean_albedo(m.sheen_roughness.clamp(0.0, 1.0));
    (c.map(|c| c * e), c[0].max(c[1]).max(c[2]) * e)
}

/// The share of a material's surface that is there (glTF 2.0 §3.9.4 alpha as coverage),
/// `tex_alpha` its base-colour texture's mean alpha (1 without one): under BLEND the mean
/// alpha; under MASK the share of texels the cutoff keeps, which a texture's mean alpha
/// stands for (exact for masks of 0 and 1); an untextured mask keeps all or nothing.
fn coverage(m: &MaterialRecord, tex_alpha: f32) -> f32 {
    let alpha = (m.base_color[3] * tex_alpha).clamp(0.0, 1.0);
    let textured = m.textures[MaterialRecord::BASE_COLOR] != MaterialRecord::NO_TEXTURE;
    if m.flags & MaterialRecord::ALPHA_BLEND != 0
        || (m.flags & MaterialRecord::ALPHA_MASK != 0 && textured)
    {
        alpha
    } else if m.flags & MaterialRecord::ALPHA_MASK != 0 {
        (alpha >= m.alpha_cutoff) as u32 as f32
    } else {
        1.0
    }
}

/// The materials as the tree sees them: each material's summary over its whole textures
/// (`MatSummary::of`), and for a textured one what a single triangle takes instead: its
/// textures' mean over the texels under it (004 §4.2–4.4 with textures), from the coarse
/// level whose texel spans the triangle (`Coarse::mean_over`).
pub struct MatTable {
    pub summaries: Vec<MatSummary>,
    records: Vec<MaterialRecord>,
    textures: Vec<TextureRecord>,
    coarse: Vec<Coarse>,
}

impl MatTable {
    pub fn new(
        records: &[MaterialRecord],
        textures: &[TextureRecord],
        coarse: Vec<Coarse>,
    ) -> Self {
        MatTable {
            summaries: records
                .iter()
                .map(|m| MatSummary::of(m, textures))
                .collect(),
            records: records.to_vec(),
            textures: textures.to_vec(),
            coarse,
        }
    }

    /// The textures' coarse levels, as `new` took them.
    pub fn into_coarse(self) -> Vec<Coarse> {
        self.coarse
    }

    /// What triangle `t` contributes per unit area (its vertex colours and the texels
    /// under it applied).
    pub fn of(&self, t: &SpillTri) -> MatSummary {
        let i = t.material as usize;
        let m = &self.records[i];
        let slots = [
            MaterialRecord::BASE_COLOR,
            MaterialRecord::METALLIC_ROUGHNESS,
            MaterialRecord::EMISSIVE,
        ];
        let coloured = t.colour != [WHITE; 3];
        if !coloured
            && slots
                .iter()
                .all(|&s| m.textures[s] as usize >= self.textures.len())
        {
            return self.summaries[i];
        }
        let mut rec = *m;
        if coloured {
            // The vertex colour multiplies the base colour (glTF 2.0 §3.9.2); linear over
            // the triangle, its mean is the vertices' mean.
            for k in 0..4 {
                let mean = t.colour.iter().map(|c| c[k] as f32).sum::<f32>() / (3.0 * 65535.0);
                rec.base_color[k] *= mean;
            }
        }
        for slot in slots {
            let Some(tex) = self.textures.get(m.textures[slot] as usize) else {
                continue;
            };
            let uv = [0, 1, 2].map(|k| m.slot_uv(slot, [t.uv[k], t.uv2[k]]));
            let c = self.coarse[m.textures[slot] as usize].mean_over(tex, &uv);
            match slot {
                MaterialRecord::BASE_COLOR => {
                    (0..4).for_each(|k| rec.base_color[k] *= c[k]);
                    // The mean alpha is now a coverage, whichever the mode.
                    if rec.flags & MaterialRecord::ALPHA_MASK != 0 {
                        rec.flags ^= MaterialRecord::ALPHA_MASK | MaterialRecord::ALPHA_BLEND;
                    }
                }
                MaterialRecord::EMISSIVE => (0..3).for_each(|k| rec.emission[k] *= c[k]),
                _ => {
                    rec.metallic *= c[2];
                    rec.roughness *= c[1];
                }
            }
            rec.textures[slot] = MaterialRecord::NO_TEXTURE;
        }
        // The archive's features come from whole materials; a triangle keeps their
        // aggregate flags so the root's flags and the features agree.
        let mut s = MatSummary::of(&rec, &self.textures);
        s.flags |= self.summaries[i].flags;
        s
    }
}

/// Area-weighted sums; divide by `weight` for the means.
#[derive(Clone, Copy, Debug, Default, serde::Serialize, serde::Deserialize)]
pub struct Cluster {
    pub area: f32,
    pub weight: f32,
    pub normal: [f32; 3],
    pub centroid: [f32; 3],
    pub radius: f32,
    pub curvature: f32,
    pub m: MatSummary,
}

/// Euclidean distance in f64 (exact to well under an f32 ulp of the result).
pub fn distance(a: [f32; 3], b: [f32; 3]) -> f64 {
    (0..3)
        .map(|i| (a[i] as f64 - b[i] as f64).powi(2))
        .sum::<f64>()
        .sqrt()
}

/// σ_max of the 3×3 part of `m`: the square root of the largest eigenvalue of MᵀM, by the
/// trigonometric solution of the symmetric eigenproblem.
fn largest_singular_value(m: &[[f64; 4]; 3]) -> f64 {
    let a: [[f64; 3]; 3] =
        std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| m[k][i] * m[k][j]).sum()));
    let p1 = a[0][1].powi(2) + a[0][2].powi(2) + a[1][2].powi(2);
    let q = (a[0][0] + a[1][1] + a[2][2]) / 3.0;
    let p2 = (0..3).map(|i| (a[i][i] - q).powi(2)).sum::<f64>() + 2.0 * p1;
    let p = (p2 / 6.0).sqrt();
    if p <= q.abs() * 1e-15 {
        return q.max(0.0).sqrt();
    }
    let b: [[f64; 3]; 3] = std::array::from_fn(|i| {
        std::array::from_fn(|j| (a[i][j] - if i == j { q } else { 0.0 }) / p)
    });
    let phi = (det3(&b) / 2.0).clamp(-1.0, 1.0).acos() / 3.0;
    (q + 2.0 * p * phi.cos()).max(0.0).sqrt()
}

/// The smallest f32 ≥ x (x a distance, so ≥ 0; f64's own rounding is 2⁻²⁹ of an f32 ulp and
/// the next f32 up covers it), so a radius stays conservative after rounding.
pub fn round_up(x: f64) -> f32 {
    let f = x as f32;
    if f as f64 >= x * (1.0 + 1e-15) {
        f
    } else {
        f.next_up()
    }
}

fn add3(a: &mut [f32; 3], b: [f32; 3], w: f32) {
    for i in 0..3 {
        a[i] += b[i] * w;
    }
}

impl Cluster {
    /// A triangle's contribution. Zero-area triangles still carry a tiny weight so a leaf of
    /// degenerate triangles gets defined means.
    pub fn triangle(p: &[[f32; 3]; 3], curvature: f32, m: &MatSummary) -> Self {
        let e1 = [0, 1, 2].map(|a| p[1][a] as f64 - p[0][a] as f64);
        let e2 = [0, 1, 2].map(|a| p[2][a] as f64 - p[0][a] as f64);
        let c = [
            e1[1] * e2[2] - e1[2] * e2[1],
            e1[2] * e2[0] - e1[0] * e2[2],
            e1[0] * e2[1] - e1[1] * e2[0],
        ];
        let len = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
        let area = (0.5 * len) as f32;
        let normal = if len > 0.0 {
            c.map(|x| (x / len) as f32)
        } else {
            [0.0; 3]
        };
        let centroid =
            [0, 1, 2].map(|a| ((p[0][a] as f64 + p[1][a] as f64 + p[2][a] as f64) / 3.0) as f32);
        let radius = p.iter().map(|v| distance(*v, centroid)).fold(0.0, f64::max);
        let radius = round_up(radius);
        let w = area.max(1e-30);
        let mut s = Cluster {
            area,
            weight: w,
            radius,
            curvature: curvature * w,
            ..Default::default()
        };
        add3(&mut s.normal, normal, w);
        add3(&mut s.centroid, centroid, w);
        s.add_material(m, w);
        s
    }

    /// Adds `m` scaled by `w` (a triangle's area, or 1 for sums that are already weighted).
    fn add_material(&mut self, m: &MatSummary, w: f32) {
        add3(&mut self.m.diffuse, m.diffuse, w);
        add3(&mut self.m.translucency, m.translucency, w);
        add3(&mut self.m.tint, m.tint, w);
        add3(&mut self.m.emission, m.emission, w);
        for i in 0..5 {
            self.m.reflect[i] += m.reflect[i] * w;
        }
        self.m.refractiveness += m.refractiveness * w;
        self.m.roughness += m.roughness * w;
        self.m.ior += m.ior * w;
        self.m.flags |= m.flags;
    }

    /// Sum of two clusters; the radius bounds both children's spheres around the new centroid.
    pub fn merge(a: &Cluster, b: &Cluster) -> Cluster {
        let mut s = *a;
        s.area += b.area;
        s.weight += b.weight;
        s.curvature += b.curvature;
        add3(&mut s.normal, b.normal, 1.0);
        add3(&mut s.centroid, b.centroid, 1.0);
        s.add_material(&b.m, 1.0);
        let c = s.mean_centroid();
        let reach = |x: &Cluster| distance(x.mean_centroid(), c) + x.radius as f64;
        s.radius = round_up(reach(a).max(reach(b)));
        s
    }

    /// The cluster of a subtree's image under the affine map `m` (rows, column 3 the
    /// translation): the means of its materials are unchanged; the
    /// centroid is mapped; the radius grows by the largest singular value; area scales by
    /// |det|^⅔ and curvature by |det|^−⅓ (exact for rotations, uniform scales, mirrors and
    /// translations; a mean over a non-uniform stretch would need every triangle); the
    /// normal sum maps by the cofactor matrix det·M⁻ᵀ (how a stretched triangle's
    /// e1 × e2 maps, winding reversed by mirrors), scaled so its length keeps meaning
    /// coherence (at most 1).
    pub fn transformed(&self, m: &[[f64; 4]; 3]) -> Cluster {
        let linear = m.map(|row| [row[0], row[1], row[2]]);
        let (cof, det) = (cofactors3(&linear), det3(&linear));
        let s2 = det.abs().powf(2.0 / 3.0);
        let map = |p: [f64; 3]| [0, 1, 2].map(|r| (0..3).map(|c| m[r][c] * p[c]).sum::<f64>());
        let n = self.normal.map(f64::from);
        let mut normal = [0, 1, 2].map(|r| (0..3).map(|c| cof[r][c] * n[c]).sum::<f64>() / s2);
        let len = normal.iter().map(|x| x * x).sum::<f64>().sqrt();
        let w = self.weight as f64;
        if len > w {
            normal = normal.map(|x| x * w / len);
        }
        let c = self.mean_centroid().map(f64::from);
        let mc = map(c);
        let centre = [0, 1, 2].map(|r| mc[r] + m[r][3]);
        let mut out = Cluster {
            area: (self.area as f64 * s2) as f32,
            normal: normal.map(|x| x as f32),
            centroid: centre.map(|x| (x * w) as f32),
            curvature: (self.curvature as f64 / det.abs().cbrt()) as f32,
            ..*self
        };
        let stored = out.mean_centroid();
        let reach = self.radius as f64 * largest_singular_value(m) * (1.0 + 1e-6);
        out.radius = round_up(reach + distance(stored, centre.map(|x| x as f32)) + f64::EPSILON);
        out
    }

    pub fn mean_centroid(&self) -> [f32; 3] {
        self.centroid.map(|c| c / self.weight)
    }

    /// The node record's cluster fields (bounds, link, centroid and structural flags are set
    /// when the node is placed in a page).
    pub fn encode(&self) -> Node {
        let w = self.weight;
        let mean3 = |v: [f32; 3]| v.map(|c| c / w);
        let mut n: Node = bytemuck::Zeroable::zeroed();
        n.area = self.area;
        n.radius = self.radius;
        n.normal = mean3(self.normal).map(snorm16);
        n.curvature = f16_encode(self.curvature / w);
        n.ior = f16_encode(self.m.ior / w);
        n.flags = self.m.flags;
        n.roughness = unorm8(self.m.roughness / w);
        n.emission = rgbe64_encode(mean3(self.m.emission));
        n.diffuse = mean3(self.m.diffuse).map(unorm8);
        n.refractiveness = unorm8(self.m.refractiveness / w);
        n.translucency = mean3(self.m.translucency).map(unorm8);
        n.visible_area = 255;
        n.reflectiveness = self.m.reflect.map(|r| unorm8(r / w));
        n.specular_tint = mean3(self.m.tint).map(unorm8);
        n.coef = u32::MAX;
        n
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_rng::TestRng;

    /// Rows of a rotation about a random axis, scaled per axis by `s`, then translated.
    fn affine(rng: &mut TestRng, s: [f64; 3]) -> [[f64; 4]; 3] {
        let a = glam::DVec3::new(rng.f64() - 0.5, rng.f64() - 0.5, rng.f64() - 0.5).normalize();
        let r = glam::DMat3::from_axis_angle(a, rng.f64() * 6.0);
        std::array::from_fn(|row| {
            let mut m = [0.0; 4];
            for c in 0..3 {
                m[c] = r.col(c)[row] * s[c];
            }
            m[3] = (rng.f64() - 0.5) * 100.0;
            m
        })
    }

    /// Alpha as coverage: holes pass light untinted, the rest keeps the material's terms.
    #[test]
    fn alpha_holes_pass_light_in_proportion_to_their_share() {
        let mut m = crate::import::default_material("m");
        m.base_color = [0.6, 0.6, 0.6, 1.0];
        m.emission = [2.0; 3];
        m.specular = 1.0;
        let opaque = MatSummary::of(&m, &[]);
        assert!(opaque.reflect[0] > 0.0);
        let tex = TextureRecord {
            mean: [1.0, 1.0, 1.0, 0.25],
            ..bytemuck::Zeroable::zeroed()
        };
        let cases = [
            (MaterialRecord::ALPHA_MASK, 1.0, Some(0), 0.25),
            (MaterialRecord::ALPHA_BLEND, 0.4, None, 0.4),
            (MaterialRecord::ALPHA_MASK, 0.4, None, 0.0),
            (MaterialRecord::ALPHA_MASK, 0.6, None, 1.0),
            (0, 0.4, Some(0), 1.0),
        ];
        for (mode, alpha, texture, a) in cases {
            let mut r = m;
            r.flags |= mode;
            r.base_color[3] = alpha;
            r.textures[MaterialRecord::BASE_COLOR] = texture.unwrap_or(MaterialRecord::NO_TEXTURE);
            let s = MatSummary::of(&r, &[tex]);
            let what = format!("mode {mode}, alpha {alpha}, texture {texture:?}");
            assert!((s.refractiveness - (1.0 - a)).abs() < 1e-6, "{what}");
            assert!(
                (s.diffuse[0] - a * opaque.diffuse[0]).abs() < 1e-6,
                "{what}"
            );
            assert!((s.translucency[1] - (1.0 - a)).abs() < 1e-6, "{what}");
            assert!((s.emission[2] - a * 2.0).abs() < 1e-6, "{what}");
            for k in 0..5 {
                assert!(
                    (s.reflect[k] - a * opaque.reflect[k]).abs() < 1e-6,
                    "{what}"
                );
            }
            assert_eq!(s.flags & NodeFlags::TRANSMISSIVE != 0, a < 1.0, "{what}");
        }
    }

    /// A transformed cluster's sphere holds every mapped vertex (any affine map), and its
    /// area and normal are what the mapped triangles' would give for rotations, uniform
    /// scales and mirrors.
    #[test]
    fn transformed_clusters_bound_and_match_their_mapped_triangles() {
        let mut rng = TestRng::new(11);
        let m = MatSummary::of(&crate::import::default_material("m"), &[]);
        for case in 0..200 {
            let tris: Vec<[[f32; 3]; 3]> = (0..1 + case % 7)
                .map(|_| {
                    let c = rng.v(10.0);
                    [0, 1, 2].map(|_| (c + rng.v(1.0)).to_array())
                })
                .collect();
            let sum = |t: &[[[f32; 3]; 3]]| {
                t.iter()
                    .map(|p| Cluster::triangle(p, 0.0, &m))
                    .reduce(|a, b| Cluster::merge(&a, &b))
                    .unwrap()
            };
            let uniform = case % 2 == 0;
            let k = 0.1 + rng.f64() * 3.0;
            let sign = if case % 3 == 0 { -1.0 } else { 1.0 };
            let s = match uniform {
                true => [sign * k, k, k],
                false => [sign * k, 0.2 + rng.f64(), 1.0 + rng.f64() * 4.0],
            };
            let map = affine(&mut rng, s);
            let got = sum(&tris).transformed(&map);
            let moved: Vec<[[f32; 3]; 3]> = tris
                .iter()
                .map(|t| {
                    t.map(|p| {
                        [0, 1, 2].map(|r| {
                            (0..3).map(|c| map[r][c] * p[c] as f64).sum::<f64>() as f32
                                + map[r][3] as f32
                        })
                    })
                })
                .collect();
            let centre = got.mean_centroid();
            for v in moved.iter().flatten() {
                let d = distance(*v, centre);
                assert!(
                    d <= got.radius as f64 * (1.0 + 1e-5),
                    "case {case}: {d} > {}",
                    got.radius
                );
            }
            if uniform {
                let want = sum(&moved);
                let rel = (got.area / want.area - 1.0).abs();
                assert!(
                    rel < 1e-3,
                    "case {case}: area {} vs {}",
                    got.area,
                    want.area
                );
                let (a, b) = (
                    got.normal.map(|x| x / got.weight),
                    want.normal.map(|x| x / want.weight),
                );
                for i in 0..3 {
                    assert!(
                        (a[i] - b[i]).abs() < 1e-3,
                        "case {case}: normal {a:?} vs {b:?}"
                    );
                }
            }
        }
    }
}
