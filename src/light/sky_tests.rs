use super::*;
use crate::light::env::Environment;
use crate::material::luminance;

fn options(elevation: f32, azimuth: f32, turbidity: f32, albedo: f32) -> SkyOptions {
    SkyOptions {
        elevation,
        azimuth,
        turbidity,
        albedo,
        sun_strength: 0.0,
        place: None,
    }
}

/// Mitsuba 3.9.1's `sunsky` (scalar_rgb, `sun_scale` 0, its Z-up frame turned to +Y up)
/// evaluated toward five directions under two skies: (options, direction, radiance).
#[allow(clippy::type_complexity)]
const MITSUBA: [([f32; 4], [f32; 3], [f32; 3]); 10] = [
    (
        [30.0, 135.0, 3.0, 0.3],
        [0.0, 1.0, 0.0],
        [0.0164659, 0.0313386, 0.0625406],
    ),
    (
        [30.0, 135.0, 3.0, 0.3],
        [0.309426, 0.206284, -0.928279],
        [0.0686091, 0.112197, 0.165171],
    ),
    (
        [30.0, 135.0, 3.0, 0.3],
        [-0.959264, 0.068519, 0.274075],
        [0.114714, 0.163768, 0.192483],
    ),
    (
        [30.0, 135.0, 3.0, 0.3],
        [0.57735, 0.57735, 0.57735],
        [0.185147, 0.205157, 0.21691],
    ),
    (
        [30.0, 135.0, 3.0, 0.3],
        [0.0, 0.948683, 0.316228],
        [0.0211982, 0.0377499, 0.0710011],
    ),
    (
        [8.0, 200.0, 6.0, 0.1],
        [0.0, 1.0, 0.0],
        [0.0106901, 0.0173467, 0.0261605],
    ),
    (
        [8.0, 200.0, 6.0, 0.1],
        [0.309426, 0.206284, -0.928279],
        [0.0627472, 0.0768699, 0.0763717],
    ),
    (
        [8.0, 200.0, 6.0, 0.1],
        [-0.959264, 0.068519, 0.274075],
        [0.113447, 0.096901, 0.0620634],
    ),
    (
        [8.0, 200.0, 6.0, 0.1],
        [0.57735, 0.57735, 0.57735],
        [0.0314813, 0.0409859, 0.0485346],
    ),
    (
        [8.0, 200.0, 6.0, 0.1],
        [0.0, 0.948683, 0.316228],
        [0.0140487, 0.0209834, 0.0296556],
    ),
];

#[test]
fn the_sky_reads_as_mitsuba_reads_it() {
    let mut worst = 0f32;
    for ([e, a, t, al], d, want) in MITSUBA {
        let env = Environment::sky(&options(e, a, t, al), 1.0, 0.0, None).unwrap();
        let got = env.le(V::from(d));
        for c in 0..3 {
            worst = worst.max((got[c] / want[c] - 1.0).abs());
        }
    }
    // The map's bilinear texels against the model at the direction itself.
    assert!(worst < 2e-3, "worst relative difference {worst}");
}

#[test]
fn below_the_horizon_the_sky_is_black() {
    let env = Environment::sky(&options(30.0, 0.0, 3.0, 0.3), 1.0, 0.0, None).unwrap();
    for d in [V::NEG_Y, V::new(0.3, -0.05, 0.9).normalize()] {
        assert_eq!(env.le(d), V::ZERO);
    }
}

#[test]
fn the_sun_is_its_disk_and_is_sampled_as_it() {
    let o = SkyOptions {
        sun_strength: 1.0,
        ..options(40.0, 70.0, 3.0, 0.3)
    };
    let sun = Sun::new(&o, 1.0);
    let dir = o.sun_direction();
    let half = (0.5 * SUN_APERTURE_DEG).to_radians();
    let edge = |angle: f32| {
        let side = dir.cross(V::Y).normalize();
        (dir * angle.cos() + side * angle.sin()).normalize()
    };
    assert_eq!(sun.le(dir), sun.le);
    assert_eq!(sun.le(edge(0.98 * half)), sun.le);
    assert_eq!(sun.le(edge(1.02 * half)), V::ZERO);
    let mut rng = crate::test_rng::TestRng::new(3);
    for _ in 0..10_000 {
        let d = sun.sample([rng.f32(), rng.f32()]);
        assert!((d.length() - 1.0).abs() < 1e-5);
        assert_eq!(sun.le(d), sun.le, "a sample off the disk");
    }
    let want = 2.0 * std::f64::consts::PI * (1.0 - (half as f64).cos());
    assert!((sun.solid_angle() as f64 / want - 1.0).abs() < 1e-5);
}

#[test]
fn the_sun_dims_and_reddens_as_it_sets_and_as_the_air_thickens() {
    let ratio = |v: V| v.z / v.x;
    let high = sun_radiance(60.0, 3.0);
    let low = sun_radiance(10.0, 3.0);
    assert!(luminance(low) < 0.7 * luminance(high));
    assert!(ratio(low) < 0.7 * ratio(high));
    assert!(luminance(sun_radiance(60.0, 6.0)) < luminance(high));
}

#[test]
fn the_sun_shines_as_mitsuba_s() {
    // Mitsuba 3.9.1's `sunsky` (`sky_scale` 0, RGB), its `eval` toward the sun's centre:
    // (elevation°, turbidity) and radiance.
    for (elevation, turbidity, mitsuba) in [
        (89.0, 2.0, [22524.129, 19106.229, 15102.364]),
        (60.0, 1.5, [22387.91, 18789.75, 14453.259]),
        (20.0, 6.0, [15104.244, 10879.045, 6264.194]),
        (10.0, 3.0, [14494.261, 8789.176, 3141.136]),
        (5.0, 9.5, [325.1574, 109.41462, 17.305244]),
    ] {
        let ours = sun_radiance(elevation, turbidity);
        for c in 0..3 {
            assert!(
                (ours[c] / mitsuba[c] - 1.0).abs() < 1e-3,
                "{elevation}° turbidity {turbidity}: {ours:?} vs {mitsuba:?}"
            );
        }
    }
}

#[test]
fn options_out_of_the_model_are_refused_by_name() {
    for (o, flag) in [
        (options(-3.0, 0.0, 3.0, 0.3), "--sun-elevation"),
        (options(95.0, 0.0, 3.0, 0.3), "--sun-elevation"),
        (options(30.0, 0.0, 0.5, 0.3), "--turbidity"),
        (options(30.0, 0.0, 3.0, 1.5), "--ground-albedo"),
    ] {
        let e = Environment::sky(&o, 1.0, 0.0, None)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains(flag), "{e}");
    }
}
