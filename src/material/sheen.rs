//! The glTF sheen lobe (KHR_materials_sheen): the "Charlie" microfibre distribution and
//! visibility of Conty Estevez & Kulla 2017, as the extension's implementation notes write
//! them, and the lobe's directional albedo E(μ), by which the layer below is scaled.

use glam::Vec3A as V;
use rayon::prelude::*;
use std::f32::consts::PI;
use std::sync::OnceLock;

/// Smallest Charlie α: below it the fibres' lobe is narrower than the albedo table resolves.
pub const MIN_ALPHA: f32 = 5e-3;

/// The Charlie α of a sheenRoughness, squared as the core material's roughness is (the
/// Khronos sample viewer, Filament and the Enterprise PBR model square it too).
pub fn alpha(roughness: f32) -> f32 {
    (roughness * roughness).max(MIN_ALPHA)
}

/// Charlie distribution D(h) = (2 + 1/α)·sin(θh)^(1/α) / 2π (h in the local frame).
pub fn distribution(h: V, a: f32) -> f32 {
    let sin2 = (1.0 - h.z * h.z).max(0.0);
    (2.0 + 1.0 / a) * sin2.powf(0.5 / a) / (2.0 * PI)
}

/// The fitted l(x) of the Charlie Λ (Conty Estevez & Kulla 2017, Table 1).
fn l(x: f32, a: f32) -> f32 {
    let t = (1.0 - a) * (1.0 - a);
    let mix = |p: f32, q: f32| p + (q - p) * t;
    let (ca, cb, cc) = (
        mix(21.5473, 25.3245),
        mix(3.82987, 3.32435),
        mix(0.19823, 0.16801),
    );
    let (cd, ce) = (mix(-1.97760, -1.27393), mix(-4.32054, -4.85967));
    ca / (1.0 + cb * x.powf(cc)) + cd * x + ce
}

/// Λ(cos θ) of the Charlie visibility, mirrored above cos θ = 0.5 as the paper does.
fn lambda(cos: f32, a: f32) -> f32 {
    let c = cos.abs().min(1.0);
    match c < 0.5 {
        true => l(c, a).exp(),
        false => (2.0 * l(0.5, a) - l(1.0 - c, a)).exp(),
    }
}

/// The white sheen lobe f(wo, wi) = D·G/(4·cos θo·cos θi), G = 1/(1 + Λ(wo) + Λ(wi)); both
/// directions above the surface.
pub fn brdf(wo: V, wi: V, a: f32) -> f32 {
    if wo.z <= 0.0 || wi.z <= 0.0 {
        return 0.0;
    }
    let h = (wo + wi).normalize();
    let g = 1.0 / (1.0 + lambda(wo.z, a) + lambda(wi.z, a));
    distribution(h, a) * g / (4.0 * wo.z * wi.z)
}

/// Table resolution: cos θo and roughness.
const NM: usize = 32;
const NR: usize = 32;

/// The white lobe's directional albedo E(μ) = ∫ f(wo, wi)·cos θi dωi at cos θo = μ and
/// sheenRoughness r, bilinear in a table integrated on first use.
pub fn albedo(mu: f32, roughness: f32) -> f32 {
    static TABLE: OnceLock<Vec<f32>> = OnceLock::new();
    let t = TABLE.get_or_init(|| {
        (0..NR * NM)
            .into_par_iter()
            .map(|k| integrate_albedo(node(k % NM, NM), alpha(node(k / NM, NR))))
            .collect()
    });
    let (m, fm) = cell(mu, NM);
    let (r, fr) = cell(roughness, NR);
    let at = |i: usize, j: usize| t[i * NM + j];
    let row = |i: usize| at(i, m) * (1.0 - fm) + at(i, m + 1) * fm;
    row(r) * (1.0 - fr) + row(r + 1) * fr
}

/// The table's i-th of n nodes over [0, 1] (μ = 0 is approached, not used: a lobe seen
/// edge-on has no albedo defined).
fn node(i: usize, n: usize) -> f32 {
    (i as f32 / (n - 1) as f32).max(1e-3)
}

/// The cell of `x` in [0, 1] on n nodes and the position in it.
fn cell(x: f32, n: usize) -> (usize, f32) {
    let s = x.clamp(0.0, 1.0) * (n - 1) as f32;
    let i = (s as usize).min(n - 2);
    (i, s - i as f32)
}

/// E at cos θo = μ by quadrature over half vectors: wi = reflect(wo, h), dωi = 4(wo·h)dωh,
/// so E = ∫ D(h)·G·(wo·h)/cos θo dωh over the h whose wi is above the surface. cos θh is
/// sampled uniformly (the Charlie lobe lies at the horizon of h, not at its pole).
fn integrate_albedo(mu: f32, a: f32) -> f32 {
    const NT: usize = 128;
    const NP: usize = 64;
    let wo = V::new((1.0 - mu * mu).max(0.0).sqrt(), 0.0, mu);
    let mut sum = 0.0f64;
    for i in 0..NT {
        let ch = (i as f32 + 0.5) / NT as f32;
        let sh = (1.0 - ch * ch).sqrt();
        for j in 0..NP {
            // φ over [0, π], doubled: the integrand is symmetric about the plane of wo.
            let phi = PI * (j as f32 + 0.5) / NP as f32;
            let h = V::new(sh * phi.cos(), sh * phi.sin(), ch);
            let oh = wo.dot(h);
            let wi = 2.0 * oh * h - wo;
            if oh <= 0.0 || wi.z <= 0.0 {
                continue;
            }
            let g = 1.0 / (1.0 + lambda(mu, a) + lambda(wi.z, a));
            sum += (distribution(h, a) * g * oh / mu) as f64;
        }
    }
    // dωh = d(cos θh)·dφ: cells of 1/NT by π/NP, twice.
    (sum * 2.0 * std::f64::consts::PI / (NT * NP) as f64) as f32
}
