//! Parsing of user-facing quantities: sizes (`512MiB`, `2GiB`, `1.5G`, `1000000`) and
//! durations (`90s`, `5m`, `1h`, `250ms`).

use anyhow::{bail, Result};

/// Bytes from a size with an optional unit; K/M/G/T and KiB/MiB/GiB/TiB are both binary
/// (powers of 1024), KB/MB/GB/TB decimal.
pub fn parse_size(s: &str) -> Result<u64> {
    let t = s.trim();
    let split = t
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(t.len());
    let (num, unit) = t.split_at(split);
    let Ok(v) = num.parse::<f64>() else {
        bail!("'{s}' is not a size (try 512MiB, 2GiB, 1.5G)")
    };
    let mult: f64 = match unit.to_ascii_lowercase().as_str() {
        "" | "b" => 1.0,
        "k" | "kib" => 1024.0,
        "m" | "mib" => 1024.0 * 1024.0,
        "g" | "gib" => 1024.0 * 1024.0 * 1024.0,
        "t" | "tib" => 1024f64.powi(4),
        "kb" => 1e3,
        "mb" => 1e6,
        "gb" => 1e9,
        "tb" => 1e12,
        u => bail!("'{s}': unknown size unit '{u}' (use B, KiB, MiB, GiB, TiB, K, M, G, T, KB, MB, GB, TB)"),
    };
    let bytes = v * mult;
    if !bytes.is_finite() || bytes >= u64::MAX as f64 {
        bail!("'{s}' is too large");
    }
    Ok(bytes as u64)
}

/// A size as a person writes it: whole MiB or GiB where exact (`64MiB`), else MiB to a
/// tenth with the exact bytes (`3.8 MiB (3984588 bytes)`), or bytes below a MiB.
pub fn format_size(bytes: u64) -> String {
    const MIB: u64 = 1 << 20;
    match bytes {
        b if b >= 1 << 30 && b.is_multiple_of(1 << 30) => format!("{}GiB", b >> 30),
        b if b >= MIB && b.is_multiple_of(MIB) => format!("{}MiB", b / MIB),
        b if b >= MIB => format!("{:.1} MiB ({b} bytes)", b as f64 / MIB as f64),
        b => format!("{b} bytes"),
    }
}

/// `bytes` rounded up to whole MiB: a budget to suggest.
pub fn whole_mib(bytes: u64) -> u64 {
    bytes.div_ceil(1 << 20) << 20
}

/// Seconds from a duration with a unit (ms, s, m, h); a bare number is seconds.
pub fn parse_duration(s: &str) -> Result<std::time::Duration> {
    let t = s.trim();
    let split = t
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(t.len());
    let (num, unit) = t.split_at(split);
    let Ok(v) = num.parse::<f64>() else {
        bail!("'{s}' is not a duration (try 90s, 5m)")
    };
    let secs = match unit.trim() {
        "" | "s" => v,
        "ms" => v / 1000.0,
        "m" | "min" => v * 60.0,
        "h" => v * 3600.0,
        u => bail!("'{s}': unknown duration unit '{u}' (use ms, s, m, h)"),
    };
    std::time::Duration::try_from_secs_f64(secs)
        .map_err(|_| anyhow::anyhow!("'{s}' is not a valid duration"))
}

/// A finite number of at least 0 (NaN, infinities and negatives are refused).
pub fn parse_non_negative(s: &str) -> Result<f32> {
    match s.trim().parse::<f32>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => bail!("'{s}' is not a finite number of at least 0"),
    }
}

/// Threads each core may be given: more only adds contention and memory.
pub const THREADS_PER_CORE: usize = 16;

/// Most worker threads accepted: `THREADS_PER_CORE` × the cores available.
pub fn max_threads() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get()) * THREADS_PER_CORE
}

/// A worker-thread count from 1 to `max_threads()`.
pub fn parse_threads(s: &str) -> Result<usize> {
    let max = max_threads();
    match s.trim().parse::<usize>() {
        Ok(n) if (1..=max).contains(&n) => Ok(n),
        _ => bail!("'{s}' is not a thread count from 1 to {max} ({THREADS_PER_CORE} per core)"),
    }
}

/// A local time with its UTC offset, RFC 3339 (`2026-06-21T15:00:00+02:00`).
pub fn parse_time(s: &str) -> Result<chrono::DateTime<chrono::FixedOffset>> {
    chrono::DateTime::parse_from_rfc3339(s).map_err(|e| {
        anyhow::anyhow!(
            "'{s}' is not a time with its UTC offset such as 2026-06-21T15:00:00+02:00 ({e})"
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes() {
        assert_eq!(parse_size("512MiB").unwrap(), 512 << 20);
        assert_eq!(parse_size("2GiB").unwrap(), 2 << 30);
        assert_eq!(parse_size("1.5G").unwrap(), 3 << 29);
        assert_eq!(parse_size("10KB").unwrap(), 10_000);
        assert_eq!(parse_size("4096").unwrap(), 4096);
        assert!(parse_size("12 parsecs").is_err());
        assert!(parse_size("GiB").is_err());
        assert!(parse_size("1e400G").is_err());
    }

    #[test]
    fn durations() {
        assert_eq!(parse_duration("90s").unwrap().as_secs(), 90);
        assert_eq!(parse_duration("5m").unwrap().as_secs(), 300);
        assert_eq!(parse_duration("250ms").unwrap().as_millis(), 250);
        assert!(parse_duration("5 fortnights").is_err());
    }
}
