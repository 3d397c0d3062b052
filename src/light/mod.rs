//! Light sources: emissive triangles (front side only unless the material is
//! double-sided), glTF punctual lights and the environment (`env`). A shading point
//! chooses one through the light tree (`tree`) by a bound on what each can send it (the
//! environment and directional lights, which have no position, as pbrt-v4's infinite
//! lights); photons leave them in proportion to power.
//!
//! Emitters are gathered once by walking only the subtrees whose nodes carry the EMISSIVE
//! flag, so a huge scene with a few lamps loads a few pages.

use crate::material::{cosine_hemisphere, luminance, Frame, Material};
use crate::paging::{Corners, NodeRef, Page};
use crate::trace::{offset_origin, Ray};
use anyhow::Result;
use canopy_format::{Archive, LightRecord, NodeFlags};
use glam::Vec3A as V;
use std::collections::HashMap;
use std::f32::consts::PI;
use tree::{LightBounds, LightTree};

mod distribution;
pub mod env;
mod env_build;
pub mod env_tiles;
mod hdr;
mod set;
pub mod sky;
mod sun_data;
mod sun_position;
pub mod tree;

pub use env::Environment;
pub use set::LightSet;

pub struct Emitter {
    pub p: [V; 3],
    /// The material whose emission it is (0 for a lamp made without one).
    pub material: u32,
    pub area: f32,
    /// Unit geometric normal (front side).
    pub n: V,
    /// Radiance; a textured lamp's mean over its texture.
    pub le: V,
    pub two_sided: bool,
    /// A textured lamp's vertex texture coordinates (its texture is its material's).
    pub texel: Option<[[f32; 2]; 3]>,
}

impl Emitter {
    /// A lamp triangle; None if it is degenerate.
    pub fn triangle(p: [V; 3], le: V, two_sided: bool) -> Option<Emitter> {
        let c = (p[1] - p[0]).cross(p[2] - p[0]);
        let area = 0.5 * c.length();
        (area > 0.0 && area.is_finite()).then(|| Emitter {
            p,
            material: 0,
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
        let texel = self.texel.map(|uv| {
            (
                self.material,
                std::array::from_fn(|k| b[0] * uv[0][k] + b[1] * uv[1][k] + b[2] * uv[2][k]),
            )
        });
        (q, err, texel)
    }
}

#[derive(Clone, Copy, Debug)]
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
    /// Light from infinitely far away, numbered after the punctual lights.
    pub env: Option<Environment>,
    /// Cumulative power, emitters first, then punctual lights, then the environment
    /// (photon emission).
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
    /// emission is textured: `emission_corners` gives where a lamp's emission texture reads
    /// at its corners).
    pub fn gather(
        archive: &Archive,
        materials: &[Material],
        emission_corners: impl Fn(u32, &Corners) -> Option<[[f32; 2]; 3]>,
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
                            e.material = tri.material;
                            e.texel = emission_corners(tri.material, &page.corners(first + slot));
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
            ..Lights::new(emitters, punctual, None, center, scene_radius)
        })
    }

    /// The lamps split by material, each set with its own lamps' hit table (what a BSDF
    /// sample that meets a lamp is weighed by) in the same scene sphere; punctual lights
    /// and the environment are left out.
    pub fn by_material(self) -> HashMap<u32, Lights> {
        // Per emitter, its material's set and its place there.
        let mut place = Vec::with_capacity(self.emitters.len());
        let mut groups: HashMap<u32, Vec<Emitter>> = HashMap::new();
        for e in self.emitters {
            let g = groups.entry(e.material).or_default();
            place.push((e.material, g.len() as u32));
            g.push(e);
        }
        let mut tables: HashMap<u32, HashMap<(u64, u32), u32>> = HashMap::new();
        for (at, i) in self.by_leaf {
            let (m, j) = place[i as usize];
            tables.entry(m).or_default().insert(at, j);
        }
        let (center, radius) = (self.center, self.radius);
        groups
            .into_iter()
            .map(|(m, es)| {
                let lights = Lights {
                    by_leaf: tables.remove(&m).unwrap_or_default(),
                    ..Lights::new(es, Vec::new(), None, center, radius)
                };
                (m, lights)
            })
            .collect()
    }

    /// The same lights with `env` as the environment.
    pub fn with_environment(self, env: Environment) -> Lights {
        Lights {
            by_leaf: self.by_leaf,
            ..Lights::new(
                self.emitters,
                self.punctual,
                Some(env),
                self.center,
                self.radius,
            )
        }
    }

    /// Lights of a scene whose bounding sphere has this center and radius.
    pub fn new(
        emitters: Vec<Emitter>,
        punctual: Vec<Punctual>,
        env: Option<Environment>,
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
        if let Some(env) = &env {
            // What crosses the scene's bounding disc: π R² ∫ Le dω (pbrt-v4's
            // `ImageInfiniteLight::Phi`).
            let disc = PI * scene_radius * scene_radius;
            add(disc * 4.0 * PI * luminance(env.mean()));
            infinite.push((emitters.len() + punctual.len()) as u32);
        }
        Lights {
            tree: LightTree::new(cdf.len(), bounded, infinite),
            by_leaf: HashMap::new(),
            emitters,
            punctual,
            env,
            cdf,
            total: total as f32,
            center,
            radius: scene_radius,
        }
    }

    /// The scene's bounding sphere the lights were made for: centre and radius.
    pub fn sphere(&self) -> (V, f32) {
        (self.center, self.radius)
    }

    pub fn is_empty(&self) -> bool {
        self.total <= 0.0
    }

    /// Whether a ray may meet any of the lights: a lamp or the environment (punctual lights
    /// have no area).
    pub fn has_area(&self) -> bool {
        !self.emitters.is_empty() || self.env.is_some()
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

    /// The first failure to read the environment's paged tiles, if any.
    pub fn error(&self) -> Option<String> {
        self.env.as_ref().and_then(Environment::error)
    }

    /// The environment's light number (after the emitters and punctual lights).
    fn env_index(&self) -> usize {
        self.emitters.len() + self.punctual.len()
    }

    /// Radiance from the environment along direction `d` (unit), which a ray that left
    /// the scene meets.
    pub fn escaped(&self, d: V) -> V {
        self.env.as_ref().map_or(V::ZERO, |e| e.le(d))
    }

    /// Solid-angle pdf with which `sample` from `p` (normal `n`) picks the environment's
    /// direction `d`: MIS weighs an escaping ray's light with it.
    pub fn pdf_env(&self, (p, n): (V, V), d: V) -> f32 {
        self.env
            .as_ref()
            .map_or(0.0, |e| self.tree.pmf(p, n, self.env_index()) * e.pdf(d))
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
        let Some(light) = self.punctual.get(i - self.emitters.len()) else {
            let (wi, le, pdf) = self.env.as_ref()?.sample(u)?;
            let pdf = pdf * p_pick;
            return (pdf > 0.0 && pdf.is_finite()).then(|| LightSample {
                wi,
                dist: f32::INFINITY,
                point: None,
                weight: le / pdf,
                pdf,
                texel: None,
            });
        };
        match light {
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
        } else if let Some(light) = self.punctual.get(i - self.emitters.len()) {
            match light {
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
                    let o = self.disc_origin(*dir, [u[0], u[1]]);
                    let disc = PI * self.radius * self.radius;
                    (o, V::ZERO, *dir, *dir, *irradiance * (disc / p_pick))
                }
            }
        } else {
            // From the environment: a direction by its density, then parallel through the
            // disc (pbrt-v4's `ImageInfiniteLight::SampleLe`).
            let (wi, le, pdf) = self.env.as_ref()?.sample([u[2], u[3]])?;
            let o = self.disc_origin(-wi, [u[0], u[1]]);
            let disc = PI * self.radius * self.radius;
            (o, V::ZERO, -wi, -wi, le * (disc / (pdf * p_pick)))
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

impl Default for Lights {
    /// No light.
    fn default() -> Lights {
        Lights::new(Vec::new(), Vec::new(), None, V::ZERO, 0.0)
    }
}

impl Lights {
    /// A uniform point of the scene's bounding disc facing `dir`, moved back out of the
    /// scene against `dir` (where light from infinitely far away enters).
    fn disc_origin(&self, dir: V, u: [f32; 2]) -> V {
        let r = self.radius * u[0].sqrt();
        let phi = 2.0 * PI * u[1];
        self.center - dir * (2.0 * self.radius)
            + Frame::new(dir).to_world(V::new(r * phi.cos(), r * phi.sin(), 0.0))
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

/// A light record as the renderer lights with it (None: it sends no light).
pub fn punctual(l: &LightRecord) -> Option<Punctual> {
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
mod tests;
