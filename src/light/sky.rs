//! `--sky`: a clear sky and its sun, as an environment.
//!
//! The sky is Hosek and Wilkie's analytic model (2012), its RGB fit, evaluated by the
//! `hw-skymodel` crate into an equirectangular map of the environment's convention and
//! then stored, paged and sampled as any map. Its unit is Mitsuba 3's `sunsky`: the model's
//! RGB over 106.7502…, Mitsuba's CIE Y normalization (checked against Mitsuba's `eval`
//! direction by direction). Below the horizon it is black, as Mitsuba's is.
//!
//! The sun is a disk of Mitsuba's aperture (0.5358°), uniformly bright, sampled as the
//! cone it subtends. Its radiance is Preetham, Shirley and Smits' (1999, appendix) form:
//! a 5,778 K black body (the sun's effective temperature, so its mean disk radiance)
//! dimmed by Rayleigh scattering (Leckner's optical depth) and aerosols (Ångström's law
//! with Preetham's β from the turbidity), over Kasten and Young's air mass, then taken to
//! linear sRGB through Wyman, Sloan and Shirley's fit of the CIE 1931 observer. Ozone and
//! water vapour are left out. Mitsuba 3's sun is Hosek and Wilkie's solar model instead,
//! whose tables no crate carries; the two are compared in docs/environment.md.

use super::env_build::{paged_capacity, Builder, Built};
use super::sun_position::sun_position;
use anyhow::{bail, Result};
use chrono::{DateTime, FixedOffset};
use glam::Vec3A as V;
use hw_skymodel::rgb::{Channel, SkyParams, SkyState};
use rayon::prelude::*;
use std::f32::consts::PI;
use std::path::Path;

/// Mitsuba 3's CIE Y normalization: the model's RGB over it is Mitsuba's radiance.
const CIE_Y_NORMALIZATION: f32 = 106.750_26;

/// The sun's angular diameter in degrees (Mitsuba 3's `sun_aperture`).
pub const SUN_APERTURE_DEG: f32 = 0.5358;

/// The sky map's size: 0.18° a texel, finer than the circumsolar glow.
const SIZE: [usize; 2] = [2048, 1024];

/// Where the sun stands and what the air holds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SkyOptions {
    /// Degrees above the horizon, 0 to 90.
    pub elevation: f32,
    /// Degrees about +Y from −Z toward +X (the map's longitude).
    pub azimuth: f32,
    /// Hosek–Wilkie turbidity, 1 to 10.
    pub turbidity: f32,
    /// Ground albedo, 0 to 1.
    pub albedo: f32,
    /// Factor on the sun's radiance (0: the sky alone).
    pub sun_strength: f32,
    /// Latitude and longitude (degrees, north and east positive) and a time: where they
    /// put the sun replaces `elevation` and `azimuth`.
    pub place: Option<(f64, f64, DateTime<FixedOffset>)>,
}

impl SkyOptions {
    /// The options with the sun placed by `place`, if given, and checked.
    pub fn resolved(&self) -> Result<SkyOptions> {
        let mut o = *self;
        if let Some((lat, lon, time)) = self.place {
            if !(-90.0..=90.0).contains(&lat) || !(-180.0..=180.0).contains(&lon) {
                bail!("--latitude {lat} --longitude {lon}: a latitude is from −90 to 90 and a longitude from −180 to 180");
            }
            let [elevation, azimuth] = sun_position(lat, lon, time);
            if elevation < 0.0 {
                bail!(
                    "--datetime {}: at latitude {lat}, longitude {lon} the sun is {:.2}° below the horizon; the sky model holds it from 0° to 90°",
                    time.to_rfc3339(),
                    -elevation
                );
            }
            eprintln!(
                "note: at latitude {lat}, longitude {lon} on {} the sun stands {elevation:.2}° up at azimuth {azimuth:.2}° (north 0°, east 90°)",
                time.to_rfc3339()
            );
            o.elevation = elevation as f32;
            o.azimuth = azimuth as f32;
        }
        o.check()?;
        Ok(o)
    }

    /// The options' range, checked before anything is built.
    fn check(&self) -> Result<()> {
        if !(0.0..=90.0).contains(&self.elevation) {
            bail!(
                "--sun-elevation {}: the sky model holds the sun from 0° (the horizon) to 90°",
                self.elevation
            );
        }
        if !(1.0..=10.0).contains(&self.turbidity) {
            bail!(
                "--turbidity {}: the sky model is fitted from 1 to 10",
                self.turbidity
            );
        }
        if !(0.0..=1.0).contains(&self.albedo) {
            bail!("--ground-albedo {}: an albedo is from 0 to 1", self.albedo);
        }
        Ok(())
    }

    /// The direction toward the sun's centre in map coordinates (+Y up).
    pub fn sun_direction(&self) -> V {
        let (sin_e, cos_e) = self.elevation.to_radians().sin_cos();
        let (sin_a, cos_a) = self.azimuth.to_radians().sin_cos();
        V::new(cos_e * sin_a, sin_e, -cos_e * cos_a)
    }
}

/// The sky's map, scaled by `strength`, paged under `share` bytes when it does not fit.
pub fn sky_map(o: &SkyOptions, strength: f32, share: Option<u64>) -> Result<Built> {
    let state = SkyState::new(&SkyParams {
        elevation: o.elevation.to_radians(),
        turbidity: o.turbidity,
        albedo: [o.albedo; 3],
    })?;
    let sun = o.sun_direction();
    let [w, h] = SIZE;
    let mut b = Builder::new(w, h, strength, paged_capacity(w, h, share));
    // A band of 64 rows (one row of tiles) at a time, its rows evaluated in parallel.
    for band in (0..h).step_by(64) {
        let rows: Vec<Vec<[f32; 3]>> = (band..(band + 64).min(h))
            .into_par_iter()
            .map(|j| {
                let v = j as f32 / (h - 1) as f32;
                (0..w)
                    .map(|i| {
                        let d = super::env::direction([(i as f32 + 0.5) / w as f32, v]);
                        radiance(&state, d, sun)
                    })
                    .collect()
            })
            .collect();
        for (k, row) in rows.iter().enumerate() {
            for (i, &rgb) in row.iter().enumerate() {
                b.put(i, band + k, rgb);
            }
        }
    }
    b.finish(Path::new("sky"))
}

/// The sky's radiance toward `d` (unit, +Y up) with the sun toward `sun`.
fn radiance(state: &SkyState, d: V, sun: V) -> [f32; 3] {
    if d.y <= 0.0 {
        return [0.0; 3];
    }
    let theta = d.y.min(1.0).acos();
    let gamma = d.dot(sun).clamp(-1.0, 1.0).acos();
    [Channel::R, Channel::G, Channel::B]
        .map(|c| state.radiance(theta, gamma, c) / CIE_Y_NORMALIZATION)
}

/// The sun: a uniformly bright disk seen from everywhere in the scene.
#[derive(Clone, Copy, Debug)]
pub struct Sun {
    /// Toward its centre, in map coordinates.
    pub dir: V,
    /// 1 − cos of its angular radius, kept apart from the cosine for its digits.
    one_minus_cos: f32,
    /// sin² of its angular radius, a hair wide so that rounding never puts a sample of
    /// the disk outside it (10⁻⁴ of its area).
    sin2_reach: f32,
    /// Its radiance.
    pub le: V,
}

impl Sun {
    pub fn new(o: &SkyOptions, strength: f32) -> Sun {
        let half = (0.5 * SUN_APERTURE_DEG).to_radians();
        Sun {
            dir: o.sun_direction(),
            one_minus_cos: 2.0 * (0.5 * half).sin().powi(2),
            sin2_reach: half.sin().powi(2) * (1.0 + 1e-4),
            le: sun_radiance(o.elevation, o.turbidity) * (strength * o.sun_strength),
        }
    }

    /// The solid angle it subtends.
    pub fn solid_angle(&self) -> f32 {
        2.0 * PI * self.one_minus_cos
    }

    /// Its radiance toward `d` (unit, map coordinates): `le` on the disk, else zero.
    pub fn le(&self, d: V) -> V {
        if self.covers(d) {
            self.le
        } else {
            V::ZERO
        }
    }

    /// Whether `d` meets the disk: from the sine of its angle to the centre, which keeps
    /// its digits at small angles where the cosine loses them.
    fn covers(&self, d: V) -> bool {
        d.dot(self.dir) > 0.0 && d.cross(self.dir).length_squared() <= self.sin2_reach
    }

    /// A direction uniform over the disk's cone, from two uniforms.
    pub fn sample(&self, [u0, u1]: [f32; 2]) -> V {
        let t = u0 * self.one_minus_cos;
        let (cos_t, sin_t) = (1.0 - t, (t * (2.0 - t)).max(0.0).sqrt());
        let (s, c) = (2.0 * PI * u1).sin_cos();
        crate::material::Frame::new(self.dir).to_world(V::new(sin_t * c, sin_t * s, cos_t))
    }

    /// The solid-angle density of `sample` at `d`.
    pub fn pdf(&self, d: V) -> f32 {
        if self.covers(d) {
            1.0 / self.solid_angle()
        } else {
            0.0
        }
    }
}

/// The sun's mean disk radiance in linear sRGB, seen from the ground with the sun
/// `elevation` degrees up through air of `turbidity`.
pub fn sun_radiance(elevation: f32, turbidity: f32) -> V {
    let zenith = 90.0 - elevation as f64;
    // Kasten and Young (1989): the relative optical air mass.
    let air_mass = 1.0 / (zenith.to_radians().cos() + 0.50572 * (96.07995 - zenith).powf(-1.6364));
    // Preetham et al. (1999), appendix: Ångström's β from the turbidity, α = 1.3.
    let beta = (0.04608 * turbidity as f64 - 0.04586).max(0.0);
    let mut xyz = [0f64; 3];
    for nm in 360..=830 {
        let l = nm as f64;
        let um = l * 1e-3;
        let depth = 0.008735 * um.powf(-4.08) + beta * um.powf(-1.3);
        let le = planck(l, 5778.0) * (-air_mass * depth).exp();
        for (x, cmf) in xyz.iter_mut().zip(cie_1931(l)) {
            *x += cmf * le;
        }
    }
    let [x, y, z] = xyz.map(|v| v / CIE_Y_NORMALIZATION as f64);
    V::new(
        (3.240_454_2 * x - 1.537_138_5 * y - 0.498_531_4 * z) as f32,
        (-0.969_266 * x + 1.876_010_8 * y + 0.041_556 * z) as f32,
        (0.055_643_4 * x - 0.204_025_9 * y + 1.057_225_2 * z) as f32,
    )
    .max(V::ZERO)
}

/// Black-body spectral radiance at `nm` nanometres and `kelvin`, in W m⁻² sr⁻¹ nm⁻¹.
fn planck(nm: f64, kelvin: f64) -> f64 {
    const H: f64 = 6.626_070_15e-34;
    const C: f64 = 299_792_458.0;
    const K: f64 = 1.380_649e-23;
    let m = nm * 1e-9;
    2.0 * H * C * C / m.powi(5) / ((H * C / (m * K * kelvin)).exp() - 1.0) * 1e-9
}

/// The CIE 1931 colour-matching functions at `nm`, by Wyman, Sloan and Shirley's
/// multi-lobe fit (JCGT 2013, §2).
fn cie_1931(nm: f64) -> [f64; 3] {
    let g = |mu: f64, s1: f64, s2: f64| {
        let s = if nm < mu { s1 } else { s2 };
        (-0.5 * ((nm - mu) / s).powi(2)).exp()
    };
    [
        1.056 * g(599.8, 37.9, 31.0) + 0.362 * g(442.0, 16.0, 26.7) - 0.065 * g(501.1, 20.4, 26.2),
        0.821 * g(568.8, 46.9, 40.5) + 0.286 * g(530.9, 16.3, 31.1),
        1.217 * g(437.0, 11.8, 36.0) + 0.681 * g(459.0, 26.0, 13.8),
    ]
}

#[cfg(test)]
#[path = "sky_tests.rs"]
mod tests;
