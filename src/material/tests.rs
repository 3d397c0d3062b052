use super::*;
use bytemuck::Zeroable;

use crate::test_rng::TestRng as Rng;

/// The sheen table's albedo agrees with a Monte Carlo estimate of the same integral drawn
/// another way: uniform directions over the hemisphere, the lobe evaluated directly
/// (not through half vectors as the table's quadrature is).
#[test]
fn sheen_albedo_matches_monte_carlo() {
    let mut rng = Rng::new(11);
    for r in [0.1f32, 0.3, 0.6, 1.0] {
        for mu in [0.1f32, 0.4, 0.8, 1.0] {
            let wo = dir(mu, 0.0);
            let n = 400_000;
            let (mut sum, mut sq) = (0f64, 0f64);
            for _ in 0..n {
                let z = rng.f32();
                let wi = dir(z, 2.0 * PI * rng.f32());
                // pdf of uniform hemisphere directions: 1/2π.
                let v = (sheen::brdf(wo, wi, sheen::alpha(r)) * wi.z * 2.0 * PI) as f64;
                sum += v;
                sq += v * v;
            }
            let mean = sum / n as f64;
            let sigma = ((sq / n as f64 - mean * mean).max(0.0) / n as f64).sqrt();
            let table = sheen::albedo(mu, r) as f64;
            // Bilinear interpolation between the table's nodes errs by up to 1e-3 where E
            // is small and steep in the roughness (r = 0.1: 0.0065 against 0.0058).
            assert!(
                (table - mean).abs() < 4.0 * sigma + 0.01 * mean + 1e-3,
                "roughness {r}, cos θo {mu}: table {table}, Monte Carlo {mean} ± {sigma}"
            );
            assert!(
                table <= 1.0 + 1e-3,
                "roughness {r}, cos θo {mu}: albedo {table}"
            );
        }
    }
}

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

/// `m` under a clearcoat (weight, roughness) and a sheen (grey level, roughness).
fn layered(m: Material, coat: f32, coat_r: f32, sheen: f32, sheen_r: f32) -> Material {
    Material {
        clearcoat: coat,
        coat_alpha: coat_r * coat_r,
        sheen: V::new(sheen, sheen * 0.8, sheen * 0.6),
        sheen_roughness: sheen_r,
        ..m
    }
}

/// The BSDFs the sampling tests check: `materials`' front sides, and coats whose own
/// normal (a clearcoat normal texture's) leans away from the base's.
fn bsdfs() -> Vec<(&'static str, Bsdf)> {
    let mut out: Vec<_> = materials()
        .into_iter()
        .map(|(name, m)| (name, m.bsdf(true)))
        .collect();
    let lambert = mat(0.8, 0.0, 1.0, 0.0, 0.0);
    let tilt = V::new(0.35, -0.2, 0.9).normalize();
    for (name, coat_r) in [("tilted rough coat", 0.3), ("tilted smooth coat", 0.0)] {
        let mut b = layered(lambert, 1.0, coat_r, 0.0, 0.0).bsdf(true);
        b.coat_n = tilt;
        out.push((name, b));
    }
    out
}

fn materials() -> Vec<(&'static str, Material)> {
    let lambert = mat(0.8, 0.0, 1.0, 0.0, 0.0);
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
        ("rough clearcoat", layered(lambert, 1.0, 0.3, 0.0, 0.0)),
        (
            "smooth clearcoat",
            layered(mat(0.5, 0.0, 0.5, 1.0, 0.0), 0.8, 0.0, 0.0, 0.0),
        ),
        (
            "coated metal",
            layered(mat(1.0, 1.0, 0.4, 1.0, 0.0), 1.0, 0.3, 0.0, 0.0),
        ),
        ("velvet", layered(lambert, 0.0, 0.0, 1.0, 0.3)),
        (
            "satin",
            layered(mat(0.9, 0.0, 0.5, 1.0, 0.0), 0.0, 0.0, 0.9, 0.8),
        ),
        ("coated velvet", layered(lambert, 0.7, 0.0, 0.9, 0.5)),
        (
            "coated glass",
            layered(mat(1.0, 0.0, 0.3, 1.0, 1.0), 1.0, 0.2, 0.0, 0.0),
        ),
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
    for (name, b) in bsdfs() {
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
    for (name, b) in bsdfs() {
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
    for (name, b) in bsdfs() {
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
