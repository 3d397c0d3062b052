//! Cluster attributes aggregated bottom-up (004 §4.2–4.4): every parameter is the
//! area-weighted mean of the children, the normal is the area-weighted mean of unit face
//! normals and deliberately not normalized.

use canopy_format::codec::{f16_encode, rgbe64_encode, snorm16, unorm8};
use canopy_format::{MaterialRecord, Node, NodeFlags};

/// cos θ at which the Fresnel table is sampled (004 §4.3.1, five samples).
pub const REFLECT_COS: [f32; 5] = [0.0, 0.25, 0.5, 0.75, 1.0];

/// What a material contributes to a node, per unit area.
#[derive(Clone, Copy, Debug, Default)]
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
    pub fn of(m: &MaterialRecord) -> Self {
        let base = [m.base_color[0], m.base_color[1], m.base_color[2]].map(|c| c.clamp(0.0, 1.0));
        let metal = m.metallic.clamp(0.0, 1.0);
        let trans = m.transmission.clamp(0.0, 1.0) * (1.0 - metal);
        let r0 = ((m.ior - 1.0) / (m.ior + 1.0)).powi(2);
        let spec = m.specular.clamp(0.0, 1.0);
        let f0_d = m.specular_color.map(|c| (r0 * c).clamp(0.0, 1.0));
        let f0 = [0, 1, 2].map(|i| f0_d[i] * (1.0 - metal) + base[i] * metal);
        let f0_max = f0[0].max(f0[1]).max(f0[2]);
        let f0d_max = f0_d[0].max(f0_d[1]).max(f0_d[2]);
        let bmax = base[0].max(base[1]).max(base[2]);
        let reflect = REFLECT_COS
            .map(|c| (1.0 - metal) * spec * schlick(f0d_max, c) + metal * schlick(bmax, c));
        let mut flags = 0;
        if m.emission.iter().any(|&e| e > 0.0) {
            flags |= NodeFlags::EMISSIVE;
        }
        if reflect.iter().any(|&r| r > 0.0) {
            flags |= NodeFlags::GLOSSY;
        }
        if trans > 0.0 {
            flags |= NodeFlags::TRANSMISSIVE;
        }
        Self {
            diffuse: base.map(|c| c * (1.0 - metal) * (1.0 - trans)),
            refractiveness: trans,
            translucency: if trans > 0.0 { base } else { [0.0; 3] },
            reflect,
            tint: if f0_max > 0.0 {
                f0.map(|c| c / f0_max)
            } else {
                [0.0; 3]
            },
            roughness: m.roughness.clamp(0.0, 1.0),
            ior: m.ior,
            emission: m.emission.map(|e| e.max(0.0)),
            flags,
        }
    }
}

/// Area-weighted sums; divide by `weight` for the means.
#[derive(Clone, Copy, Debug, Default)]
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
