//! The irradiance cache: PBGI's gathers shared between pixels.
//!
//! 003 ch. 2 gathers once per micropolygon, not per pixel sample; Canopy shares a gather
//! with every receiver near it on the same surface, as irradiance caching does (Ward,
//! Rubinstein and Clear 1988, and the splatting weight of 003 eq. 5.1). A record holds a
//! gather's irradiance E at a point p with normal n and the distance R over which it may
//! be carried: the smaller of the harmonic mean distance of what its micro-buffer saw and
//! a light-weighted inverse-square mean, so that bright light close by keeps it short. A
//! receiver x with normal m reads the records with
//!
//!   ε = |x − p| / R + √(1 − m·n) < a        (a = `--pbgi-cache`)
//!
//! weighted by 1/ε − 1/a (which falls to zero at the edge, so no record's border shows;
//! a radiance record takes √(max(1 − m·n, 1 − ω·ω_o) / turn) for the second term)
//! and skips records in front of it (their hemisphere sees what x's cannot). Each record
//! is carried to x by its irradiance gradients (Ward and Heckbert 1992, from the
//! micro-buffer's texel borders: [`Gradients`]): E + (x − p)·∇t + (n × m)·∇r, at least
//! zero; on bunny_box that lowered the RMSE by 8–9% at equal samples (the showroom and
//! sponza are unchanged). R is clamped
//! to between one and `MAX_PIXELS` pixel footprints over a, so a record covers at least
//! its own pixel and no record spreads across a large part of the screen.
//!
//! Records are placed before the first pass, coarse to fine over the pixel grid (every
//! 16th pixel, then 8th, … then every pixel), each level gathering only where the records
//! of the levels before it leave the pixel's first hit uncovered; a level's records are
//! added once all of them are gathered, so the cache, like the image, does not depend on
//! the thread count. Receivers the cache misses gather alone (`--pbgi-reuse`).
//!
//! A record's noise, unlike a pixel sample's, does not average away as the render goes
//! on: every receiver around it reads the same error. So between passes the records
//! take more gathers (at new rays) and keep their mean, those that gain most first: the
//! variance of a record's mean, s²/k over its k gathers, falls by s²/(k(k+1)) with one
//! more, spread over the pixels its sphere of influence spans, s² the records' mean
//! spread of a gather (a record's own would bias its mean: `worth_refining`), measured
//! on one record in `SPREAD_SAMPLE`, which take their second gather first.
//!
//! Refinement lowers the records' noise, not the interpolation's error where irradiance
//! changes faster than a record's gradients say (room's corner under the ceiling's hot
//! spot, a band narrower than a record's reach). So between passes a small share of the
//! rays also probes: a gather at a covered pixel is compared with what the cache gives
//! there and kept as a record when the two differ by more than two standard deviations
//! of their difference (the covering records' spread of a gather and of their means).

use super::microbuffer::Gradients;
use crate::material::luminance;
use crate::moments::Moments;
use glam::Vec3A as V;
use rustc_hash::FxHashMap;
use std::f32::consts::PI;

/// Largest influence radius a·R of a record, in pixel footprints at its point.
pub const MAX_PIXELS: f32 = 4.0;

/// Most gathers a record averages.
pub const MAX_GATHERS: u64 = 64;

/// One record in this many (by index) takes a second gather before any other is judged:
/// their spreads give the records' mean spread of a gather, by which the rest are
/// refined. A second gather for every record took sponza_textured's cache 16.0 s of a
/// 60-s render against 10.8 s, and its RMSE there was 9% higher (docs/pbgi.md).
pub const SPREAD_SAMPLE: usize = 8;

/// One gather kept, or the mean of several at one point.
#[derive(Clone, Copy, Debug)]
pub struct Record {
    pub p: V,
    pub n: V,
    /// Irradiance: the mean of the gathers.
    pub e: V,
    /// The mean of the gathers' gradients, in world space.
    pub g: Gradients,
    /// Harmonic mean distance, clamped (see the module doc).
    pub r: f32,
    /// The gathers' luminances.
    pub y: Moments,
    /// Pixels its sphere of influence covers, π (a·R / footprint)²: how many pixels its
    /// error reaches. The square of the radius alone (a third of that) refined too little:
    /// with the disc the 60-s RMSE fell by 2.5–5% on room, bunny_box and the showroom
    /// (sponza unchanged).
    pub pixels: f32,
    /// The pixel whose centre's first hit is p.
    pub at: [u32; 2],
    /// The luminance of the receiver's diffuse lobe: what a pixel shows per unit of E.
    pub lobe: f32,
    /// What 1 − cos of a receiver's turn away from the record is measured against in ε
    /// (see the module doc): 1 for irradiance; the lobe's width squared, (2α)², for
    /// radiance records (`radiance_cache`).
    pub turn: f32,
    /// A radiance record's outgoing direction, which a receiver's must match as its normal
    /// does (zero for irradiance).
    pub wo: V,
}

impl Record {
    /// A gather's record: `distance` how far its micro-buffer's light may be carried
    /// ([`super::microbuffer::MicroBuffer::reach_distance`]; infinite when it saw nothing),
    /// `footprint` a pixel's width at p.
    pub fn new(p: V, n: V, e: V, distance: f32, footprint: f32, a: f32) -> Record {
        let lo = footprint / a;
        let hi = MAX_PIXELS * lo;
        let r = if distance.is_finite() {
            distance.clamp(lo, hi)
        } else {
            hi
        };
        let y = Moments::of([luminance(e)]);
        Record {
            p,
            n,
            e,
            g: Gradients::default(),
            r,
            y,
            pixels: PI * (r / lo).powi(2),
            at: [0, 0],
            lobe: 1.0,
            turn: 1.0,
            wo: V::ZERO,
        }
    }

    /// Another gather's irradiance at p and its gradients.
    pub fn add(&mut self, e: V, g: &Gradients) {
        self.y.add(luminance(e));
        let share = 1.0 / self.y.count as f32;
        self.e += (e - self.e) * share;
        self.g.blend(g, share);
    }

    /// The gradients as a lookup applies them: each channel's translational one shortened
    /// so that it changes E by at most E across the record's reach a·R (Křivánek et al.
    /// 2006's gradient limiting): one texel ray per texel makes them noisy, and on the
    /// showroom the full gradients left the dark sides of the plinths 16% bright, their
    /// noise driven below zero and clamped.
    pub fn carry(&self, a: f32) -> Gradients {
        let reach = a * self.r;
        let mut g = self.g;
        for (c, t) in g.t.iter_mut().enumerate() {
            let most = self.e[c].max(0.0) / reach;
            let len = t.length();
            if len > most {
                *t *= most / len;
            }
        }
        g
    }

    /// How much one more gather would lower the squared error the record spreads over
    /// its pixels: the variance of its mean falls from s²/k to s²/(k+1), s² the spread of
    /// one gather, `spread`.
    pub fn gain(&self, spread: f64) -> f64 {
        let k = self.y.count as f64;
        if self.y.count >= MAX_GATHERS {
            return 0.0;
        }
        spread / (k * (k + 1.0)) * self.pixels as f64
    }
}

/// The records, found through a hash grid per power-of-two cell size.
pub struct IrradianceCache {
    a: f32,
    records: Vec<Record>,
    /// (level, cell) → records whose influence sphere overlaps the cell; a record sits at
    /// the level whose cells are at least as wide as its sphere.
    grid: FxHashMap<(i8, [i32; 3]), Vec<u32>>,
    levels: Vec<i8>,
    /// Per record: its gradients as lookups apply them ([`Record::carry`]).
    carry: Vec<Gradients>,
    /// The sum of the spreads of a gather of the records with two gathers or more, and
    /// their number: the records' mean spread ([`Self::gather_spread`]).
    spreads: (f64, u64),
}

impl IrradianceCache {
    /// An empty cache of error bound `a` (> 0).
    pub fn new(a: f32) -> IrradianceCache {
        IrradianceCache {
            a,
            records: Vec::new(),
            grid: FxHashMap::default(),
            levels: Vec::new(),
            carry: Vec::new(),
            spreads: (0.0, 0),
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

    /// Gathers the records averaged.
    pub fn gathers(&self) -> u64 {
        self.records.iter().map(|r| r.y.count).sum()
    }

    pub fn records(&self) -> &[Record] {
        &self.records
    }

    /// Another gather's irradiance for record `id`.
    pub fn add(&mut self, id: usize, e: V, g: &Gradients) {
        if e.is_finite() && g.is_finite() {
            self.count_spread(id, -1.0);
            self.records[id].add(e, g);
            self.count_spread(id, 1.0);
            self.carry[id] = self.records[id].carry(self.a);
        }
    }

    /// Adds (`sign` 1) or takes away (−1) record `id`'s spread in the records' sum.
    fn count_spread(&mut self, id: usize, sign: f64) {
        let y = &self.records[id].y;
        if y.count >= 2 {
            self.spreads.0 = (self.spreads.0 + sign * y.variance()).max(0.0);
            self.spreads.1 = self.spreads.1.wrapping_add_signed(sign as i64);
        }
    }

    /// The records' mean spread of a gather (luminance variance), over those with two
    /// gathers or more; None while there are none.
    pub fn gather_spread(&self) -> Option<f64> {
        let (sum, n) = self.spreads;
        (n > 0).then(|| sum / n as f64)
    }

    /// The records (in index order) whose next gather lowers the squared error they
    /// spread over their pixels, [`Record::gain`] times their lobe squared, by more than
    /// `threshold`, and every record of one gather among the `SPREAD_SAMPLE`-th; none that
    /// has `MAX_GATHERS`.
    ///
    /// A gather's spread is the records' mean ([`Self::gather_spread`]), the same for
    /// all: a record that chose by its own spread stopped where its first gathers happened
    /// to agree, and where light is heavy-tailed they agree low, having missed the tail,
    /// so the records' mean fell short (caustics at 256 spp −0.6%, room_glass at 16 spp
    /// −0.3%, against −0.09% to +0.08% and +0.03% with every sample gathering for itself).
    /// The sampled records are chosen by index, not by what they hold, so their spreads
    /// are the records'.
    pub fn worth_refining(&self, threshold: f64) -> Vec<usize> {
        let spread = self.gather_spread().unwrap_or(0.0);
        let worth = |i: usize| {
            let r = &self.records[i];
            let sampled = i.is_multiple_of(SPREAD_SAMPLE) && r.y.count < 2;
            sampled || r.gain(spread) * (r.lobe as f64).powi(2) > threshold
        };
        (0..self.records.len()).filter(|&i| worth(i)).collect()
    }

    /// Bytes held (records and grid lists).
    pub fn bytes(&self) -> u64 {
        let lists: usize = self.grid.values().map(|v| v.capacity() * 4 + 48).sum();
        let carry = self.carry.capacity() * size_of::<Gradients>();
        (self.records.capacity() * size_of::<Record>() + carry + lists) as u64
    }

    /// Room for `n` more records, and no more.
    pub fn reserve_exact(&mut self, n: usize) {
        self.records.reserve_exact(n);
        self.carry.reserve_exact(n);
    }

    /// Bytes a record adds at most once room is made for it: itself, its carried
    /// gradients, and a place (and a list) in the grid's cells.
    pub fn record_cost() -> u64 {
        (size_of::<Record>() + size_of::<Gradients>() + 8 * (4 + 48)) as u64
    }

    /// Adds records, in their order.
    pub fn extend(&mut self, records: impl IntoIterator<Item = Record>) {
        for rec in records {
            let finite = rec.p.is_finite() && rec.e.is_finite() && rec.g.is_finite();
            if !(finite && rec.r > 0.0 && rec.r.is_finite()) {
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
            self.carry.push(rec.carry(self.a));
            self.records.push(rec);
            self.count_spread(id as usize, 1.0);
        }
    }

    /// The weighted mean irradiance of the records that cover a receiver at `x` with
    /// normal `m`, and the smallest reach a·R among them; None when none does.
    pub fn lookup(&self, x: V, m: V) -> Option<(V, f32)> {
        let (mut sum, mut weight, mut reach) = (V::ZERO, 0.0f32, f32::INFINITY);
        self.covering(x, m, V::ZERO, |id, w| {
            let rec = &self.records[id];
            let moved = self.carry[id].change((x - rec.p).into(), rec.n.cross(m).into());
            sum += (rec.e + V::from(moved)).max(V::ZERO) * w;
            weight += w;
            reach = reach.min(self.a * rec.r);
        });
        (weight > 0.0).then(|| (sum / weight, reach))
    }

    /// Whether a gather's irradiance `e` at `x` with normal `m` differs from what the
    /// cache gives there by more than `sigmas` standard deviations of the difference, in
    /// luminance (the cache's and the gather's variance from [`Self::spread`]). None where
    /// the cache cannot tell: no record covers x, or none that does has two gathers.
    pub fn disagrees(&self, x: V, m: V, e: V, sigmas: f64) -> Option<bool> {
        let (of_cache, of_gather) = self.spread(x, m)?;
        let (cached, _) = self.lookup(x, m)?;
        let d = (luminance(e) - luminance(cached)) as f64;
        Some(d * d > sigmas * sigmas * (of_cache + of_gather))
    }

    /// The variance of what the cache gives at `x` with normal `m` and of one gather
    /// there, in luminance: the covering records' spread of a gather, s² (their own with
    /// two gathers or more, else the records' mean), weighted as `lookup` weighs them,
    /// and that over their gathers, s²/k. None when no record covers x or no spread is
    /// known yet.
    pub fn spread(&self, x: V, m: V) -> Option<(f64, f64)> {
        let known = self.gather_spread()?;
        let (mut mean, mut gather, mut weight) = (0.0, 0.0, 0.0);
        self.covering(x, m, V::ZERO, |id, w| {
            let y = &self.records[id].y;
            let s2 = if y.count >= 2 { y.variance() } else { known };
            let w = w as f64;
            mean += w * s2 / y.count as f64;
            gather += w * s2;
            weight += w;
        });
        (weight > 0.0).then(|| (mean / weight, gather / weight))
    }

    /// Calls `f` with the index and weight of every record that covers x with normal m
    /// and outgoing direction `wo` (read by radiance records only).
    pub fn covering(&self, x: V, m: V, wo: V, mut f: impl FnMut(usize, f32)) {
        for &level in &self.levels {
            let Some(ids) = self.grid.get(&(level, cell(x, cell_size(level)))) else {
                continue;
            };
            for &id in ids {
                if let Some(w) = self.weight(&self.records[id as usize], x, m, wo) {
                    f(id as usize, w);
                }
            }
        }
    }

    /// Record `rec`'s weight at x with normal m and outgoing direction wo, if it covers x.
    fn weight(&self, rec: &Record, x: V, m: V, wo: V) -> Option<f32> {
        weight(rec, self.a, x, m, wo)
    }
}

/// Record `rec`'s weight at x with normal m and outgoing direction wo in a cache of error
/// bound `a`, if it covers x.
pub fn weight(rec: &Record, a: f32, x: V, m: V, wo: V) -> Option<f32> {
    let cos = rec.n.dot(m);
    if cos <= 0.0 {
        return None;
    }
    let d = x - rec.p;
    // A record in front of x sees what x's hemisphere cannot.
    if d.dot(rec.n + m) < -0.1 * a * rec.r {
        return None;
    }
    let mut bend = 1.0 - cos;
    if rec.wo != V::ZERO {
        bend = bend.max(1.0 - rec.wo.dot(wo));
    }
    let eps = d.length() / rec.r + (bend / rec.turn).max(0.0).sqrt();
    (eps < a).then(|| 1.0 / eps.max(1e-6 * a) - 1.0 / a)
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

    /// A gather beyond two standard deviations of the difference from the cache (the
    /// records' spread of a gather plus that of their means) disagrees with it, one within
    /// does not, and the cache cannot tell where no record has two gathers yet or where
    /// none covers.
    #[test]
    fn a_gather_disagrees_beyond_the_records_spread() {
        let mut cache = IrradianceCache::new(0.5);
        let record = |p: V, gathers: &[f32]| {
            let mut r = Record::new(p, V::Z, V::splat(gathers[0]), 1.0, 0.01, 0.5);
            for &e in &gathers[1..] {
                r.add(V::splat(e), &Gradients::default());
            }
            r
        };
        cache.extend([
            record(V::ZERO, &[1.0, 1.2]),
            record(V::X * 0.01, &[0.9, 1.1]),
        ]);
        let x = V::X * 0.005;
        let (e, _) = cache.lookup(x, V::Z).unwrap();
        assert!((luminance(e) - 1.05).abs() < 1e-4, "{e}");
        // Both records: s² = 0.02 over 2 gathers; the difference's variance is 0.03.
        let (of_cache, of_gather) = cache.spread(x, V::Z).unwrap();
        assert!((of_cache - 0.01).abs() < 1e-6 && (of_gather - 0.02).abs() < 1e-6);
        let sd = 0.03f32.sqrt();
        for (e, far) in [
            (1.05 + 2.1 * sd, true),
            (1.05 - 2.1 * sd, true),
            (1.05 + 1.9 * sd, false),
        ] {
            assert_eq!(cache.disagrees(x, V::Z, V::splat(e), 2.0), Some(far), "{e}");
        }
        assert_eq!(cache.disagrees(V::X * 5.0, V::Z, V::ONE, 2.0), None);
        let mut young = IrradianceCache::new(0.5);
        young.extend([record(V::ZERO, &[1.0])]);
        assert!(young.lookup(x, V::Z).is_some());
        assert_eq!(young.disagrees(x, V::Z, V::splat(9.0), 2.0), None);
        // Once some record has a spread, a record of one gather takes the records' mean:
        // s² = 0.02 from a record far away, over its one gather.
        young.extend([record(V::X * 5.0, &[1.0, 1.2])]);
        let (of_cache, of_gather) = young.spread(x, V::Z).unwrap();
        assert!((of_cache - 0.02).abs() < 1e-6 && (of_gather - 0.02).abs() < 1e-6);
        assert_eq!(young.disagrees(x, V::Z, V::splat(9.0), 2.0), Some(true));
    }

    fn random_cache(rng: &mut TestRng, count: usize) -> (IrradianceCache, Vec<Record>) {
        let mut v = || V::new(rng.f32(), rng.f32(), rng.f32());
        let recs: Vec<Record> = (0..count)
            .map(|_| Record {
                p: v() * 10.0,
                n: (v() * 0.4 + V::Z).normalize(),
                e: v(),
                g: Gradients {
                    t: [(); 3].map(|_| (v() - V::splat(0.5)).into()),
                    r: [(); 3].map(|_| (v() - V::splat(0.5)).into()),
                },
                r: 0.05 + v().x * 3.0,
                y: Moments::default(),
                pixels: 1.0,
                at: [0, 0],
                lobe: 1.0,
                turn: 1.0,
                wo: V::ZERO,
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
                if let Some(w) = cache.weight(r, x, m, V::ZERO) {
                    let d = x - r.p;
                    let turn = r.n.cross(m);
                    let g = r.carry(cache.a());
                    let moved = V::from_array(
                        [0, 1, 2].map(|c| g.t[c].dot(d.into()) + g.r[c].dot(turn.into())),
                    );
                    sum += (r.e + moved).max(V::ZERO) * w;
                    weight += w;
                }
            }
            let got = cache.lookup(x, m);
            match got {
                Some((e, _)) => {
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
            g: Gradients::default(),
            r: 2.0,
            y: Moments::default(),
            pixels: 1.0,
            at: [0, 0],
            lobe: 1.0,
            turn: 1.0,
            wo: V::ZERO,
        };
        let mut cache = IrradianceCache::new(0.5);
        cache.extend([rec]);
        assert_eq!(cache.lookup(V::ZERO, V::Z), Some((rec.e, 1.0)));
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

    /// A receiver reads a record moved by its gradients: a step along the translational
    /// one, a normal turned about the rotational one; a steep translational gradient is
    /// limited to changing E by E across the record's reach.
    #[test]
    fn a_record_is_carried_to_the_receiver_by_its_gradients() {
        let g = Gradients {
            t: [glam::Vec3::X * 0.5; 3],
            r: [glam::Vec3::Y; 3],
        };
        let rec = Record {
            g,
            ..Record::new(V::ZERO, V::Z, V::ONE, 2.0, 1.0, 0.5)
        };
        let mut cache = IrradianceCache::new(0.5);
        cache.extend([rec]);
        let e = |x: V, m: V| cache.lookup(x, m).unwrap().0;
        assert!(
            (e(V::new(0.2, 0.0, 0.0), V::Z) - V::splat(1.1))
                .abs()
                .max_element()
                < 1e-6
        );
        let a = 0.1f32;
        let turned = V::new(a.sin(), 0.0, a.cos());
        assert!(
            (e(V::ZERO, turned) - V::splat(1.0 + a.sin()))
                .abs()
                .max_element()
                < 1e-6
        );
        let back = e(V::new(-0.01, 0.0, 0.0), V::Z);
        assert!(
            (back - V::splat(0.995)).abs().max_element() < 1e-6,
            "{back}"
        );
        let steep = Record {
            g: Gradients {
                t: [glam::Vec3::X * 100.0; 3],
                ..g
            },
            ..rec
        };
        let mut cache = IrradianceCache::new(0.5);
        cache.extend([steep]);
        // Limited to E over the reach a·R = 1: 1 per unit, not 100.
        let e = cache.lookup(V::new(-0.02, 0.0, 0.0), V::Z).unwrap().0;
        assert!((e - V::splat(0.98)).abs().max_element() < 1e-6, "{e}");
    }

    /// Records whose gathers are skewed (0.5 plus an exponential of mean 0.5, as when a
    /// few texels see a hot spot), refined a gather a round while their gain is worth it:
    /// their mean keeps 1 within four standard errors (a gather's deviation is 0.5).
    /// Refined by their own spread shrunk toward the records' mean (four gathers' worth)
    /// it read 2.7% low, by their own spread alone 8% low: stopping where the first
    /// gathers agree stops where they are low.
    #[test]
    fn refined_records_keep_a_skewed_mean() {
        let mut rng = TestRng::new(5);
        let mut draw = || V::splat(0.5 - 0.5 * (1.0 - rng.f32()).ln());
        let (trials, records) = (200, 50);
        let (mut sum, mut gathers) = (0.0f64, 0u64);
        for _ in 0..trials {
            let mut cache = IrradianceCache::new(0.3);
            cache.extend((0..records).map(|_| Record::new(V::ZERO, V::Z, draw(), 1.0, 0.01, 0.3)));
            loop {
                let ids = cache.worth_refining(0.2);
                if ids.is_empty() {
                    break;
                }
                ids.into_iter()
                    .for_each(|i| cache.add(i, draw(), &Gradients::default()));
            }
            sum += cache.records().iter().map(|r| r.e.x as f64).sum::<f64>();
            gathers += cache.gathers();
        }
        let n = (trials * records) as f64;
        let (mean, gathers) = (sum / n, gathers as f64 / n);
        let se = 0.5 / (n * gathers).sqrt();
        assert!(
            (mean - 1.0).abs() < 4.0 * se,
            "mean {mean} over {gathers} gathers, standard error {se}"
        );
    }

    /// A record's irradiance is the mean of its gathers and its moments those of their
    /// luminances; refinement goes to the sampled records of one gather, and to those of
    /// the fewest gathers over the most pixels (as their lobe shows them), a gather's
    /// spread being the records' mean, past a threshold, never to one at `MAX_GATHERS`.
    #[test]
    fn records_average_their_gathers_and_the_uncertain_are_refined() {
        let mut rng = TestRng::new(9);
        let gathers: Vec<V> = (0..9)
            .map(|_| V::new(rng.f32(), rng.f32(), rng.f32()))
            .collect();
        let mut rec = Record::new(V::ZERO, V::Z, gathers[0], 1.0, 0.01, 0.3);
        gathers[1..]
            .iter()
            .for_each(|&e| rec.add(e, &Gradients::default()));
        let mean = gathers.iter().sum::<V>() / 9.0;
        assert!((rec.e - mean).abs().max_element() < 1e-6);
        let y: Vec<f64> = gathers.iter().map(|&e| luminance(e) as f64).collect();
        let my = y.iter().sum::<f64>() / 9.0;
        let var = y.iter().map(|v| (v - my).powi(2)).sum::<f64>() / 8.0;
        assert!((rec.y.variance() - var).abs() < 1e-9 * var.max(1.0));

        let at = |i: f32| V::new(i * 100.0, 0.0, 0.0);
        let make = |i: f32, es: &[f32], pixels: f32| {
            let mut r = Record::new(at(i), V::Z, V::splat(es[0]), 1.0, 0.01, 0.3);
            es[1..]
                .iter()
                .for_each(|&e| r.add(V::splat(e), &Gradients::default()));
            Record { pixels, ..r }
        };
        let mut cache = IrradianceCache::new(0.3);
        cache.extend([
            make(0.0, &[1.0, 1.1], 4.0),
            make(1.0, &[0.0, 2.0], 1.0),
            make(2.0, &[0.5], 1.0),
            make(3.0, &[0.0, 2.0].repeat(32), 16.0),
            make(4.0, &[1.0, 1.1], 16.0),
        ]);
        // Spreads 0.005, 2, -, 64/63, 0.005: s² = (0.01 + 2 + 64/63) / 4 = 0.756; gains
        // s²/6·4 = 0.504, s²/6 = 0.126, s²/2 = 0.378 (one gather), 0 (64), s²/6·16 = 2.017.
        let s2 = (0.01 + 2.0 + 64.0 / 63.0) / 4.0;
        assert!((cache.gather_spread().unwrap() - s2).abs() < 1e-6);
        assert_eq!(cache.worth_refining(1.0), vec![4]);
        assert_eq!(cache.worth_refining(0.4), vec![0, 4]);
        assert_eq!(cache.worth_refining(0.3), vec![0, 2, 4]);
        assert_eq!(cache.worth_refining(0.1), vec![0, 1, 2, 4]);
        assert_eq!(cache.worth_refining(0.0), vec![0, 1, 2, 4]);
        assert_eq!(cache.gathers(), 2 + 2 + 1 + 64 + 2);
        // Records of one gather and no spread known: the sampled ones (every
        // SPREAD_SAMPLE-th) first, whatever the threshold; once they have their second
        // gathers, the rest by the spread they give.
        let mut fresh = IrradianceCache::new(0.3);
        fresh.extend((0..2 * SPREAD_SAMPLE).map(|i| make(i as f32, &[0.5], 1.0)));
        assert_eq!(fresh.gather_spread(), None);
        assert_eq!(fresh.worth_refining(0.0), vec![0, SPREAD_SAMPLE]);
        fresh.add(0, V::splat(0.7), &Gradients::default());
        fresh.add(SPREAD_SAMPLE, V::splat(0.3), &Gradients::default());
        // Each sampled record's spread of two gathers is d²/2; s² is their mean.
        let s2 = fresh.gather_spread().unwrap();
        let d = |v: f32| (luminance(V::splat(v)) - luminance(V::splat(0.5))) as f64;
        let expected = (d(0.7).powi(2) / 2.0 + d(0.3).powi(2) / 2.0) / 2.0;
        assert!((s2 - expected).abs() < 1e-7, "{s2} against {expected}");
        assert!(fresh.worth_refining(s2 / 2.0).is_empty());
        assert_eq!(
            fresh.worth_refining(s2 / 2.0 * 0.99).len(),
            2 * SPREAD_SAMPLE - 2
        );
        // A dim lobe shows less of a record's error: at half, a quarter of the gain (alone,
        // its spread is the mean: 0.005/6·16/4).
        let mut dim = IrradianceCache::new(0.3);
        dim.extend([Record {
            lobe: 0.5,
            ..make(4.0, &[1.0, 1.1], 16.0)
        }]);
        assert!(dim.worth_refining(0.003).len() == 1 && dim.worth_refining(0.004).is_empty());
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
        // Its reach a·R = 0.025 is 2.5 footprints: a disc of π·2.5² pixels.
        let rec = Record::new(V::ZERO, V::Z, V::ONE, 0.05, 0.01, 0.5);
        assert!((rec.pixels - PI * 6.25).abs() < 1e-4, "{}", rec.pixels);
    }
}
