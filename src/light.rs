//! Light sources: emissive triangles (front side only unless the material is
//! double-sided) and glTF punctual lights, chosen in proportion to their power.
//!
//! Emitters are gathered once by walking only the subtrees whose nodes carry the EMISSIVE
//! flag, so a huge scene with a few lamps loads a few pages.

use crate::material::{cosine_hemisphere, Frame, Material};
use crate::paging::{Page, CHILD_PAGE, INNER, KIND_MASK, LEAF};
use crate::trace::{offset_origin, Ray};
use anyhow::Result;
use canopy_format::{Archive, LightRecord, NodeFlags};
use glam::Vec3A as V;
use std::f32::consts::PI;

pub struct Emitter {
    pub p: [V; 3],
    pub area: f32,
    /// Unit geometric normal (front side).
    pub n: V,
    pub le: V,
    pub two_sided: bool,
}

impl Emitter {
    /// A uniform point on the triangle and its error bound.
    fn point(&self, u: [f32; 2]) -> (V, V) {
        let su = u[0].sqrt();
        let (b0, b1) = (1.0 - su, u[1] * su);
        let q = self.p[0] * b0 + self.p[1] * b1 + self.p[2] * (1.0 - b0 - b1);
        let err =
            self.p[0].abs().max(self.p[1].abs()).max(self.p[2].abs()) * crate::trace::gamma(7);
        (q, err)
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

pub fn luminance(c: V) -> f32 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
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
    /// Cumulative power, emitters first, then punctual lights.
    cdf: Vec<f32>,
    total: f32,
    /// Bounding sphere of the scene (directional lights emit through its disc).
    center: V,
    radius: f32,
}

/// A photon leaving a light: its ray and its power (divided by the sampling pdfs).
pub struct Photon {
    pub ray: Ray,
    pub flux: V,
}

/// Power of an emitter as the light chooser weighs it.
fn emitter_power(le: V, area: f32, two_sided: bool) -> f32 {
    PI * luminance(le) * area * if two_sided { 2.0 } else { 1.0 }
}

impl Lights {
    pub fn gather(archive: &Archive, materials: &[Material], scene_radius: f32) -> Result<Lights> {
        let mut emitters = Vec::new();
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
            let t = page.bvh[ni as usize];
            let a = t.a & !KIND_MASK;
            match t.a & KIND_MASK {
                LEAF => {
                    for tri in &page.tris[a as usize..(a + t.b) as usize] {
                        let m = &materials[tri.material as usize];
                        if !m.is_emissive() {
                            continue;
                        }
                        let p = tri.p.map(V::from);
                        let c = (p[1] - p[0]).cross(p[2] - p[0]);
                        let area = 0.5 * c.length();
                        if area > 0.0 && area.is_finite() {
                            emitters.push(Emitter {
                                p,
                                area,
                                n: c.normalize(),
                                le: m.emission,
                                two_sided: m.double_sided,
                            });
                        }
                    }
                }
                INNER => stack.extend([(pi, a), (pi, t.b)]),
                CHILD_PAGE => {
                    pages.push(Page::decode(archive, a)?);
                    let at = pages.len() as u32 - 1;
                    stack.extend([(at, 0), (at, 1)]);
                }
                _ => {}
            }
        }
        let punctual = archive
            .lights
            .iter()
            .filter_map(punctual)
            .collect::<Vec<_>>();
        let mut cdf = Vec::with_capacity(emitters.len() + punctual.len());
        let mut total = 0.0f64;
        for e in &emitters {
            total += emitter_power(e.le, e.area, e.two_sided) as f64;
            cdf.push(total as f32);
        }
        for l in &punctual {
            total += match l {
                Punctual::Spot {
                    intensity,
                    cos_outer,
                    ..
                } => 2.0 * PI * (1.0 - cos_outer) * luminance(*intensity),
                Punctual::Directional { irradiance, .. } => {
                    PI * scene_radius * scene_radius * luminance(*irradiance)
                }
            } as f64;
            cdf.push(total as f32);
        }
        let h = &archive.header;
        Ok(Lights {
            emitters,
            punctual,
            cdf,
            total: total as f32,
            center: 0.5 * (V::from(h.bounds_min) + V::from(h.bounds_max)),
            radius: scene_radius,
        })
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

    /// Probability of choosing an emitter triangle with this radiance and area.
    pub fn pick_pdf(&self, le: V, area: f32, two_sided: bool) -> f32 {
        if self.total <= 0.0 {
            return 0.0;
        }
        emitter_power(le, area, two_sided) / self.total
    }

    /// Samples a light for shading point `p`.
    pub fn sample(&self, p: V, u_pick: f32, u: [f32; 2]) -> Option<LightSample> {
        if self.is_empty() {
            return None;
        }
        let (i, p_pick) = self.pick(u_pick);
        if p_pick <= 0.0 {
            return None;
        }
        if let Some(e) = self.emitters.get(i) {
            // Uniform point on the triangle.
            let (q, err) = e.point([u[0], u[1]]);
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
                })
            }
            Punctual::Directional { dir, irradiance } => Some(LightSample {
                wi: -*dir,
                dist: f32::INFINITY,
                point: None,
                weight: *irradiance / p_pick,
                pdf: 0.0,
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
        let (o, err, n, d, flux) = if let Some(e) = self.emitters.get(i) {
            let (q, err) = e.point([u[0], u[1]]);
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
