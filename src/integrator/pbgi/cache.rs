//! The irradiance cache: PBGI's gathers shared between pixels.
//!
//! 003 ch. 2 gathers once per micropolygon, not per pixel sample; Canopy shares a gather
//! with every receiver near it on the same surface, as irradiance caching does (Ward,
//! Rubinstein and Clear 1988, and the splatting weight of 003 eq. 5.1). A record holds a
//! gather's irradiance E at a point p with normal n and the harmonic mean distance R of
//! what its micro-buffer saw. A receiver x with normal m reads the records with
//!
//!   ε = |x − p| / R + √(1 − m·n) < a        (a = `--pbgi-cache`)
//!
//! weighted by 1/ε − 1/a (which falls to zero at the edge, so no record's border shows)
//! and skips records in front of it (their hemisphere sees what x's cannot). R is clamped
//! to between one and `MAX_PIXELS` pixel footprints over a, so a record covers at least
//! its own pixel and no record spreads across a large part of the screen.
//!
//! Records are placed before the first pass, coarse to fine over the pixel grid (every
//! 16th pixel, then 8th, … then every pixel), each level gathering only where the records
//! of the levels before it leave the pixel's first hit uncovered; a level's records are
//! added once all of them are gathered, so the cache, like the image, does not depend on
//! the thread count. Receivers the cache misses gather alone (`--pbgi-reuse`).

use glam::Vec3A as V;
use std::collections::HashMap;

/// Largest influence radius a·R of a record, in pixel footprints at its point.
pub const MAX_PIXELS: f32 = 4.0;

/// One gather kept.
#[derive(Clone, Copy, Debug)]
pub struct Record {
    pub p: V,
    pub n: V,
    /// Irradiance.
    pub e: V,
    /// Harmonic mean distance, clamped (see the module doc).
    pub r: f32,
}

impl Record {
    /// A gather's record: `harmonic` the harmonic mean distance of its micro-buffer's
    /// hits (infinite when it saw nothing), `footprint` a pixel's width at p.
    pub fn new(p: V, n: V, e: V, harmonic: f32, footprint: f32, a: f32) -> Record {
        let lo = footprint / a;
        let hi = MAX_PIXELS * lo;
        let r = if harmonic.is_finite() {
            harmonic.clamp(lo, hi)
        } else {
            hi
        };
        Record { p, n, e, r }
    }
}

/// The records, found through a hash grid per power-of-two cell size.
pub struct IrradianceCache {
    a: f32,
    records: Vec<Record>,
    /// (level, cell) → records whose influence sphere overlaps the cell; a record sits at
    /// the level whose cells are at least as wide as its sphere.
    grid: HashMap<(i8, [i32; 3]), Vec<u32>>,
    levels: Vec<i8>,
}

impl IrradianceCache {
    /// An empty cache of error bound `a` (> 0).
    pub fn new(a: f32) -> IrradianceCache {
        IrradianceCache {
            a,
            records: Vec::new(),
            grid: HashMap::new(),
            levels: Vec::new(),
        }
    }

    /// The error bound a.
    pub fn a(&self) -> f32 {
        self.a
    }

    pub fn len(&self) -> usize {
        self.records.len()
    }

    pub fn is_empty(&self) -> bool {
        self.records.is_empty()
    }

    /// Bytes held (records and grid lists).
    pub fn bytes(&self) -> u64 {
        let lists: usize = self.grid.values().map(|v| v.capacity() * 4 + 48).sum();
        (self.records.capacity() * size_of::<Record>() + lists) as u64
    }

    /// Adds records, in their order.
    pub fn extend(&mut self, records: impl IntoIterator<Item = Record>) {
        for rec in records {
            if !(rec.p.is_finite() && rec.e.is_finite() && rec.r > 0.0 && rec.r.is_finite()) {
                continue;
            }
            let reach = self.a * rec.r;
            // A sphere too wide for f32 cells would span billions of them.
            if !(2.0 * reach).is_finite() {
                continue;
            }
            let id = self.records.len() as u32;
            let level = level_of(2.0 * reach);
            let size = cell_size(level);
            let lo = cell(rec.p - V::splat(reach), size);
            let hi = cell(rec.p + V::splat(reach), size);
            for x in lo[0]..=hi[0] {
                for y in lo[1]..=hi[1] {
                    for z in lo[2]..=hi[2] {
                        self.grid.entry((level, [x, y, z])).or_default().push(id);
                    }
                }
            }
            if let Err(at) = self.levels.binary_search(&level) {
                self.levels.insert(at, level);
            }
            self.records.push(rec);
        }
    }

    /// The weighted mean irradiance of the records that cover a receiver at `x` with
    /// normal `m`, or None when none does.
    pub fn lookup(&self, x: V, m: V) -> Option<V> {
        let (mut sum, mut weight) = (V::ZERO, 0.0f32);
        for &level in &self.levels {
            let Some(ids) = self.grid.get(&(level, cell(x, cell_size(level)))) else {
                continue;
            };
            for &id in ids {
                let rec = &self.records[id as usize];
                if let Some(w) = self.weight(rec, x, m) {
                    sum += rec.e * w;
                    weight += w;
                }
            }
        }
        (weight > 0.0).then(|| sum / weight)
    }

    /// Record `rec`'s weight at x with normal m, if it covers x.
    fn weight(&self, rec: &Record, x: V, m: V) -> Option<f32> {
        let cos = rec.n.dot(m);
        if cos <= 0.0 {
            return None;
        }
        let d = x - rec.p;
        // A record in front of x sees what x's hemisphere cannot.
        if d.dot(rec.n + m) < -0.1 * self.a * rec.r {
            return None;
        }
        let eps = d.length() / rec.r + (1.0 - cos).max(0.0).sqrt();
        (eps < self.a).then(|| 1.0 / eps.max(1e-6 * self.a) - 1.0 / self.a)
    }
}

/// Cells of level L are 2^L wide (scene units).
fn cell_size(level: i8) -> f32 {
    (level as f32).exp2()
}

/// The smallest level whose cells are at least `width` wide.
fn level_of(width: f32) -> i8 {
    width.max(1e-30).log2().ceil().clamp(-100.0, 127.0) as i8
}

fn cell(p: V, size: f32) -> [i32; 3] {
    let c = (p / size).floor();
    [c.x as i32, c.y as i32, c.z as i32]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_rng::TestRng;

    fn random_cache(rng: &mut TestRng, count: usize) -> (IrradianceCache, Vec<Record>) {
        let mut v = || V::new(rng.f32(), rng.f32(), rng.f32());
        let recs: Vec<Record> = (0..count)
            .map(|_| Record {
                p: v() * 10.0,
                n: (v() * 0.4 + V::Z).normalize(),
                e: v(),
                r: 0.05 + v().x * 3.0,
            })
            .collect();
        let mut cache = IrradianceCache::new(0.4);
        cache.extend(recs.iter().copied());
        (cache, recs)
    }

    /// The grid finds exactly the records a scan of all of them finds, with their
    /// weighted mean.
    #[test]
    fn lookups_through_the_grid_equal_a_scan_of_every_record() {
        let mut rng = TestRng::new(5);
        let (cache, recs) = random_cache(&mut rng, 400);
        let mut hits = 0;
        for _ in 0..2000 {
            let x = V::new(rng.f32(), rng.f32(), rng.f32()) * 10.0;
            let m = (V::new(rng.f32(), rng.f32(), rng.f32()) * 0.4 + V::Z).normalize();
            let (mut sum, mut weight) = (V::ZERO, 0.0);
            for r in &recs {
                if let Some(w) = cache.weight(r, x, m) {
                    sum += r.e * w;
                    weight += w;
                }
            }
            let got = cache.lookup(x, m);
            match got {
                Some(e) => {
                    hits += 1;
                    let want = sum / weight;
                    assert!((e - want).abs().max_element() < 1e-4, "{e} against {want}");
                }
                None => assert_eq!(weight, 0.0),
            }
        }
        assert!(hits > 200, "{hits} lookups hit");
    }

    /// A receiver on a record reads it; its weight falls to zero at distance a·R and at
    /// a normal turned by acos(1 − a²); a record in front of the receiver is skipped.
    #[test]
    fn a_record_covers_its_sphere_of_influence_and_no_more() {
        let rec = Record {
            p: V::ZERO,
            n: V::Z,
            e: V::new(1.0, 2.0, 3.0),
            r: 2.0,
        };
        let mut cache = IrradianceCache::new(0.5);
        cache.extend([rec]);
        assert_eq!(cache.lookup(V::ZERO, V::Z), Some(rec.e));
        assert!(cache.lookup(V::new(0.99, 0.0, 0.0), V::Z).is_some());
        assert!(cache.lookup(V::new(1.01, 0.0, 0.0), V::Z).is_none());
        let turned = |deg: f32| V::new(deg.to_radians().sin(), 0.0, deg.to_radians().cos());
        let limit = (1.0f32 - 0.25).acos().to_degrees();
        assert!(cache.lookup(V::ZERO, turned(limit - 1.0)).is_some());
        assert!(cache.lookup(V::ZERO, turned(limit + 1.0)).is_none());
        // x below the record's plane: the record, in front of it, sees more.
        assert!(cache.lookup(V::new(0.0, 0.0, -0.5), V::Z).is_none());
        assert!(cache.lookup(V::new(0.0, 0.0, 0.5), V::Z).is_some());
    }

    /// R is clamped to [1, MAX_PIXELS] pixel footprints over a, and a gather that saw
    /// nothing gets the largest.
    #[test]
    fn a_records_radius_is_clamped_to_its_pixel_footprints() {
        let r = |h: f32| Record::new(V::ZERO, V::Z, V::ONE, h, 0.01, 0.5).r;
        assert_eq!(r(1e-9), 0.02);
        assert_eq!(r(0.05), 0.05);
        assert_eq!(r(100.0), 0.02 * MAX_PIXELS);
        assert_eq!(r(f32::INFINITY), 0.02 * MAX_PIXELS);
    }
}
