//! `--sky`: a clear sky and its sun, as an environment.
//!
//! The sky is Hosek and Wilkie's analytic model (2012), its RGB fit, evaluated by the
//! `hw-skymodel` crate into an equirectangular map of the environment's convention and
//! then stored, paged and sampled as any map. Its unit is Mitsuba 3's `sunsky`: the model's
//! RGB over 106.7502…, Mitsuba's CIE Y normalization (checked against Mitsuba's `eval`
//! direction by direction). Below the horizon it is black, as Mitsuba's is.
//!
//! The sun is a disk of Mitsuba's aperture (0.5358°), uniformly bright, sampled as the
//! cone it subtends. Its radiance is Hosek and Wilkie's solar model (2013) as Mitsuba 3
//! uses it by default: the disk's irradiance, limb darkening integrated, tabulated over
//! turbidity and elevation (`sun_data.rs`) and spread evenly over the disk.

use super::env_build::{paged_capacity, Builder, Built};
use super::sun_data::SUN_IRRADIANCE;
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
/// `elevation` degrees up through air of `turbidity`: Hosek and Wilkie's solar irradiance
/// (`sun_data.rs`), interpolated linearly in turbidity and elevation, taken to linear sRGB
/// through the CIE 1931 observer at the model's wavelengths and spread evenly over the
/// disk, as Mitsuba 3's `sunsky` does (`complex_sun` off).
pub fn sun_radiance(elevation: f32, turbidity: f32) -> V {
    let lerp_index = |x: f32, last: usize| {
        let x = x.clamp(0.0, last as f32);
        let i = (x as usize).min(last - 1);
        (i, x - i as f32)
    };
    let (t, ft) = lerp_index(turbidity - 1.0, SUN_IRRADIANCE.len() - 1);
    let (e, fe) = lerp_index((elevation - 2.0) / 3.0, SUN_IRRADIANCE[0].len() - 1);
    let at = |t: usize, e: usize, k: usize| SUN_IRRADIANCE[t][e][k];
    let mut rgb = V::ZERO;
    for (k, xyz) in CIE_1931_AT_MODEL_WAVELENGTHS.iter().enumerate() {
        let low = at(t, e, k) * (1.0 - fe) + at(t, e + 1, k) * fe;
        let high = at(t + 1, e, k) * (1.0 - fe) + at(t + 1, e + 1, k) * fe;
        rgb += xyz_to_linear_srgb(*xyz) * (low * (1.0 - ft) + high * ft);
    }
    // Mitsuba's spectral-to-RGB constant for the sun, over the disk's solid angle as
    // Mitsuba computes it (1 − cos in single precision, 0.2% under the exact value):
    // the same radiance as Mitsuba's, so that renders compare.
    const SPEC_TO_RGB_SUN_CONV: f32 = 467.069_3;
    let half = (0.5 * SUN_APERTURE_DEG).to_radians();
    let solid_angle = 2.0 * PI * (1.0 - half.cos());
    let le = rgb / CIE_1931_AT_MODEL_WAVELENGTHS.len() as f32 * SPEC_TO_RGB_SUN_CONV
        / CIE_Y_NORMALIZATION
        / solid_angle;
    // Within a degree or two of the horizon the red sun's blue falls out of the sRGB
    // gamut; a light is never negative, so it is clamped there (Mitsuba keeps it).
    le.max(V::ZERO)
}

/// The CIE 1931 2° colour-matching functions (x̄, ȳ, z̄) at 320, 360, …, 720 nm.
const CIE_1931_AT_MODEL_WAVELENGTHS: [[f32; 3]; 11] = [
    [0.0, 0.0, 0.0],
    [1.299e-4, 3.917e-6, 6.061e-4],
    [1.431e-2, 3.96e-4, 6.785e-2],
    [3.4828e-1, 2.3e-2, 1.74706],
    [9.564e-2, 1.3902e-1, 8.1295e-1],
    [6.327e-2, 7.1e-1, 7.825e-2],
    [5.945e-1, 9.95e-1, 3.9e-3],
    [1.0622, 6.31e-1, 8.0e-4],
    [4.479e-1, 1.75e-1, 2.0e-5],
    [4.677e-2, 1.7e-2, 0.0],
    [2.899_327e-3, 1.047e-3, 0.0],
];

/// CIE XYZ to linear sRGB (Rec. 709 primaries, D65 white).
fn xyz_to_linear_srgb([x, y, z]: [f32; 3]) -> V {
    V::new(
        3.240_479 * x - 1.537_15 * y - 0.498_535 * z,
        -0.969_256 * x + 1.875_991 * y + 0.041_556 * z,
        0.055_648 * x - 0.204_043 * y + 1.057_311 * z,
    )
}

#[cfg(test)]
#[path = "sky_tests.rs"]
mod tests;
