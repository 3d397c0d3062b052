//! Materials: the glTF 2.0 metallic-roughness model (spec Appendix B) with
//! `KHR_materials_specular`, `_ior`, `_transmission`, `_emissive_strength`, `_volume`,
//! `_sheen` and `_clearcoat`.
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
//!   which caustics need;
//! - KHR_materials_sheen: the Charlie lobe (`sheen`) times sheenColor, above the three
//!   lobes, which are scaled by 1 − max(sheenColor)·E(cos θo), E the white lobe's albedo.
//!   The extension's full form takes the smaller scaling of E(cos θo) and E(cos θi); its
//!   simplified form, used here, keeps the diffuse lobe the same for every incident
//!   direction, which PBGI's irradiance gather relies on;
//! - KHR_materials_clearcoat: a GGX lobe of clearcoatRoughness with Schlick Fresnel at
//!   F0 = 0.04 (ior 1.5), weighted by clearcoatFactor, over everything else, which is
//!   scaled by 1 − clearcoat·F(cos θo) (the Khronos sample viewer's form; the extension's
//!   text takes F at the half vector, the same for a mirror and close for a rough coat).
//!   A white sheen over a white base under a smooth coat thus reflects all light.
//!   The coat has its own normal (`Bsdf::coat_n`, from a clearcoatNormalTexture): its
//!   lobe and its Fresnel are taken about that normal, everything beneath about the
//!   base's shading normal.

mod sheen;

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
    /// KHR_materials_clearcoat: the coat's weight and GGX α (clearcoatRoughness²).
    pub clearcoat: f32,
    pub coat_alpha: f32,
    /// KHR_materials_sheen: the sheen colour (zero without a sheen) and roughness.
    pub sheen: V,
    pub sheen_roughness: f32,
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
            clearcoat: m.clearcoat.clamp(0.0, 1.0),
            coat_alpha: m.clearcoat_roughness.clamp(0.0, 1.0).powi(2),
            sheen: V::from(m.sheen_color).clamp(V::ZERO, V::ONE),
            sheen_roughness: m.sheen_roughness.clamp(0.0, 1.0),
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
        !self.has_base_specular() && self.clearcoat == 0.0 && self.sheen == V::ZERO
    }

    /// The base layer has a specular reflection or interface lobe.
    fn has_base_specular(&self) -> bool {
        self.metallic > 0.0 || self.transmission > 0.0 || self.specular > 0.0
    }

    /// Has a perfectly smooth (delta) mirror, interface or coat lobe: caustics are possible.
    pub fn has_delta_lobe(&self) -> bool {
        self.has_base_specular() && self.alpha < SMOOTH_ALPHA
            || self.clearcoat > 0.0 && self.coat_alpha < SMOOTH_ALPHA
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
            coat: self.clearcoat,
            coat_alpha: self.coat_alpha,
            coat_n: V::Z,
            sheen: self.sheen,
            sheen_roughness: self.sheen_roughness,
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
    /// Clearcoat weight and GGX α.
    pub coat: f32,
    pub coat_alpha: f32,
    /// The coat's normal in this frame (unit; +z unless a clearcoat normal texture tilts it).
    pub coat_n: V,
    /// Sheen colour (zero: none) and roughness.
    pub sheen: V,
    pub sheen_roughness: f32,
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

/// The GGX reflection lobe without Fresnel: D(h)·G2/(4·cos θo·cos θi), G2 the
/// height-correlated Smith masking-shadowing.
fn ggx_reflection(wo: V, wi: V, h: V, a: f32) -> f32 {
    let d = ggx_d(h, a);
    let g2 = 1.0 / (1.0 + ggx_lambda(wo, a) + ggx_lambda(wi, a));
    d * g2 / (4.0 * wo.z * wi.z)
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

/// What the layers leave at one viewing direction θo.
#[derive(Clone, Copy)]
struct Scales {
    /// What the coat leaves of everything below it: 1 − coat·F(cos θo).
    coat: f32,
    /// The white sheen lobe's directional albedo E(cos θo) (0 without a sheen).
    sheen_e: f32,
    /// What reaches the base: coat · (1 − max(sheen)·E).
    base: f32,
}

/// The lobes a BSDF samples from, in the order `Bsdf::lobe_probs` lists them.
const INTERFACE: usize = 0;
const SPECULAR: usize = 1;
const DIFFUSE: usize = 2;
const SHEEN: usize = 3;
const COAT: usize = 4;

/// Schlick Fresnel of the clearcoat layer: F0 = 0.04 (ior 1.5), F90 = 1
/// (KHR_materials_clearcoat).
pub fn coat_fresnel(c: f32) -> f32 {
    0.04 + 0.96 * (1.0 - c.clamp(0.0, 1.0)).powi(5)
}

impl Bsdf {
    /// A Lambertian BSDF of albedo `rho`.
    pub fn lambert(rho: V) -> Bsdf {
        Bsdf {
            diffuse: rho,
            f0: V::ZERO,
            f90: V::ZERO,
            alpha: 1.0,
            trans: 0.0,
            tint: V::ONE,
            eta: 1.0,
            coat: 0.0,
            coat_alpha: 0.0,
            coat_n: V::Z,
            sheen: V::ZERO,
            sheen_roughness: 0.0,
        }
    }

    fn spec_on(&self) -> bool {
        self.f90.max_element() > 0.0 || self.f0.max_element() > 0.0
    }

    /// The coat's frame within this one, None where its normal is this frame's +z.
    fn coat_frame(&self) -> Option<Frame> {
        (self.coat_n != V::Z).then(|| Frame::new(self.coat_n))
    }

    /// The coat's cosine of `wo` (about its own normal).
    fn coat_cos(&self, wo: V) -> f32 {
        wo.dot(self.coat_n)
    }

    /// What the layers leave for a viewer at `wo` (computed once per evaluation).
    fn scales(&self, wo: V) -> Scales {
        let coat = match self.coat > 0.0 {
            true => 1.0 - self.coat * coat_fresnel(self.coat_cos(wo)),
            false => 1.0,
        };
        let sheen_on = self.sheen.max_element() > 0.0;
        let sheen_e = match sheen_on {
            true => sheen::albedo(wo.z, self.sheen_roughness),
            false => 0.0,
        };
        let base = match sheen_on {
            true => coat * (1.0 - self.sheen.max_element() * sheen_e),
            false => coat,
        };
        Scales {
            coat,
            sheen_e,
            base,
        }
    }

    /// Lobe selection probabilities: dielectric interface, glossy reflection, diffuse,
    /// sheen, clearcoat.
    fn lobe_probs(&self, wo: V, sc: &Scales) -> [f32; 5] {
        let f = schlick(self.f0, self.f90, wo.z);
        let base = sc.base;
        let mut p = [0.0; 5];
        p[INTERFACE] = base * self.trans * luminance(self.tint).max(0.05);
        if self.spec_on() {
            p[SPECULAR] = base * luminance(f) * (1.0 - self.trans);
        }
        p[DIFFUSE] = base * luminance(self.diffuse * (V::ONE - f)).max(0.0);
        if self.sheen.max_element() > 0.0 {
            p[SHEEN] = sc.coat * luminance(self.sheen) * sc.sheen_e;
        }
        if self.coat_cos(wo) > 0.0 {
            p[COAT] = self.coat * coat_fresnel(self.coat_cos(wo));
        }
        // Summed in this order, the three base lobes' shares are the same bits as without
        // the layers.
        let sum = p[DIFFUSE] + p[SPECULAR] + p[INTERFACE] + p[SHEEN] + p[COAT];
        match sum > 0.0 {
            true => p.map(|x| x / sum),
            false => [0.0; 5],
        }
    }

    /// Value f(wo, wi) (non-delta lobes) and the pdf of sampling wi.
    pub fn eval(&self, wo: V, wi: V) -> (V, f32) {
        if wo.z <= 0.0 {
            return (V::ZERO, 0.0);
        }
        let sc = self.scales(wo);
        let probs = self.lobe_probs(wo, &sc);
        let base = sc.base;
        let mut f = V::ZERO;
        let mut pdf = 0.0;
        if wi.z > 0.0 {
            let fr = schlick(self.f0, self.f90, wo.z);
            let h = || (wo + wi).normalize();
            if probs[DIFFUSE] > 0.0 {
                f += self.diffuse * (V::ONE - fr) * (base * FRAC_1_PI);
                pdf += probs[DIFFUSE] * wi.z * FRAC_1_PI;
            }
            if probs[SPECULAR] > 0.0 && self.alpha >= SMOOTH_ALPHA {
                let h = h();
                let fh = schlick(self.f0, self.f90, wo.dot(h));
                f += fh * ggx_reflection(wo, wi, h, self.alpha) * (1.0 - self.trans) * base;
                pdf += probs[SPECULAR] * ggx_pdf_vn(wo, h, self.alpha) / (4.0 * wo.dot(h));
            }
            if probs[SHEEN] > 0.0 {
                let a = sheen::alpha(self.sheen_roughness);
                f += self.sheen * (sheen::brdf(wo, wi, a) * sc.coat);
                pdf += probs[SHEEN] * wi.z * FRAC_1_PI;
            }
            if probs[COAT] > 0.0 && self.coat_alpha >= SMOOTH_ALPHA {
                let (fc, pc) = self.eval_coat(wo, wi);
                f += V::splat(fc);
                pdf += probs[COAT] * pc;
            }
        }
        if probs[INTERFACE] > 0.0 && self.alpha >= SMOOTH_ALPHA && wi.z != 0.0 {
            let (fi, pi) = self.eval_interface(wo, wi);
            f += fi * base;
            pdf += probs[INTERFACE] * pi;
        }
        (f, pdf)
    }

    /// The rough coat's value and the pdf of sampling `wi` given its lobe, in the coat's
    /// frame; zero where either direction is below the coat.
    fn eval_coat(&self, wo: V, wi: V) -> (f32, f32) {
        let (wo, wi) = match self.coat_frame() {
            Some(cf) => (cf.to_local(wo), cf.to_local(wi)),
            None => (wo, wi),
        };
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return (0.0, 0.0);
        }
        let (a, h) = (self.coat_alpha, (wo + wi).normalize());
        let fc = self.coat * coat_fresnel(wo.dot(h));
        (
            fc * ggx_reflection(wo, wi, h, a),
            ggx_pdf_vn(wo, h, a) / (4.0 * wo.dot(h)),
        )
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

    /// The lobe `u` picks among `probs` after the interface's share: the glossy
    /// reflection, diffuse, sheen and coat shares in turn (rounding left over goes to the
    /// last lobe that has a share).
    fn pick(probs: &[f32; 5], u: f32) -> Option<usize> {
        let mut u = u;
        for lobe in [SPECULAR, DIFFUSE, SHEEN, COAT] {
            if u < probs[lobe] {
                return Some(lobe);
            }
            u -= probs[lobe];
        }
        [COAT, SHEEN, DIFFUSE].into_iter().find(|&l| probs[l] > 0.0)
    }

    /// A delta sample along the mirror direction `wi` of a smooth lobe whose reflectance
    /// is `f`.
    fn mirror(wi: V, f: V, p_lobe: f32) -> BsdfSample {
        BsdfSample {
            wi,
            weight: f / p_lobe,
            pdf: p_lobe,
            delta: true,
        }
    }

    /// Samples an incident direction with three uniforms (lobe choice, then two).
    pub fn sample(&self, wo: V, u_lobe: f32, u: [f32; 2]) -> Option<BsdfSample> {
        if wo.z <= 0.0 {
            return None;
        }
        let sc = self.scales(wo);
        let probs = self.lobe_probs(wo, &sc);
        if u_lobe < probs[INTERFACE] {
            let p = probs[INTERFACE];
            return self.sample_interface(wo, u_lobe / p, u, p, sc.base);
        }
        let lobe = Bsdf::pick(&probs, u_lobe - probs[INTERFACE])?;
        let wi = match lobe {
            SPECULAR if self.alpha < SMOOTH_ALPHA => {
                let f = schlick(self.f0, self.f90, wo.z) * (1.0 - self.trans) * sc.base;
                let wi = V::new(-wo.x, -wo.y, wo.z);
                return Some(Bsdf::mirror(wi, f, probs[SPECULAR]));
            }
            COAT if self.coat_alpha < SMOOTH_ALPHA => {
                let f = V::splat(self.coat * coat_fresnel(self.coat_cos(wo)));
                let wi = reflect(wo, self.coat_n);
                return (wi.z > 0.0).then(|| Bsdf::mirror(wi, f, probs[COAT]));
            }
            SPECULAR => reflect(wo, ggx_sample_vn(wo, self.alpha, u)),
            COAT => match self.coat_frame() {
                Some(cf) => {
                    let wo = cf.to_local(wo);
                    cf.to_world(reflect(wo, ggx_sample_vn(wo, self.coat_alpha, u)))
                }
                None => reflect(wo, ggx_sample_vn(wo, self.coat_alpha, u)),
            },
            _ => cosine_hemisphere(u),
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
    /// microfacet sampled from the visible normals when rough. `base` is what the layers
    /// above leave of it (`Scales::base`).
    fn sample_interface(
        &self,
        wo: V,
        u: f32,
        u2: [f32; 2],
        p_lobe: f32,
        base: f32,
    ) -> Option<BsdfSample> {
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
        let trans = self.trans * base;
        if u < fr {
            return Some(BsdfSample {
                wi: V::new(-wo.x, -wo.y, wo.z),
                weight: V::splat(trans / p_lobe),
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
            weight: self.tint * (trans / p_lobe / (eta * eta)),
            pdf: p_lobe * (1.0 - fr),
            delta: true,
        })
    }

    /// The share of `sample`'s lobe choices at `wo` that fall on a delta lobe: the smooth
    /// reflection and interface, then the smooth coat, whose choices come first and last.
    /// Returns (the base's share, the coat's).
    fn delta_shares(&self, wo: V) -> (f32, f32) {
        if wo.z <= 0.0 {
            return (0.0, 0.0);
        }
        let p = self.lobe_probs(wo, &self.scales(wo));
        let base = match self.alpha < SMOOTH_ALPHA {
            true => p[INTERFACE] + p[SPECULAR],
            false => 0.0,
        };
        let coat = match self.coat_alpha < SMOOTH_ALPHA {
            true => p[COAT],
            false => 0.0,
        };
        (base, coat)
    }

    /// The probability that `sample` at `wo` takes a delta lobe.
    pub fn delta_share(&self, wo: V) -> f32 {
        let (base, coat) = self.delta_shares(wo);
        base + coat
    }

    /// A sample of the delta lobes alone, `u` choosing among them by their shares: what
    /// `sample` returns when its lobe choice falls on one (weight f/p of that lobe's
    /// choice), for an estimator that takes the delta lobes with probability
    /// `delta_share` and the others apart.
    pub fn sample_delta(&self, wo: V, u: f32, u2: [f32; 2]) -> Option<BsdfSample> {
        let (base, coat) = self.delta_shares(wo);
        let x = u * (base + coat);
        let u_lobe = match x < base {
            true => x,
            // The coat's choices are the last `coat` of [0, 1).
            false => (1.0 - coat + (x - base)).min(1.0 - f32::EPSILON),
        };
        self.sample(wo, u_lobe, u2).filter(|s| s.delta)
    }

    /// The diffuse lobe's value at `wo`, the same for every incident direction.
    pub fn diffuse_lobe(&self, wo: V) -> V {
        self.eval(wo, V::Z).0 - self.glossy().eval(wo, V::Z).0
    }

    /// The same BSDF without its diffuse lobe.
    pub fn glossy(&self) -> Bsdf {
        Bsdf {
            diffuse: V::ZERO,
            ..*self
        }
    }

    /// Whether the BSDF has no non-delta lobe (next-event estimation is useless).
    pub fn has_smooth_only(&self) -> bool {
        let p = self.lobe_probs(V::Z, &self.scales(V::Z));
        let base_smooth = (p[SPECULAR] == 0.0 && p[INTERFACE] == 0.0) || self.alpha < SMOOTH_ALPHA;
        let coat_smooth = p[COAT] == 0.0 || self.coat_alpha < SMOOTH_ALPHA;
        p[DIFFUSE] == 0.0 && p[SHEEN] == 0.0 && base_smooth && coat_smooth
    }

    /// The parameters of the reflection lobes other than the diffuse as bits: equal
    /// keys, equal glossy reflection.
    pub fn glossy_key(&self) -> [u32; 18] {
        let (f0, f90, sh, cn) = (self.f0, self.f90, self.sheen, self.coat_n);
        [
            f0.x,
            f0.y,
            f0.z,
            f90.x,
            f90.y,
            f90.z,
            self.alpha,
            self.trans,
            self.eta,
            self.coat,
            self.coat_alpha,
            cn.x,
            cn.y,
            cn.z,
            sh.x,
            sh.y,
            sh.z,
            self.sheen_roughness,
        ]
        .map(f32::to_bits)
    }
}

/// A white sheen lobe's albedo averaged over the hemisphere of viewing directions,
/// weighted by cos θ: 2∫E(μ)·μ dμ.
pub fn sheen_mean_albedo(roughness: f32) -> f32 {
    const N: usize = 64;
    (0..N)
        .map(|i| {
            let mu = (i as f32 + 0.5) / N as f32;
            2.0 * sheen::albedo(mu, roughness) * mu / N as f32
        })
        .sum()
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
mod tests;
