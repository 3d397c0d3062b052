//! Light sources: emissive triangles (front side only unless the material is
//! double-sided) and glTF punctual lights. A shading point chooses one through the light
//! tree (`tree`) by a bound on what each can send it; photons leave them in proportion to
//! power.
//!
//! Emitters are gathered once by walking only the subtrees whose nodes carry the EMISSIVE
//! flag, so a huge scene with a few lamps loads a few pages.

use crate::material::{cosine_hemisphere, luminance, Frame, Material};
use crate::paging::{NodeRef, Page};
use crate::trace::{offset_origin, Ray};
use anyhow::Result;
use canopy_format::{Archive, LightRecord, NodeFlags};
use glam::Vec3A as V;
use std::collections::HashMap;
use std::f32::consts::PI;
use tree::{LightBounds, LightTree};

pub mod tree;

pub struct Emitter {
    pub p: [V; 3],
    pub area: f32,
    /// Unit geometric normal (front side).
    pub n: V,
    /// Radiance; a textured lamp's mean over its texture.
    pub le: V,
    pub two_sided: bool,
    /// A textured lamp's material and vertex texture coordinates.
    pub texel: Option<(u32, [[f32; 2]; 3])>,
}

impl Emitter {
    /// A lamp triangle; None if it is degenerate.
    pub fn triangle(p: [V; 3], le: V, two_sided: bool) -> Option<Emitter> {
        let c = (p[1] - p[0]).cross(p[2] - p[0]);
        let area = 0.5 * c.length();
        (area > 0.0 && area.is_finite()).then(|| Emitter {
            p,
            area,
            n: c / (2.0 * area),
            le,
            two_sided,
            texel: None,
        })
    }

    /// A uniform point on the triangle, its error bound, and where it falls in a textured
    /// lamp's texture.
    fn point(&self, u: [f32; 2]) -> (V, V, Option<(u32, [f32; 2])>) {
        let su = u[0].sqrt();
        let b = [1.0 - su, u[1] * su, 1.0 - (1.0 - su) - u[1] * su];
        let q = self.p[0] * b[0] + self.p[1] * b[1] + self.p[2] * b[2];
        let err =
            self.p[0].abs().max(self.p[1].abs()).max(self.p[2].abs()) * crate::trace::gamma(7);
        let texel = self.texel.map(|(m, uv)| {
            (
                m,
                std::array::from_fn(|k| b[0] * uv[0][k] + b[1] * uv[1][k] + b[2] * uv[2][k]),
            )
        });
        (q, err, texel)
    }
}

pub enum Punctual {
    /// Radiant intensity (glTF candela), spot cone cosines (−1 for a point light).
    Spot {
        pos: V,
        dir: V,
        intensity: V,
        cos_outer: f32,
        cos_inner: f32,
    },
    /// Irradiance (glTF lux) arriving along `dir`.
    Directional { dir: V, irradiance: V },
}

/// One light sample seen from a shading point.
pub struct LightSample {
    /// Unit direction to the light.
    pub wi: V,
    /// Distance to the sampled point (∞ for directional).
    pub dist: f32,
    /// The sampled point, its error bound and its surface normal (for the shadow ray's
    /// far end); None for directional lights.
    pub point: Option<(V, V, V)>,
    /// Radiance (area) or radiance-equivalent (delta) arriving, divided by the pdf.
    pub weight: V,
    /// Solid-angle pdf (area lights), 0 for delta lights.
    pub pdf: f32,
    /// On a textured lamp, its material and the texture point sampled: `weight` holds the
    /// lamp's mean radiance, which the texel there over the mean turns into the radiance.
    pub texel: Option<(u32, [f32; 2])>,
}

impl LightSample {
    /// The shadow ray from `from` (already offset off its surface) to the sampled point,
    /// whose own end is offset off the light's surface; unit direction.
    pub fn shadow_ray(&self, from: V) -> Ray {
        match self.point {
            Some((q, qerr, qn)) => {
                let to = offset_origin(q, qerr, qn, from - q);
                let len = (to - from).length();
                Ray {
                    o: from,
                    d: (to - from) / len,
                    t_max: len * (1.0 - 1e-4),
                }
            }
            None => Ray {
                o: from,
                d: self.wi,
                t_max: f32::INFINITY,
            },
        }
    }
}

pub struct Lights {
    pub emitters: Vec<Emitter>,
    pub punctual: Vec<Punctual>,
    /// Cumulative power, emitters first, then punctual lights (photon emission).
    cdf: Vec<f32>,
    /// Chooses lights for shading points; lights numbered as in `cdf`.
    tree: LightTree,
    /// Emitter of each lamp triangle, by its leaf's global node number and its slot there
    /// (what a hit carries).
    by_leaf: HashMap<(u64, u32), u32>,
    total: f32,
    /// Bounding sphere of the scene (directional lights emit through its disc).
    center: V,
    radius: f32,
}

/// A photon leaving a light: its ray and its power (divided by the sampling pdfs).
pub struct Photon {
    pub ray: Ray,
    pub flux: V,
    /// As `LightSample::texel`, for `flux`.
    pub texel: Option<(u32, [f32; 2])>,
}

/// Power of an emitter as the light chooser weighs it.
fn emitter_power(le: V, area: f32, two_sided: bool) -> f32 {
    PI * luminance(le) * area * if two_sided { 2.0 } else { 1.0 }
}

impl Lights {
    /// The archive's lamps, with `materials`' emission (a texture's mean for those whose
    /// emission is `textured`).
    pub fn gather(
        archive: &Archive,
        materials: &[Material],
        textured: impl Fn(u32) -> bool,
        scene_radius: f32,
    ) -> Result<Lights> {
        let mut emitters = Vec::new();
        let mut by_leaf = HashMap::new();
        let mut stack: Vec<(u32, u32)> = Vec::new();
        let root = Page::decode(archive, archive.header.root_page)?;
        let mut pages = vec![root];
        for r in 0..pages[0].roots {
            stack.push((0, r));
        }
        while let Some((pi, ni)) = stack.pop() {
            let page = &pages[pi as usize];
            let Some(node) = page.nodes.get(ni as usize) else {
                continue;
            };
            if node.flags & NodeFlags::EMISSIVE == 0 {
                continue;
            }
            match page.bvh[ni as usize].link() {
                NodeRef::Leaf { first, count } => {
                    let leaf = page.first_node + ni as u64;
                    for slot in 0..count {
                        let Some(tri) = page.tri(first + slot) else {
                            continue;
                        };
                        let m = &materials[tri.material as usize];
                        if !m.is_emissive() {
                            continue;
                        }
                        let e = Emitter::triangle(tri.p.map(V::from), m.emission, m.double_sided);
                        if let Some(mut e) = e {
                            if textured(tri.material) {
                                let uv = page.uvs.get((first + slot) as usize).copied();
                                e.texel = Some((tri.material, uv.unwrap_or_default()));
                            }
                            by_leaf.insert((leaf, slot), emitters.len() as u32);
                            emitters.push(e);
                        }
                    }
                }
                NodeRef::Inner(l, r) => stack.extend([(pi, l), (pi, r)]),
                // Never emissive (checked when the page is read): skipped above.
                NodeRef::Instance(_) => {}
                NodeRef::ChildPage(child) => {
                    pages.push(Page::decode(archive, child)?);
                    let at = pages.len() as u32 - 1;
                    stack.extend([(at, 0), (at, 1)]);
                }
            }
        }
        let punctual = archive
            .lights
            .iter()
            .filter_map(punctual)
            .collect::<Vec<_>>();
        let h = &archive.header;
        let center = 0.5 * (V::from(h.bounds_min) + V::from(h.bounds_max));
        Ok(Lights {
            by_leaf,
            ..Lights::new(emitters, punctual, center, scene_radius)
        })
    }

    /// Lights of a scene whose bounding sphere has this center and radius.
    pub fn new(
        emitters: Vec<Emitter>,
        punctual: Vec<Punctual>,
        center: V,
        scene_radius: f32,
    ) -> Lights {
        // Each light's power feeds the photon CDF; its bounds (or none, for a directional
        // light) the tree.
        let mut cdf = Vec::with_capacity(emitters.len() + punctual.len());
        let mut total = 0.0f64;
        let mut add = |power: f32| {
            total += power as f64;
            cdf.push(total as f32);
        };
        let mut bounded = Vec::new();
        let mut infinite = Vec::new();
        for (i, e) in emitters.iter().enumerate() {
            let phi = emitter_power(e.le, e.area, e.two_sided);
            add(phi);
            bounded.push((
                i as u32,
                LightBounds {
                    lo: e.p[0].min(e.p[1]).min(e.p[2]),
                    hi: e.p[0].max(e.p[1]).max(e.p[2]),
                    w: e.n,
                    cos_o: 1.0,
                    cos_e: 0.0,
                    phi,
                    two_sided: e.two_sided,
                },
            ));
        }
        for (k, l) in punctual.iter().enumerate() {
            let i = (emitters.len() + k) as u32;
            match l {
                // pbrt-v4 `SpotLight::Bounds`: the normal cone is the full-intensity cone
                // and light leaves up to the outer one beyond it.
                Punctual::Spot {
                    pos,
                    dir,
                    intensity,
                    cos_outer,
                    cos_inner,
                } => {
                    add(2.0 * PI * (1.0 - cos_outer) * luminance(*intensity));
                    let (cos_o, cos_e) = if *cos_outer <= -1.0 {
                        (-1.0, 0.0)
                    } else {
                        let inner = cos_inner.clamp(-1.0, 1.0).acos();
                        let outer = cos_outer.clamp(-1.0, 1.0).acos();
                        (*cos_inner, (outer - inner).max(0.0).cos())
                    };
                    bounded.push((
                        i,
                        LightBounds {
                            lo: *pos,
                            hi: *pos,
                            w: *dir,
                            cos_o,
                            cos_e,
                            phi: 4.0 * PI * luminance(*intensity),
                            two_sided: false,
                        },
                    ));
                }
                Punctual::Directional { irradiance, .. } => {
                    add(PI * scene_radius * scene_radius * luminance(*irradiance));
                    infinite.push(i);
                }
            }
        }
        Lights {
            tree: LightTree::new(cdf.len(), bounded, infinite),
            by_leaf: HashMap::new(),
            emitters,
            punctual,
            cdf,
            total: total as f32,
            center,
            radius: scene_radius,
        }
    }

    pub fn is_empty(&self) -> bool {
        self.total <= 0.0
    }

    fn pick(&self, u: f32) -> (usize, f32) {
        let x = u * self.total;
        let i = self
            .cdf
            .partition_point(|&c| c <= x)
            .min(self.cdf.len() - 1);
        let lo = if i == 0 { 0.0 } else { self.cdf[i - 1] };
        (i, (self.cdf[i] - lo) / self.total)
    }

    /// The emitter of the lamp triangle in slot `slot` of leaf `leaf` (global node number),
    /// as a hit names it.
    pub fn emitter_at(&self, leaf: u64, slot: u32) -> Option<u32> {
        self.by_leaf.get(&(leaf, slot)).copied()
    }

    /// Solid-angle pdf with which `sample` from `p` (normal `n`) picks the point a BSDF
    /// sample hit on `emitter` (None: a triangle no light sample picks), `dist2` away, seen
    /// at |cos| `cos_l` on a triangle of `area`: MIS weighs the hit's emission with it.
    pub fn pdf_li(
        &self,
        (p, n): (V, V),
        emitter: Option<u32>,
        dist2: f32,
        cos_l: f32,
        area: f32,
    ) -> f32 {
        emitter.map_or(0.0, |i| self.tree.pmf(p, n, i as usize)) * dist2 / (cos_l * area)
    }

    /// Samples a light for shading point `p` on a surface with normal `n` (zero: a point
    /// of any orientation).
    pub fn sample(&self, p: V, n: V, u_pick: f32, u: [f32; 2]) -> Option<LightSample> {
        let (i, p_pick) = self.tree.sample(p, n, u_pick)?;
        if p_pick <= 0.0 {
            return None;
        }
        if let Some(e) = self.emitters.get(i) {
            // Uniform point on the triangle.
            let (q, err, texel) = e.point([u[0], u[1]]);
            let d = q - p;
            let dist2 = d.length_squared();
            let dist = dist2.sqrt();
            if dist <= 0.0 || !dist.is_finite() {
                return None;
            }
            let wi = d / dist;
            let cos_l = -wi.dot(e.n);
            if cos_l <= 0.0 && !e.two_sided {
                return None;
            }
            let pdf = p_pick / e.area * dist2 / cos_l.abs();
            if !(pdf > 0.0 && pdf.is_finite()) {
                return None;
            }
            return Some(LightSample {
                wi,
                dist,
                point: Some((q, err, e.n)),
                weight: e.le / pdf,
                pdf,
                texel,
            });
        }
        match &self.punctual[i - self.emitters.len()] {
            Punctual::Spot {
                pos,
                dir,
                intensity,
                cos_outer,
                cos_inner,
            } => {
                let d = *pos - p;
                let dist2 = d.length_squared();
                let dist = dist2.sqrt();
                if dist <= 0.0 {
                    return None;
                }
                let wi = d / dist;
                let fall = spot_falloff((-wi).dot(*dir), *cos_outer, *cos_inner);
                if fall <= 0.0 {
                    return None;
                }
                Some(LightSample {
                    wi,
                    dist,
                    point: Some((*pos, V::ZERO, wi)),
                    weight: *intensity * (fall / dist2 / p_pick),
                    pdf: 0.0,
                    texel: None,
                })
            }
            Punctual::Directional { dir, irradiance } => Some(LightSample {
                wi: -*dir,
                dist: f32::INFINITY,
                point: None,
                weight: *irradiance / p_pick,
                pdf: 0.0,
                texel: None,
            }),
        }
    }

    /// Emits a photon (004 §4.7, eq. 4.28): a light chosen by power, a point on it and a
    /// direction (cosine-weighted from a lamp's surface, uniform in a spot's cone, parallel
    /// through the scene's bounding disc for a directional light), with six uniforms.
    pub fn emit(&self, u_pick: f32, u: [f32; 5]) -> Option<Photon> {
        if self.is_empty() {
            return None;
        }
        let (i, p_pick) = self.pick(u_pick);
        if p_pick <= 0.0 {
            return None;
        }
        let mut texel = None;
        let (o, err, n, d, flux) = if let Some(e) = self.emitters.get(i) {
            let (q, err, at) = e.point([u[0], u[1]]);
            texel = at;
            // Two-sided lamps pick a side with u[4]: half the pdf, twice the power.
            let (n, sides) = if e.two_sided && u[4] < 0.5 {
                (-e.n, 2.0)
            } else if e.two_sided {
                (e.n, 2.0)
            } else {
                (e.n, 1.0)
            };
            let d = Frame::new(n).to_world(cosine_hemisphere([u[2], u[3]]));
            // L·cos / (p_pick · 1/A · cos/π · 1/sides).
            (q, err, n, d, e.le * (PI * e.area * sides / p_pick))
        } else {
            match &self.punctual[i - self.emitters.len()] {
                Punctual::Spot {
                    pos,
                    dir,
                    intensity,
                    cos_outer,
                    cos_inner,
                } => {
                    let lo = cos_outer.max(-1.0);
                    let z = 1.0 - u[2] * (1.0 - lo);
                    let s = (1.0 - z * z).max(0.0).sqrt();
                    let phi = 2.0 * PI * u[3];
                    let axis = if *cos_outer <= -1.0 { V::Z } else { *dir };
                    let d = Frame::new(axis).to_world(V::new(s * phi.cos(), s * phi.sin(), z));
                    let fall = spot_falloff(d.dot(*dir), *cos_outer, *cos_inner);
                    let pdf = 1.0 / (2.0 * PI * (1.0 - lo));
                    (*pos, V::ZERO, d, d, *intensity * (fall / (pdf * p_pick)))
                }
                Punctual::Directional { dir, irradiance } => {
                    let r = self.radius * u[0].sqrt();
                    let phi = 2.0 * PI * u[1];
                    let f = Frame::new(*dir);
                    let o = self.center - *dir * (2.0 * self.radius)
                        + f.to_world(V::new(r * phi.cos(), r * phi.sin(), 0.0));
                    let disc = PI * self.radius * self.radius;
                    (o, V::ZERO, *dir, *dir, *irradiance * (disc / p_pick))
                }
            }
        };
        if !(flux.is_finite() && flux.max_element() > 0.0) {
            return None;
        }
        Some(Photon {
            ray: Ray {
                o: offset_origin(o, err, n, d),
                d: d.normalize(),
                t_max: f32::INFINITY,
            },
            flux,
            texel,
        })
    }
}

/// glTF spot falloff for a direction at cosine `c` from the axis (1 for point lights).
fn spot_falloff(c: f32, cos_outer: f32, cos_inner: f32) -> f32 {
    if cos_outer <= -1.0 {
        return 1.0;
    }
    let t = ((c - cos_outer) / (cos_inner - cos_outer).max(1e-6)).clamp(0.0, 1.0);
    t * t
}

fn punctual(l: &LightRecord) -> Option<Punctual> {
    let color = V::from(l.color).max(V::ZERO) * l.intensity.max(0.0);
    if color.max_element() <= 0.0 {
        return None;
    }
    let dir = V::from(l.direction).normalize_or_zero();
    match l.kind {
        0 => Some(Punctual::Spot {
            pos: V::from(l.position),
            dir: V::NEG_Z,
            intensity: color,
            cos_outer: -1.0,
            cos_inner: -1.0,
        }),
        1 => Some(Punctual::Spot {
            pos: V::from(l.position),
            dir,
            intensity: color,
            cos_outer: l.outer_cone.cos(),
            cos_inner: l.inner_cone.cos(),
        }),
        2 if dir != V::ZERO => Some(Punctual::Directional {
            dir,
            irradiance: color,
        }),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::test_rng::TestRng as Rng;

    fn scattered_lights(rng: &mut Rng) -> Lights {
        let emitters = (0..200)
            .filter_map(|k| {
                let c = rng.v(10.0);
                let p = [c + rng.v(0.5), c + rng.v(0.5), c + rng.v(0.5)];
                Emitter::triangle(p, V::new(1.0, 2.0, 0.5) * rng.f32(), k % 5 == 0)
            })
            .collect();
        let punctual = vec![
            Punctual::Spot {
                pos: V::new(0.0, 8.0, 0.0),
                dir: V::NEG_Y,
                intensity: V::splat(40.0),
                cos_outer: 0.7,
                cos_inner: 0.9,
            },
            Punctual::Spot {
                pos: V::new(3.0, -2.0, 1.0),
                dir: V::NEG_Z,
                intensity: V::splat(5.0),
                cos_outer: -1.0,
                cos_inner: -1.0,
            },
            Punctual::Directional {
                dir: V::new(0.3, -1.0, 0.2).normalize(),
                irradiance: V::splat(2.0),
            },
        ];
        Lights::new(emitters, punctual, V::ZERO, 20.0)
    }

    /// MIS weighs a BSDF-sampled hit on a lamp with `pick_pdf` converted to solid angle;
    /// that must be the pdf `sample` returned for the same point, or the two strategies
    /// double-count or lose light.
    #[test]
    fn a_lamp_hit_has_the_pdf_its_light_sample_had() {
        let mut rng = Rng::new(0x51ab_1e5e_ed00_0001);
        let lights = scattered_lights(&mut rng);
        let mut checked = 0;
        for _ in 0..5000 {
            let p = rng.v(15.0);
            let n = rng.v(1.0).normalize();
            let Some(ls) = lights.sample(p, n, rng.f32(), [rng.f32(), rng.f32()]) else {
                continue;
            };
            if ls.pdf == 0.0 {
                continue;
            }
            let (q, _, normal) = ls.point.unwrap();
            // The lamp holding q: its normal, and sub-triangle areas that add up to its own.
            let a = |x: V, y: V, z: V| 0.5 * (y - x).cross(z - x).length();
            let (i, e) = lights
                .emitters
                .iter()
                .enumerate()
                .find(|(_, e)| {
                    let sum = a(q, e.p[1], e.p[2]) + a(e.p[0], q, e.p[2]) + a(e.p[0], e.p[1], q);
                    e.n == normal && (sum / e.area - 1.0).abs() < 1e-3
                })
                .expect("the sampled point lies on a lamp");
            let d2 = (q - p).length_squared();
            let cos_l = ls.wi.dot(e.n).abs();
            let hit_pdf = lights.pdf_li((p, n), Some(i as u32), d2, cos_l, e.area);
            assert!(
                (hit_pdf / ls.pdf - 1.0).abs() < 1e-3,
                "light sample pdf {} against the hit's {hit_pdf}",
                ls.pdf
            );
            checked += 1;
        }
        assert!(checked > 1000, "{checked} lamp samples");
    }

    #[test]
    fn tree_probabilities_sum_to_at_most_one_and_are_what_sampling_returns() {
        let mut rng = Rng::new(0x9e37_79b9_7f4a_7c15);
        let lights = scattered_lights(&mut rng);
        let count = lights.emitters.len() + lights.punctual.len();
        for _ in 0..50 {
            let p = rng.v(15.0);
            let n = rng.v(1.0).normalize();
            let pmf: Vec<f32> = (0..count).map(|i| lights.tree.pmf(p, n, i)).collect();
            // Below 1 by what descends into subtrees whose bound is loose: there sampling
            // finds no light, which is no bias, as only lights that cannot reach p are left.
            let total: f32 = pmf.iter().sum();
            assert!(
                total <= 1.0 + 1e-5 && total > 0.5,
                "probabilities at {p} sum to {total}"
            );
            let draws = 4000;
            let mut hits = vec![0u32; count];
            for k in 0..draws {
                let u = (k as f32 + rng.f32()) / draws as f32;
                let Some((i, q)) = lights.tree.sample(p, n, u) else {
                    continue;
                };
                let rel = (q - pmf[i]).abs() / pmf[i];
                assert!(
                    rel < 1e-5,
                    "sampled light {i}: pmf {q} but {} by walking",
                    pmf[i]
                );
                hits[i] += 1;
            }
            for (i, &h) in hits.iter().enumerate() {
                let expect = pmf[i] * draws as f32;
                // Stratified u: each light's count is within one stratum per tree level of
                // its expectation; 4σ of an unstratified count bounds that loosely.
                let slack = 4.0 * expect.sqrt() + 12.0;
                assert!(
                    (h as f32 - expect).abs() <= slack,
                    "light {i}: {h} draws, {expect} expected"
                );
            }
        }
    }

    #[test]
    fn a_one_sided_lamp_facing_away_is_never_chosen() {
        let tri = |z: f32, flip: bool, two_sided: bool| {
            let (a, b) = (V::new(1.0, 0.0, z), V::new(0.0, 1.0, z));
            let p = if flip {
                [V::new(0.0, 0.0, z), b, a]
            } else {
                [V::new(0.0, 0.0, z), a, b]
            };
            Emitter::triangle(p, V::ONE, two_sided).unwrap()
        };
        // Normals +z: the lamp at z = 1 faces away from the origin, the one at z = −1 faces it.
        let lights = Lights::new(
            vec![
                tri(1.0, false, false),
                tri(-1.0, false, false),
                tri(2.0, false, true),
            ],
            Vec::new(),
            V::ZERO,
            5.0,
        );
        let (p, n) = (V::new(0.2, 0.2, 0.0), V::ZERO);
        assert_eq!(lights.tree.pmf(p, n, 0), 0.0);
        assert!(lights.tree.pmf(p, n, 1) > 0.0);
        assert!(
            lights.tree.pmf(p, n, 2) > 0.0,
            "a two-sided lamp lights both sides"
        );
        for k in 0..1000 {
            let (i, _) = lights.tree.sample(p, n, k as f32 / 1000.0).unwrap();
            assert_ne!(i, 0);
        }
        assert!(lights.sample(p, n, 0.5, [0.5, 0.5]).is_some());
    }

    /// Two spheres of one-sided lamps, outward normals.
    fn lamp_spheres() -> Vec<Emitter> {
        let mut out = Vec::new();
        for (c, r, le) in [
            (V::new(0.0, 3.0, 0.0), 0.5, 20.0),
            (V::new(6.0, 4.0, 1.0), 0.8, 8.0),
        ] {
            let (nlat, nlon) = (12, 24);
            let at = |i: usize, j: usize| {
                let th = PI * i as f32 / nlat as f32;
                let ph = 2.0 * PI * j as f32 / nlon as f32;
                c + r * V::new(th.sin() * ph.cos(), th.cos(), th.sin() * ph.sin())
            };
            for i in 0..nlat {
                for j in 0..nlon {
                    let q = [at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1)];
                    for t in [[q[0], q[1], q[2]], [q[0], q[2], q[3]]] {
                        let Some(e) = Emitter::triangle(t, V::splat(le), false) else {
                            continue;
                        };
                        let outward = (t[0] + t[1] + t[2]) / 3.0 - c;
                        let t = if e.n.dot(outward) < 0.0 {
                            [t[0], t[2], t[1]]
                        } else {
                            t
                        };
                        out.extend(Emitter::triangle(t, V::splat(le), false));
                    }
                }
            }
        }
        out
    }

    /// Irradiance at `p` with normal `n` from the lamps by a fine midpoint rule: each
    /// triangle cut into k² pieces.
    fn irradiance(emitters: &[Emitter], p: V, n: V) -> f64 {
        let k = 12;
        let mut e = 0.0f64;
        for l in emitters {
            let (du, dv) = ((l.p[1] - l.p[0]) / k as f32, (l.p[2] - l.p[0]) / k as f32);
            for a in 0..k {
                for b in 0..k - a {
                    let base = l.p[0] + du * a as f32 + dv * b as f32;
                    let mut pieces = vec![base + (du + dv) / 3.0];
                    if a + b + 1 < k {
                        pieces.push(base + (du + dv) * (2.0 / 3.0));
                    }
                    for q in pieces {
                        let d = q - p;
                        let d2 = d.length_squared();
                        let w = d / d2.sqrt();
                        let (cs, cl) = (n.dot(w), -l.n.dot(w));
                        if cs > 0.0 && cl > 0.0 {
                            let da = l.area / (k * k) as f32;
                            e += (l.le.x * cs * cl * da / d2) as f64;
                        }
                    }
                }
            }
        }
        e
    }

    #[test]
    fn light_tree_samples_are_unbiased_and_beat_sampling_by_power() {
        let mut rng = Rng::new(7);
        let emitters = lamp_spheres();
        let area: f32 = emitters.iter().map(|e| e.area).sum();
        let le_area: Vec<f32> = emitters.iter().map(|e| e.le.x * e.area).collect();
        let total: f32 = le_area.iter().sum();
        let reference = Lights::new(lamp_spheres(), Vec::new(), V::ZERO, 10.0);
        assert!(area > 0.0);
        for (p, n) in [
            (V::new(0.0, 0.0, 0.0), V::Y),
            (V::new(2.0, 1.0, -1.0), V::new(0.2, 1.0, 0.1).normalize()),
            (V::new(4.0, 4.0, 3.0), V::new(0.0, 0.0, -1.0)),
        ] {
            let exact = irradiance(&emitters, p, n);
            let draws = 40_000;
            let (mut s1, mut s2, mut q1, mut q2) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
            for _ in 0..draws {
                let v = reference
                    .sample(p, n, rng.f32(), [rng.f32(), rng.f32()])
                    .map_or(0.0, |ls| (ls.weight.x * n.dot(ls.wi).max(0.0)) as f64);
                s1 += v;
                s2 += v * v;
                // Sampling by power alone: a triangle in proportion to Le·A, a point on it.
                let x = rng.f32() * total;
                let i = le_area
                    .iter()
                    .scan(0.0, |acc, w| {
                        *acc += w;
                        Some(*acc)
                    })
                    .position(|c| c > x)
                    .unwrap_or(emitters.len() - 1);
                let e = &emitters[i];
                let (q, _, _) = e.point([rng.f32(), rng.f32()]);
                let d = q - p;
                let w = d.normalize();
                let (cs, cl) = (n.dot(w).max(0.0), (-e.n.dot(w)).max(0.0));
                let v = (e.le.x * cs * cl / d.length_squared() * total / e.le.x) as f64;
                q1 += v;
                q2 += v * v;
            }
            let nd = draws as f64;
            let (mean, var) = (s1 / nd, s2 / nd - (s1 / nd).powi(2));
            let var_power = q2 / nd - (q1 / nd).powi(2);
            let sigma = (var / nd).sqrt();
            assert!(
                (mean - exact).abs() < 4.0 * sigma + 2e-3 * exact,
                "at {p}: tree estimate {mean} ± {sigma}, midpoint rule {exact}"
            );
            assert!(
                var < 0.5 * var_power,
                "at {p}: variance {var} with the tree, {var_power} by power"
            );
        }
    }
}
