//! Materials: the glTF 2.0 metallic-roughness model (spec Appendix B) with
//! `KHR_materials_specular`, `_ior`, `_transmission` and `_emissive_strength`.
//!
//! Lobes, in the shading frame (z = normal on the side of the outgoing direction):
//! - Lambert, albedo baseColor·(1−metallic)·(1−transmission), weighted by 1 − F(cos θo) of
//!   the specular layer above it (the layer's reflectance at the viewing angle, so the sum
//!   never exceeds one);
//! - GGX/Smith reflection (height-correlated G2, visible-normal sampling) with Schlick
//!   Fresnel: dielectric F0 = ((η−1)/(η+1))²·specularColor·specular and F90 = specular,
//!   blended with the metal's F0 = baseColor, F90 = 1 by metallic;
//! - transmission·(1−metallic) of a dielectric interface with relative index η (exact
//!   Fresnel), smooth (a delta lobe) when roughness is below `SMOOTH_ALPHA`, otherwise GGX
//!   (Walter et al. 2007), tinted by baseColor. Without `KHR_materials_volume` glTF calls
//!   transmission thin-walled; we refract (as Mitsuba's `dielectric`/`roughdielectric`),
//!   which caustics need.

use canopy_format::MaterialRecord;
use glam::Vec3A as V;
use std::f32::consts::{FRAC_1_PI, PI};

/// GGX α below which a lobe is treated as a perfect mirror / smooth interface.
pub const SMOOTH_ALPHA: f32 = 1e-3;

#[derive(Clone, Copy, Debug)]
pub struct Material {
    pub base: V,
    pub metallic: f32,
    /// GGX α = roughness².
    pub alpha: f32,
    pub ior: f32,
    pub transmission: f32,
    pub specular: f32,
    pub specular_color: V,
    pub emission: V,
    pub double_sided: bool,
    /// baseColorFactor's alpha (textures multiply theirs in).
    pub opacity: f32,
    /// KHR_materials_volume: the attenuation coefficient σ = −ln(colour)/distance per
    /// channel inside the mesh (zero without a volume).
    pub sigma: V,
}

/// σ per channel from a record's attenuation colour and distance (zero for no volume); a
/// colour channel of 0 absorbs all but a trace (σ for 10⁻⁶ at the distance).
fn attenuation(m: &MaterialRecord) -> V {
    let d = m.attenuation_distance;
    if !(d.is_finite() && d > 0.0) {
        return V::ZERO;
    }
    V::from(m.attenuation_color.map(|c| -c.clamp(1e-6, 1.0).ln() / d))
}

impl Material {
    pub fn from_record(m: &MaterialRecord) -> Material {
        let r = m.roughness.clamp(0.0, 1.0);
        Material {
            base: V::new(m.base_color[0], m.base_color[1], m.base_color[2]).clamp(V::ZERO, V::ONE),
            metallic: m.metallic.clamp(0.0, 1.0),
            alpha: r * r,
            ior: if m.ior >= 1.0 { m.ior } else { 1.5 },
            transmission: m.transmission.clamp(0.0, 1.0),
            specular: m.specular.clamp(0.0, 1.0),
            specular_color: V::from(m.specular_color).max(V::ZERO),
            emission: V::from(m.emission).max(V::ZERO),
            double_sided: m.flags & MaterialRecord::DOUBLE_SIDED != 0,
            opacity: m.base_color[3].clamp(0.0, 1.0),
            sigma: attenuation(m),
        }
    }

    /// Beer–Lambert transmittance exp(−σ·length) of a segment `length` long that ended on
    /// the back of this material (`front` false): inside a mesh with a volume (glTF's
    /// KHR_materials_volume, whose meshes are closed). 1 on a front face or without one.
    pub fn transmittance(&self, front: bool, length: f32) -> V {
        match front {
            true => V::ONE,
            false => (-self.sigma * length).exp(),
        }
    }

    /// The base colour multiplied by a vertex colour's RGB (glTF 2.0 §3.9.2, `COLOR_0`).
    pub fn tint(&mut self, rgba: [f32; 4]) {
        self.base = (self.base * V::new(rgba[0], rgba[1], rgba[2])).clamp(V::ZERO, V::ONE);
    }

    pub fn is_emissive(&self) -> bool {
        self.emission.max_element() > 0.0
    }

    /// Radiance emitted toward a viewer on the front side (`front`) or the back: one-sided
    /// emitters are dark from behind.
    pub fn emitted(&self, front: bool) -> V {
        if self.is_emissive() && (front || self.double_sided) {
            self.emission
        } else {
            V::ZERO
        }
    }

    /// A single-sided opaque surface hit from behind absorbs: nothing reflects there.
    pub fn absorbs(&self, front: bool) -> bool {
        !front && !self.double_sided && self.transmission == 0.0
    }

    /// Lambertian only: the cone integrator stores light on these and the light pass
    /// leaves caustics on them.
    pub fn is_pure_diffuse(&self) -> bool {
        self.metallic == 0.0 && self.transmission == 0.0 && self.specular == 0.0
    }

    /// Has a perfectly smooth (delta) mirror or interface lobe: caustics are possible.
    pub fn has_delta_lobe(&self) -> bool {
        !self.is_pure_diffuse() && self.alpha < SMOOTH_ALPHA
    }

    /// The BSDF seen from outside (`front`: the ray arrived on the front face).
    pub fn bsdf(&self, front: bool) -> Bsdf {
        let f0_ior = ((self.ior - 1.0) / (self.ior + 1.0)).powi(2);
        let f0_d = (self.specular_color * f0_ior).min(V::ONE) * self.specular;
        let f90_d = V::splat(self.specular);
        let m = self.metallic;
        Bsdf {
            diffuse: self.base * ((1.0 - m) * (1.0 - self.transmission)),
            f0: f0_d * (1.0 - m) + self.base * m,
            f90: f90_d * (1.0 - m) + V::ONE * m,
            alpha: self.alpha.max(1e-4),
            trans: self.transmission * (1.0 - m),
            tint: self.base,
            eta: if front { self.ior } else { 1.0 / self.ior },
        }
    }
}

/// A BSDF in the local frame (z up = the side the outgoing direction is on).
#[derive(Clone, Copy, Debug)]
pub struct Bsdf {
    pub diffuse: V,
    pub f0: V,
    pub f90: V,
    pub alpha: f32,
    /// Weight of the dielectric interface (transmission·(1−metallic)).
    pub trans: f32,
    pub tint: V,
    /// Relative index of refraction across the surface (inside / outside).
    pub eta: f32,
}

#[derive(Clone, Copy, Debug)]
pub struct BsdfSample {
    pub wi: V,
    /// BSDF value times |cos θi| / pdf.
    pub weight: V,
    pub pdf: f32,
    pub delta: bool,
}

fn schlick(f0: V, f90: V, c: f32) -> V {
    let k = (1.0 - c.clamp(0.0, 1.0)).powi(5);
    f0 + (f90 - f0) * k
}

/// Exact unpolarized Fresnel reflectance of a dielectric interface, `cos_i` on the side
/// whose relative index is `eta` (inside/outside).
pub fn fresnel_dielectric(cos_i: f32, eta: f32) -> f32 {
    let c = cos_i.clamp(0.0, 1.0);
    let s2 = (1.0 - c * c) / (eta * eta);
    if s2 >= 1.0 {
        return 1.0;
    }
    let ct = (1.0 - s2).sqrt();
    let rs = (c - eta * ct) / (c + eta * ct);
    let rp = (eta * c - ct) / (eta * c + ct);
    0.5 * (rs * rs + rp * rp)
}

/// Rec. 709 luminance weights of linear R, G, B.
pub const REC709: [f64; 3] = [0.2126, 0.7152, 0.0722];

/// Rec. 709 luminance of a linear RGB colour (each weight the nearest f32 to the decimal).
pub fn luminance(c: V) -> f32 {
    let [r, g, b] = REC709.map(|w| w as f32);
    r * c.x + g * c.y + b * c.z
}

/// GGX normal distribution D(h), h in the local frame.
pub fn ggx_d(h: V, a: f32) -> f32 {
    let c2 = h.z * h.z;
    if c2 <= 0.0 {
        return 0.0;
    }
    let a2 = a * a;
    let k = c2 * (a2 - 1.0) + 1.0;
    a2 / (PI * k * k)
}

/// Smith Λ for GGX.
fn ggx_lambda(w: V, a: f32) -> f32 {
    let c2 = w.z * w.z;
    if c2 <= 0.0 {
        return f32::INFINITY;
    }
    let t2 = (1.0 - c2).max(0.0) / c2;
    0.5 * ((1.0 + a * a * t2).sqrt() - 1.0)
}

fn ggx_g1(w: V, a: f32) -> f32 {
    1.0 / (1.0 + ggx_lambda(w, a))
}

/// Visible-normal sample (Heitz 2018, spherical-cap form of Dupuy & Benyoub 2023).
pub fn ggx_sample_vn(wo: V, a: f32, u: [f32; 2]) -> V {
    let wh = V::new(a * wo.x, a * wo.y, wo.z).normalize();
    let phi = 2.0 * PI * u[0];
    let z = (1.0 - u[1]) * (1.0 + wh.z) - wh.z;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let c = V::new(r * phi.cos(), r * phi.sin(), z) + wh;
    V::new(a * c.x, a * c.y, c.z.max(1e-7)).normalize()
}

/// pdf of `ggx_sample_vn` over half vectors: G1(wo)·max(0, wo·h)·D(h)/cos θo.
pub fn ggx_pdf_vn(wo: V, h: V, a: f32) -> f32 {
    if wo.z <= 0.0 {
        return 0.0;
    }
    ggx_g1(wo, a) * wo.dot(h).max(0.0) * ggx_d(h, a) / wo.z
}

fn reflect(w: V, n: V) -> V {
    2.0 * w.dot(n) * n - w
}

/// Refraction of `wo` about normal `m` (on wo's side) into the medium of relative index
/// `eta`; None under total internal reflection.
fn refract(wo: V, m: V, eta: f32) -> Option<V> {
    let c = wo.dot(m);
    let s2 = (1.0 - c * c).max(0.0) / (eta * eta);
    if s2 >= 1.0 {
        return None;
    }
    let ct = (1.0 - s2).sqrt();
    Some((-wo / eta + (c / eta - ct) * m).normalize())
}

impl Bsdf {
    fn spec_on(&self) -> bool {
        self.f90.max_element() > 0.0 || self.f0.max_element() > 0.0
    }

    /// Lobe selection probabilities (diffuse, glossy reflection, dielectric interface).
    fn lobe_probs(&self, wo: V) -> [f32; 3] {
        let f = schlick(self.f0, self.f90, wo.z);
        let d = luminance(self.diffuse * (V::ONE - f)).max(0.0);
        let s = if self.spec_on() {
            luminance(f) * (1.0 - self.trans)
        } else {
            0.0
        };
        let t = self.trans * luminance(self.tint).max(0.05);
        let sum = d + s + t;
        if sum <= 0.0 {
            return [0.0; 3];
        }
        [d / sum, s / sum, t / sum]
    }

    /// Value f(wo, wi) (non-delta lobes) and the pdf of sampling wi.
    pub fn eval(&self, wo: V, wi: V) -> (V, f32) {
        if wo.z <= 0.0 {
            return (V::ZERO, 0.0);
        }
        let probs = self.lobe_probs(wo);
        let mut f = V::ZERO;
        let mut pdf = 0.0;
        if wi.z > 0.0 {
            let fr = schlick(self.f0, self.f90, wo.z);
            if probs[0] > 0.0 {
                f += self.diffuse * (V::ONE - fr) * FRAC_1_PI;
                pdf += probs[0] * wi.z * FRAC_1_PI;
            }
            if probs[1] > 0.0 && self.alpha >= SMOOTH_ALPHA {
                let h = (wo + wi).normalize();
                let fh = schlick(self.f0, self.f90, wo.dot(h));
                let d = ggx_d(h, self.alpha);
                let g2 = 1.0 / (1.0 + ggx_lambda(wo, self.alpha) + ggx_lambda(wi, self.alpha));
                f += fh * (d * g2 / (4.0 * wo.z * wi.z)) * (1.0 - self.trans);
                pdf += probs[1] * ggx_pdf_vn(wo, h, self.alpha) / (4.0 * wo.dot(h));
            }
        }
        if probs[2] > 0.0 && self.alpha >= SMOOTH_ALPHA && wi.z != 0.0 {
            let (fi, pi) = self.eval_interface(wo, wi);
            f += fi;
            pdf += probs[2] * pi;
        }
        (f, pdf)
    }

    /// The rough dielectric interface (Walter et al. 2007, as pbrt-v4
    /// `DielectricBxDF::f/PDF` writes it): value and the pdf of sampling wi given this lobe.
    fn eval_interface(&self, wo: V, wi: V) -> (V, f32) {
        let (a, eta) = (self.alpha, self.eta);
        let reflect = wi.z > 0.0;
        let etap = if reflect { 1.0 } else { eta };
        let wm = wi * etap + wo;
        if wm.length_squared() == 0.0 {
            return (V::ZERO, 0.0);
        }
        let mut wm = wm.normalize();
        if wm.z < 0.0 {
            wm = -wm;
        }
        // Microfacets seen from behind by either direction contribute nothing.
        if wm.dot(wi) * wi.z < 0.0 || wm.dot(wo) * wo.z < 0.0 {
            return (V::ZERO, 0.0);
        }
        let fr = fresnel_dielectric(wo.dot(wm), eta);
        let d = ggx_d(wm, a);
        let g = 1.0 / (1.0 + ggx_lambda(wo, a) + ggx_lambda(V::new(wi.x, wi.y, wi.z.abs()), a));
        let pdf_vn = ggx_pdf_vn(wo, wm, a);
        if reflect {
            let f = self.trans * fr * d * g / (4.0 * wo.z * wi.z).abs();
            (V::splat(f), pdf_vn / (4.0 * wo.dot(wm).abs()) * fr)
        } else {
            let denom = (wi.dot(wm) + wo.dot(wm) / etap).powi(2);
            if denom == 0.0 {
                return (V::ZERO, 0.0);
            }
            // Radiance is scaled by 1/η'² across the interface (pbrt-v4 §9.5.2).
            let f = self.trans * (1.0 - fr) * d * g * (wi.dot(wm) * wo.dot(wm)).abs()
                / (wi.z * wo.z * denom).abs()
                / (etap * etap);
            (
                self.tint * f,
                pdf_vn * (1.0 - fr) * wi.dot(wm).abs() / denom,
            )
        }
    }

    /// Samples an incident direction with three uniforms (lobe choice, then two).
    pub fn sample(&self, wo: V, u_lobe: f32, u: [f32; 2]) -> Option<BsdfSample> {
        if wo.z <= 0.0 {
            return None;
        }
        let probs = self.lobe_probs(wo);
        if u_lobe < probs[2] {
            return self.sample_interface(wo, u_lobe / probs[2], u, probs[2]);
        }
        let u_lobe = u_lobe - probs[2];
        let smooth = self.alpha < SMOOTH_ALPHA;
        if u_lobe < probs[1] && smooth {
            let wi = V::new(-wo.x, -wo.y, wo.z);
            let f = schlick(self.f0, self.f90, wo.z) * (1.0 - self.trans);
            return Some(BsdfSample {
                wi,
                weight: f / probs[1],
                pdf: probs[1],
                delta: true,
            });
        }
        let wi = if u_lobe < probs[1] {
            let h = ggx_sample_vn(wo, self.alpha, u);
            reflect(wo, h)
        } else if probs[0] > 0.0 {
            cosine_hemisphere(u)
        } else {
            return None;
        };
        if wi.z <= 0.0 {
            return None;
        }
        let (f, pdf) = self.eval(wo, wi);
        if pdf <= 0.0 {
            return None;
        }
        Some(BsdfSample {
            wi,
            weight: f * wi.z / pdf,
            pdf,
            delta: false,
        })
    }

    /// The dielectric interface: reflect with the exact Fresnel, else refract; about a GGX
    /// microfacet sampled from the visible normals when rough.
    fn sample_interface(&self, wo: V, u: f32, u2: [f32; 2], p_lobe: f32) -> Option<BsdfSample> {
        if self.alpha >= SMOOTH_ALPHA {
            let wm = ggx_sample_vn(wo, self.alpha, u2);
            let fr = fresnel_dielectric(wo.dot(wm), self.eta);
            let wi = if u < fr {
                Some(reflect(wo, wm)).filter(|w| w.z > 0.0)
            } else {
                refract(wo, wm, self.eta).filter(|w| w.z < 0.0)
            }?;
            let (f, pdf) = self.eval(wo, wi);
            if pdf <= 0.0 {
                return None;
            }
            return Some(BsdfSample {
                wi,
                weight: f * wi.z.abs() / pdf,
                pdf,
                delta: false,
            });
        }
        let fr = fresnel_dielectric(wo.z, self.eta);
        if u < fr {
            return Some(BsdfSample {
                wi: V::new(-wo.x, -wo.y, wo.z),
                weight: V::splat(self.trans / p_lobe),
                pdf: p_lobe * fr,
                delta: true,
            });
        }
        let eta = self.eta;
        let s2 = (1.0 - wo.z * wo.z) / (eta * eta);
        let ct = (1.0 - s2).max(0.0).sqrt();
        let wi = V::new(-wo.x / eta, -wo.y / eta, -ct);
        // Radiance is scaled by 1/η² crossing into the denser medium (pbrt-v4 §9.5.2).
        Some(BsdfSample {
            wi,
            weight: self.tint * (self.trans / p_lobe / (eta * eta)),
            pdf: p_lobe * (1.0 - fr),
            delta: true,
        })
    }

    /// Whether the BSDF has any non-delta lobe (next-event estimation is useful).
    pub fn has_smooth_only(&self) -> bool {
        let p = self.lobe_probs(V::Z);
        p[0] == 0.0 && ((p[1] == 0.0 && p[2] == 0.0) || self.alpha < SMOOTH_ALPHA)
    }
}

/// Cosine-weighted hemisphere direction (concentric disk mapping).
pub fn cosine_hemisphere(u: [f32; 2]) -> V {
    let (a, b) = (2.0 * u[0] - 1.0, 2.0 * u[1] - 1.0);
    let (r, phi) = if a == 0.0 && b == 0.0 {
        (0.0, 0.0)
    } else if a.abs() > b.abs() {
        (a, PI / 4.0 * (b / a))
    } else {
        (b, PI / 2.0 - PI / 4.0 * (a / b))
    };
    let (x, y) = (r * phi.cos(), r * phi.sin());
    V::new(x, y, (1.0 - x * x - y * y).max(0.0).sqrt())
}

/// Orthonormal basis around a unit normal (Duff et al. 2017).
#[derive(Clone, Copy, Debug)]
pub struct Frame {
    pub t: V,
    pub b: V,
    pub n: V,
}

impl Frame {
    pub fn new(n: V) -> Frame {
        let s = 1f32.copysign(n.z);
        let a = -1.0 / (s + n.z);
        let b = n.x * n.y * a;
        Frame {
            t: V::new(1.0 + s * n.x * n.x * a, s * b, -s * n.x),
            b: V::new(b, s + n.y * n.y * a, -n.y),
            n,
        }
    }
    pub fn to_local(&self, v: V) -> V {
        V::new(v.dot(self.t), v.dot(self.b), v.dot(self.n))
    }
    pub fn to_world(&self, v: V) -> V {
        self.t * v.x + self.b * v.y + self.n * v.z
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bytemuck::Zeroable;

    use crate::test_rng::TestRng as Rng;

    fn mat(base: f32, metallic: f32, roughness: f32, specular: f32, transmission: f32) -> Material {
        let mut r = MaterialRecord::zeroed();
        r.base_color = [base, base * 0.9, base * 0.8, 1.0];
        r.metallic = metallic;
        r.roughness = roughness;
        r.specular = specular;
        r.specular_color = [1.0; 3];
        r.ior = 1.5;
        r.transmission = transmission;
        r.flags = MaterialRecord::DOUBLE_SIDED;
        Material::from_record(&r)
    }

    fn materials() -> Vec<(&'static str, Material)> {
        vec![
            ("lambert", mat(0.8, 0.0, 1.0, 0.0, 0.0)),
            ("plastic", mat(0.5, 0.0, 0.5, 1.0, 0.0)),
            ("glossy plastic", mat(0.9, 0.0, 0.15, 1.0, 0.0)),
            ("rough metal", mat(1.0, 1.0, 0.3, 1.0, 0.0)),
            ("very rough metal", mat(1.0, 1.0, 1.0, 1.0, 0.0)),
            ("mirror", mat(1.0, 1.0, 0.0, 1.0, 0.0)),
            ("glass", mat(1.0, 0.0, 0.0, 1.0, 1.0)),
            ("half glass", mat(0.7, 0.0, 0.4, 1.0, 0.5)),
            ("rough glass", mat(1.0, 0.0, 0.3, 1.0, 1.0)),
        ]
    }

    fn dir(cos: f32, phi: f32) -> V {
        let s = (1.0 - cos * cos).max(0.0).sqrt();
        V::new(s * phi.cos(), s * phi.sin(), cos)
    }

    /// A non-delta sample's weight and pdf are what `eval` gives for its direction:
    /// weight = f·|cos θi| / pdf (eval is what MIS and light sampling use, sample what the
    /// paths use; a mismatch biases one against the other).
    #[test]
    fn sample_weights_agree_with_eval() {
        let mut rng = Rng::new(5);
        for (name, m) in materials() {
            let b = m.bsdf(true);
            let mut checked = 0;
            for k in 0..8 {
                let wo = dir(0.05 + 0.95 * k as f32 / 7.0, 1.3);
                for _ in 0..2000 {
                    let Some(s) = b.sample(wo, rng.f32(), [rng.f32(), rng.f32()]) else {
                        continue;
                    };
                    if s.delta || s.pdf < 1e-3 {
                        continue;
                    }
                    let (f, pdf) = b.eval(wo, s.wi);
                    let want = f * s.wi.z.abs() / pdf;
                    let tol = 2e-3 * want.max_element().max(1e-3);
                    assert!(
                        (pdf / s.pdf - 1.0).abs() < 2e-3,
                        "{name}: sampled pdf {} against eval's {pdf} at wo {wo:?}, wi {:?}",
                        s.pdf,
                        s.wi
                    );
                    assert!(
                        (s.weight - want).abs().max_element() < tol,
                        "{name}: weight {:?} against f·cos/pdf {want:?}",
                        s.weight
                    );
                    checked += 1;
                }
            }
            let smooth = name == "mirror" || name == "glass";
            assert!(
                smooth || checked > 1000,
                "{name}: {checked} samples checked"
            );
        }
    }

    #[test]
    fn albedo_never_exceeds_one() {
        let mut rng = Rng::new(1);
        for (name, m) in materials() {
            let b = m.bsdf(true);
            for k in 0..12 {
                let wo = dir(0.02 + 0.98 * k as f32 / 11.0, 0.7);
                let n = 40_000;
                let (mut sum, mut sq) = (0f64, 0f64);
                for _ in 0..n {
                    let s = b.sample(wo, rng.f32(), [rng.f32(), rng.f32()]);
                    if let Some(s) = &s {
                        assert!(
                            s.weight.is_finite() && s.weight.min_element() >= 0.0,
                            "{name}: sample weight {:?}",
                            s.weight
                        );
                    }
                    let w = match s {
                        // Energy, not radiance: undo the 1/η² of refraction.
                        Some(s) if s.wi.z < 0.0 => s.weight.max_element() * b.eta * b.eta,
                        Some(s) => s.weight.max_element(),
                        None => 0.0,
                    } as f64;
                    sum += w;
                    sq += w * w;
                }
                let mean = sum / n as f64;
                let sigma = ((sq / n as f64 - mean * mean).max(0.0) / n as f64).sqrt();
                assert!(
                    mean <= 1.0 + 4.0 * sigma + 1e-4,
                    "{name}: albedo {mean} ± {sigma} at cos θo = {}",
                    wo.z
                );
                // A white mirror and clear smooth glass absorb nothing: all energy returns.
                if name == "mirror" || name == "glass" {
                    assert!(
                        mean >= 1.0 - 4.0 * sigma - 1e-4,
                        "{name}: albedo {mean} ± {sigma} at cos θo = {} loses energy",
                        wo.z
                    );
                }
            }
        }
        // Lambert with cosine sampling: every sample weighs exactly the albedo.
        let b = mat(0.8, 0.0, 1.0, 0.0, 0.0).bsdf(true);
        let s = b.sample(dir(0.5, 0.0), 0.3, [0.2, 0.9]).unwrap();
        assert!((s.weight - V::new(0.8, 0.72, 0.64)).abs().max_element() < 1e-5);
    }

    /// Wilson–Hilferty normal deviate of a chi-square statistic.
    fn chi2_z(chi2: f64, dof: f64) -> f64 {
        let k = 2.0 / (9.0 * dof);
        ((chi2 / dof).powf(1.0 / 3.0) - (1.0 - k)) / k.sqrt()
    }

    #[test]
    fn sampling_matches_pdf_chi_square() {
        const NT: usize = 20;
        const NP: usize = 40;
        // Sub-samples per bin side when integrating the pdf (glossy lobes are narrow).
        const S: usize = 24;
        let mut rng = Rng::new(7);
        for (name, m) in materials() {
            let b = m.bsdf(true);
            for cos_o in [0.15f32, 0.6, 0.95] {
                let wo = dir(cos_o, 1.1);
                let n = 300_000;
                let mut obs = vec![0f64; NT * NP];
                for _ in 0..n {
                    if let Some(s) = b.sample(wo, rng.f32(), [rng.f32(), rng.f32()]) {
                        if s.delta {
                            continue;
                        }
                        let t = (((s.wi.z + 1.0) * 0.5 * NT as f32) as usize).min(NT - 1);
                        let mut phi = s.wi.y.atan2(s.wi.x);
                        if phi < 0.0 {
                            phi += 2.0 * PI;
                        }
                        let p = ((phi / (2.0 * PI) * NP as f32) as usize).min(NP - 1);
                        obs[t * NP + p] += 1.0;
                    }
                }
                // Expected counts: the pdf integrated over each bin (midpoint rule).
                let mut exp = vec![0f64; NT * NP];
                let (dc, dp) = (2.0 / NT as f64, 2.0 * std::f64::consts::PI / NP as f64);
                for t in 0..NT {
                    for p in 0..NP {
                        let mut sum = 0.0;
                        for i in 0..S {
                            for j in 0..S {
                                let c = -1.0 + (t as f64 + (i as f64 + 0.5) / S as f64) * dc;
                                let ph = (p as f64 + (j as f64 + 0.5) / S as f64) * dp;
                                sum += b.eval(wo, dir(c as f32, ph as f32)).1 as f64;
                            }
                        }
                        exp[t * NP + p] = sum / (S * S) as f64 * dc * dp * n as f64;
                    }
                }
                // Pool bins expecting fewer than 5 samples.
                let (mut chi2, mut dof, mut pool_o, mut pool_e) = (0.0, 0.0, 0.0, 0.0);
                for (o, e) in obs.iter().zip(&exp) {
                    if *e < 5.0 {
                        pool_o += o;
                        pool_e += e;
                    } else {
                        chi2 += (o - e) * (o - e) / e;
                        dof += 1.0;
                    }
                }
                if pool_e > 0.0 {
                    chi2 += (pool_o - pool_e) * (pool_o - pool_e) / pool_e.max(1.0);
                    dof += 1.0;
                }
                if obs.iter().sum::<f64>() == 0.0 {
                    // Only delta lobes (mirror, smooth glass): nothing to bin.
                    assert!(exp.iter().sum::<f64>() < 1.0, "{name}: pdf without samples");
                    continue;
                }
                let z = chi2_z(chi2, (dof - 1.0_f64).max(1.0));
                assert!(
                    z < 4.5,
                    "{name}, cos θo {cos_o}: chi² {chi2:.1} with {dof} bins (z = {z:.2})"
                );
            }
        }
    }

    #[test]
    fn smooth_dielectric_splits_by_fresnel() {
        let b = mat(1.0, 0.0, 0.0, 1.0, 1.0).bsdf(true);
        let wo = dir(0.5, 0.0);
        // The Fresnel equations from their s and p amplitudes (Born & Wolf), in f64, not
        // the function the sampler calls.
        let (ci, eta) = (0.5f64, 1.5f64);
        let ct = (1.0 - (1.0 - ci * ci) / (eta * eta)).sqrt();
        let rs = (ci - eta * ct) / (ci + eta * ct);
        let rp = (eta * ci - ct) / (eta * ci + ct);
        let fr = (0.5 * (rs * rs + rp * rp)) as f32;
        let mut rng = Rng::new(3);
        let n = 200_000;
        let mut refl = 0;
        for _ in 0..n {
            let s = b.sample(wo, rng.f32(), [rng.f32(), rng.f32()]).unwrap();
            assert!(s.delta);
            if s.wi.z > 0.0 {
                refl += 1;
            } else {
                // Snell: sin θt = sin θi / η.
                let st = (1.0 - s.wi.z * s.wi.z).sqrt();
                assert!((st - (0.75f32).sqrt() / 1.5).abs() < 1e-5);
            }
        }
        let got = refl as f32 / n as f32;
        let sigma = (fr * (1.0 - fr) / n as f32).sqrt();
        assert!(
            (got - fr).abs() < 4.0 * sigma,
            "reflected share {got}, Fresnel {fr} ± {sigma}"
        );
        // Normal incidence on η = 1.5: F = 0.04.
        assert!((fresnel_dielectric(1.0, 1.5) - 0.04).abs() < 1e-6);
        // Total internal reflection from inside beyond the critical angle.
        assert_eq!(fresnel_dielectric(0.3, 1.0 / 1.5), 1.0);
    }
}
