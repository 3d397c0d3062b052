//! Where the sun stands in the sky at a place and time: the Astronomical Almanac's
//! low-precision solar coordinates (mean longitude and anomaly, the ecliptic longitude to
//! the second harmonic, the obliquity; then right ascension, declination and the local
//! hour angle from Greenwich mean sidereal time), good to about 0.01° between 1950 and
//! 2050. World frame of `--sky`: +Y up, north toward −Z and east toward +X, so the
//! compass azimuth is the map's longitude.

use chrono::{DateTime, FixedOffset};

/// The sun's elevation above the horizon and its compass azimuth (from north through
/// east), in degrees, at `latitude` (north positive) and `longitude` (east positive) at
/// `time`.
pub fn sun_position(latitude: f64, longitude: f64, time: DateTime<FixedOffset>) -> [f64; 2] {
    // Days from J2000.0 (2000-01-01 12:00 UT).
    let unix_days =
        time.timestamp() as f64 / 86_400.0 + time.timestamp_subsec_nanos() as f64 / 86_400e9;
    let n = unix_days + 2_440_587.5 - 2_451_545.0;
    let mean_longitude = 280.460 + 0.985_647_4 * n;
    let anomaly = (357.528 + 0.985_600_3 * n).to_radians();
    let ecliptic =
        (mean_longitude + 1.915 * anomaly.sin() + 0.020 * (2.0 * anomaly).sin()).to_radians();
    let obliquity = (23.439 - 0.000_000_4 * n).to_radians();
    let right_ascension = (obliquity.cos() * ecliptic.sin()).atan2(ecliptic.cos());
    let declination = (obliquity.sin() * ecliptic.sin()).asin();
    // Greenwich mean sidereal time in hours, then the local hour angle.
    let sidereal = 18.697_374_558 + 24.065_709_824_419_08 * n;
    let hour_angle =
        ((sidereal * 15.0 + longitude).rem_euclid(360.0)).to_radians() - right_ascension;
    let (sin_lat, cos_lat) = latitude.to_radians().sin_cos();
    let (sin_dec, cos_dec) = declination.sin_cos();
    let cos_zenith = sin_lat * sin_dec + cos_lat * cos_dec * hour_angle.cos();
    let elevation = 90.0 - cos_zenith.clamp(-1.0, 1.0).acos().to_degrees();
    let azimuth = (-hour_angle.sin() * cos_dec)
        .atan2(sin_dec * cos_lat - cos_dec * sin_lat * hour_angle.cos())
        .to_degrees()
        .rem_euclid(360.0);
    [elevation, azimuth]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Mitsuba 3.9.1's `sunsky` (Blanco-Muriel et al.'s PSA algorithm, an independent
    /// method) placed the sun at these (latitude, longitude, time) → (elevation, azimuth):
    /// its `sun_direction` in its local frame (X south, Y west, Z up) read back.
    const MITSUBA: [(f64, f64, &str, f64, f64); 6] = [
        (
            35.6894,
            139.6917,
            "2010-07-10T15:00:00+09:00",
            46.080,
            265.752,
        ),
        (
            35.6894,
            139.6917,
            "2010-07-10T08:00:00+09:00",
            39.382,
            89.193,
        ),
        (48.85, 2.35, "2026-12-03T12:30:00+01:00", 18.976, 177.457),
        (-33.87, 151.21, "2026-01-15T17:45:00+10:00", 15.453, 254.662),
        (64.15, -21.94, "2026-06-21T23:30:00+00:00", 0.638, 332.76),
        (0.0, 0.0, "2026-03-20T12:00:00+00:00", 88.134, 91.329),
    ];

    fn direction([elevation, azimuth]: [f64; 2]) -> [f64; 3] {
        let (se, ce) = elevation.to_radians().sin_cos();
        let (sa, ca) = azimuth.to_radians().sin_cos();
        [ce * sa, se, -ce * ca]
    }

    #[test]
    fn the_sun_stands_where_mitsuba_puts_it() {
        for (lat, lon, time, elevation, azimuth) in MITSUBA {
            let time = DateTime::parse_from_rfc3339(time).unwrap();
            let ours = direction(sun_position(lat, lon, time));
            let theirs = direction([elevation, azimuth]);
            let cos: f64 = ours.iter().zip(theirs).map(|(a, b)| a * b).sum();
            let degrees = cos.clamp(-1.0, 1.0).acos().to_degrees();
            // Both are good to about 0.01°; the sun is 0.54° wide.
            assert!(degrees < 0.03, "{lat}, {lon} at {time}: {degrees}° apart");
        }
    }
}
