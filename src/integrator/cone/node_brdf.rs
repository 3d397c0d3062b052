//! The cluster BRDF (004 §4.3–4.4): how a node hit as a whole reflects, refracts, scatters
//! diffusely and emits.

use crate::integrator::Scene;
use crate::material::Frame;
use crate::trace::{Cone, ConeHit, Ray};
use canopy_format::codec::{rgbe64_decode, snorm16_decode, unorm8_decode};
use glam::Vec3A as V;

/// ∫ Θ dω / π over the sphere for eq. 4.4's Θ = (1 − |n|)/4 + ⟨n, ω⟩ (clamped at 0) with
/// a normal of length `len`: 1 for a flat cluster and for a closed one (|n| = 0), less
/// between (0.78 at |n| = 0.5). Light samples divide Θ by it so a cluster reflects its
/// albedo under uniform light, as its cosine-sampled bounce does; Θ as printed darkened
/// sponza's clusters (about 15% of the default cones' bias there).
pub fn theta_norm(len: f32) -> f32 {
    let len = len.clamp(0.0, 1.0);
    let a = (1.0 - len) / 4.0;
    // Θ > 0 for cos > c0.
    let c0 = if len > 0.0 {
        (-a / len).max(-1.0)
    } else {
        -1.0
    };
    2.0 * (a * (1.0 - c0) + len * (1.0 - c0 * c0) / 2.0)
}

/// p_reflect at cos θ from the node's five-sample table (004 §4.3.1), linearly
/// interpolated.
pub fn reflect_lut(lut: [u8; 5], c: f32) -> f32 {
    let x = c.clamp(0.0, 1.0) * 4.0;
    let i = (x as usize).min(3);
    let f = x - i as f32;
    unorm8_decode(lut[i]) * (1.0 - f) + unorm8_decode(lut[i + 1]) * f
}

/// Samples the cluster's Phong lobe (004 eq. 4.7–4.11): shininess s' = s|n| + (1 − |n|)
/// about r' = r|n| + ω(1 − |n|), with s from the GGX roughness (s = 2/α² − 2); a sample
/// below the cluster's plane is mirrored back above it rather than rejected, keeping the
/// lobe's energy. `n`: unit normal on the side of `wo`, `len`: the cluster normal's length.
/// Returns the direction and s'.
pub fn phong_lobe(n: V, len: f32, wo: V, roughness: u8, u: [f32; 2]) -> (V, f32) {
    let r = 2.0 * n.dot(wo) * n - wo;
    let axis = (r * len + wo * (1.0 - len)).normalize_or(n);
    let a = unorm8_decode(roughness).powi(2).max(1e-3);
    let s = (2.0 / (a * a) - 2.0).clamp(1.0, 1e4) * len + (1.0 - len);
    let cos_t = u[0].powf(1.0 / (s + 1.0));
    let sin_t = (1.0 - cos_t * cos_t).max(0.0).sqrt();
    let phi = 2.0 * std::f32::consts::PI * u[1];
    let mut wi = Frame::new(axis)
        .to_world(V::new(sin_t * phi.cos(), sin_t * phi.sin(), cos_t))
        .normalize();
    if wi.dot(n) < 0.0 {
        wi -= 2.0 * wi.dot(n) * n;
    }
    (wi, s)
}

/// Emission a cone (`ray`, `cone`) hit sends back along it: a lamp triangle's from its
/// emitting side(s) (its texel over the cone's footprint), a cluster's when its normal
/// faces the cone (or it has none).
pub fn hit_emission(scene: &Scene, hit: &ConeHit, ray: &Ray, cone: &Cone) -> V {
    let wo = -ray.d;
    match hit {
        // Most triangles emit nothing: look no texel up for them.
        ConeHit::Tri(h) if !scene.materials[h.tri.material as usize].is_emissive() => V::ZERO,
        ConeHit::Tri(h) => scene
            .material_at_cone(h, ray, cone)
            .m
            .emitted(h.ng().dot(wo) > 0.0),
        ConeHit::Node { record, .. } => {
            let nn = V::from(record.normal.map(snorm16_decode));
            if nn.dot(wo) > 0.0 || nn.length() <= 1e-6 {
                V::from(rgbe64_decode(record.emission))
            } else {
                V::ZERO
            }
        }
    }
}
