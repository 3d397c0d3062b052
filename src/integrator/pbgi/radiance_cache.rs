//! Seed 002's radiance cache (§4.3) for WPBGI's glossy receivers: a gather's incident
//! light kept as Haar coefficients at a record shared between the pixels around it, each
//! sample taking its own wavelet BRDF product with it (002 eq. 20).
//!
//! The records are the irradiance cache's (`cache`), placed and refined the same way, with
//! the incident light beside them on the BRDF table's support. Deviations from 002, whose
//! records hold light for every ω_o over a uniform half-cube of fixed resolution:
//! - a record keeps the adaptive micro-buffer of the ω_o it was gathered at, in the frame
//!   turned to put that ω_o in its xz-plane, so it covers receivers whose outgoing
//!   direction and normal are within the lobe's width of its own (`Record::turn`, `wo`);
//!   a receiver takes the product at its own elevation of ω_o, in the record's frame;
//! - a record's reach is the harmonic mean distance its leaves saw times the lobe's width,
//!   as a move of d shifts what lies at distance D by d/D; 002 reads the best single point.

use super::brdf_table::BrdfTable;
use super::irradiance_cache::{IrradianceCache, Record};
use super::microbuffer::Gradients;
use super::wpbgi::Incident;
use glam::{Vec3, Vec3A as V};
use std::sync::Arc;

/// The smallest cos θ_o a pixel's length on the surface is taken at.
const MIN_COS: f32 = 0.2;

/// A record's light: the mean of its gathers on its table's support.
#[derive(Default)]
pub struct Light {
    table: Option<Arc<BrdfTable>>,
    coefs: Vec<Vec3>,
    gathers: u32,
}

impl Light {
    /// Takes another gather into the mean and returns its reflected radiance at its own
    /// ω_o; None, and the gather left out, when it is not finite.
    pub fn add(&mut self, inc: &Incident) -> Option<V> {
        let e = V::from(inc.table.product(inc.theta_o, &inc.faces));
        let coefs = inc.table.on_support(&inc.faces);
        if !(e.is_finite() && coefs.iter().all(|c| c.is_finite())) {
            return None;
        }
        self.gathers += 1;
        let share = 1.0 / self.gathers as f32;
        self.coefs.resize(coefs.len(), Vec3::ZERO);
        for (m, c) in self.coefs.iter_mut().zip(coefs) {
            *m += (c - *m) * share;
        }
        self.table = Some(inc.table.clone());
        Some(e)
    }

    /// Bytes its coefficients hold.
    pub fn bytes(&self) -> u64 {
        (self.coefs.capacity() * size_of::<Vec3>()) as u64
    }
}

pub struct RadianceCache {
    pub records: IrradianceCache,
    light: Vec<Light>,
}

impl RadianceCache {
    pub fn new(a: f32) -> RadianceCache {
        RadianceCache {
            records: IrradianceCache::new(a),
            light: Vec::new(),
        }
    }

    /// A record at receiver point `p`, normal `n`, outgoing direction `wo` (world space)
    /// of a gather reflecting `e` there whose leaves saw things at harmonic mean distance
    /// `depth`, the lobe's α; `footprint` a pixel's width at p across the view. Its reach
    /// is clamped by the pixel's length on the surface, footprint / cos θ_o (up to 5×):
    /// seen at a grazing angle, the next pixel's hit lies that far away.
    #[allow(clippy::too_many_arguments)]
    pub fn record(
        p: V,
        n: V,
        wo: V,
        e: V,
        depth: f32,
        alpha: f32,
        footprint: f32,
        a: f32,
    ) -> Record {
        let width = 2.0 * alpha;
        let along = footprint / wo.dot(n).max(MIN_COS);
        let rec = Record::new(p, n, e, depth * width, along, a);
        Record {
            turn: width * width,
            wo,
            ..rec
        }
    }

    /// Adds records with their light, in order.
    pub fn extend(&mut self, found: impl IntoIterator<Item = (Record, Light)>) {
        for (rec, light) in found {
            let before = self.records.len();
            self.records.extend([rec]);
            if self.records.len() > before {
                self.light.push(light);
            }
        }
    }

    /// Another gather for record `id`.
    pub fn add(&mut self, id: usize, inc: &Incident) {
        if let Some(e) = self.light[id].add(inc) {
            self.records.add(id, e, &Gradients::default());
        }
    }

    /// The reflected radiance at a receiver at `x` with normal `m`, outgoing direction
    /// `wo` and BRDF table `table`: the weighted mean of the covering records' products at
    /// the receiver's elevation of ω_o. None when no record of that table covers it.
    pub fn lookup(&self, x: V, m: V, wo: V, table: &Arc<BrdfTable>) -> Option<V> {
        let theta_o = wo.dot(m).clamp(-1.0, 1.0).acos();
        let (mut sum, mut weight) = (V::ZERO, 0.0f32);
        self.records.covering(x, m, wo, |id, w| {
            let light = &self.light[id];
            if light.table.as_ref().is_some_and(|t| Arc::ptr_eq(t, table)) {
                sum += V::from(table.product_on(theta_o, &light.coefs)) * w;
                weight += w;
            }
        });
        (weight > 0.0).then(|| sum / weight)
    }

    /// Coefficients a record keeps, on average.
    pub fn coefficients(&self) -> usize {
        self.light.iter().map(|l| l.coefs.len()).sum::<usize>() / self.light.len().max(1)
    }

    /// Bytes held: the records and their light.
    pub fn bytes(&self) -> u64 {
        let light: u64 = self.light.iter().map(Light::bytes).sum();
        self.records.bytes() + light
    }
}

#[cfg(test)]
mod tests {
    use super::super::brdf_table::tests::{gold, random_faces};
    use super::super::brdf_table::THRESHOLD;
    use super::*;

    const A: f32 = 0.3;
    const ALPHA: f32 = 0.1;
    const THETA: f32 = 0.5;

    fn table() -> Arc<BrdfTable> {
        Arc::new(BrdfTable::new(&gold(ALPHA), THRESHOLD))
    }

    fn gather(table: &Arc<BrdfTable>, seed: u64) -> Incident {
        Incident {
            table: table.clone(),
            faces: random_faces(seed),
            theta_o: THETA,
            depth: 2.0,
        }
    }

    fn wo_at(theta: f32) -> V {
        V::new(theta.sin(), 0.0, theta.cos())
    }

    /// A record at the origin, normal +z, ω_o at elevation THETA, of `gathers` gathers;
    /// its reach R is the depth 2 times the lobe's width 2α, 0.4 (a pixel 0.1 wide).
    fn cache_of(gathers: &[Incident]) -> RadianceCache {
        let mut cache = RadianceCache::new(A);
        let mut light = Light::default();
        let e = light.add(&gathers[0]).unwrap();
        let rec = RadianceCache::record(V::ZERO, V::Z, wo_at(THETA), e, 2.0, ALPHA, 0.1, A);
        cache.extend([(rec, light)]);
        for g in &gathers[1..] {
            cache.add(0, g);
        }
        cache
    }

    /// At its own point, normal and ω_o a record gives back the product with the mean of
    /// its gathers' light: the mean of their products, since the product is linear.
    #[test]
    fn a_record_gives_back_its_gathers_mean_reflection() {
        let table = table();
        let gathers = [gather(&table, 1), gather(&table, 2), gather(&table, 3)];
        let cache = cache_of(&gathers);
        let mean: Vec3 = gathers
            .iter()
            .map(|g| table.product(THETA, &g.faces))
            .sum::<Vec3>()
            / 3.0;
        let got = Vec3::from(cache.lookup(V::ZERO, V::Z, wo_at(THETA), &table).unwrap());
        let scale = mean.abs().max_element();
        assert!(
            (got - mean).abs().max_element() < 1e-4 * scale,
            "{got} against {mean}"
        );
        assert_eq!(cache.records.gathers(), 3);
    }

    /// A record covers a receiver while its distance over R plus the turn of its normal
    /// or of its ω_o, √((1 − cos) / (2α)²), stays below a: a move of 0.1 (not 0.14), a
    /// normal or ω_o turned by 0.07 rad (not 0.1; an irradiance record still covers a
    /// normal turned by 0.4), and only receivers of its own BRDF table.
    #[test]
    fn a_record_covers_receivers_within_its_lobes_width() {
        let table = table();
        let cache = cache_of(&[gather(&table, 1)]);
        let covers = |x: V, m: V, wo: V| cache.lookup(x, m, wo, &table).is_some();
        let wo = wo_at(THETA);
        assert!(covers(V::new(0.0, 0.1, 0.0), V::Z, wo));
        assert!(!covers(V::new(0.0, 0.14, 0.0), V::Z, wo));
        let tilted = |d: f32| V::new(0.0, d.sin(), d.cos());
        assert!(covers(V::ZERO, tilted(0.07), wo));
        assert!(!covers(V::ZERO, tilted(0.1), wo));
        assert!(covers(V::ZERO, V::Z, wo_at(THETA + 0.07)));
        assert!(!covers(V::ZERO, V::Z, wo_at(THETA + 0.1)));
        let other = Arc::new(BrdfTable::new(&gold(ALPHA), THRESHOLD));
        assert!(cache.lookup(V::ZERO, V::Z, wo, &other).is_none());
        let irradiance = Record::new(V::ZERO, V::Z, V::ONE, 0.4, 0.1, A);
        assert!(
            super::super::irradiance_cache::weight(&irradiance, A, V::ZERO, tilted(0.4), wo)
                .is_some()
        );
    }

    /// A receiver two records cover takes the mean of their products weighted by
    /// 1/ε − 1/a (the irradiance cache's weight): between the two, nearer the nearer.
    #[test]
    fn covering_records_blend_by_their_weights() {
        let table = table();
        let (g1, g2) = (gather(&table, 1), gather(&table, 5));
        let wo = wo_at(THETA);
        let mut cache = RadianceCache::new(A);
        let mut records = Vec::new();
        for (x, g) in [(0.0, &g1), (0.06, &g2)] {
            let mut light = Light::default();
            let e = light.add(g).unwrap();
            let p = V::new(x, 0.0, 0.0);
            let rec = RadianceCache::record(p, V::Z, wo, e, 2.0, ALPHA, 0.1, A);
            records.push((rec, table.product(THETA, &g.faces)));
            cache.extend([(rec, light)]);
        }
        let x = V::new(0.02, 0.0, 0.0);
        let w: Vec<f32> = records
            .iter()
            .map(|(r, _)| super::super::irradiance_cache::weight(r, A, x, V::Z, wo).unwrap())
            .collect();
        assert!(w[0] > w[1] && w[1] > 0.0, "{w:?}");
        let want = (records[0].1 * w[0] + records[1].1 * w[1]) / (w[0] + w[1]);
        let got = Vec3::from(cache.lookup(x, V::Z, wo, &table).unwrap());
        let scale = want.abs().max_element();
        assert!(
            (got - want).abs().max_element() < 1e-4 * scale,
            "{got} against {want}"
        );
    }

    /// A record's reach is at least a pixel's length on the surface over a: its width
    /// across the view over cos θ_o, down to cos 0.2 (5 pixels). A gather that saw things
    /// close by (a reach of 2α × 0.01) still covers its neighbouring pixels' receivers,
    /// farther the more grazing the view.
    #[test]
    fn a_records_reach_is_at_least_a_pixels_length_on_the_surface() {
        let footprint = 0.1;
        for (theta, cos) in [(0.0f32, 1.0f32), (1.2, 1.2f32.cos()), (1.5, MIN_COS)] {
            let wo = wo_at(theta);
            let rec = RadianceCache::record(V::ZERO, V::Z, wo, V::ONE, 0.01, ALPHA, footprint, A);
            let reach = footprint / cos / A;
            assert!(
                (rec.r / reach - 1.0).abs() < 1e-5,
                "θ {theta}: {} against {reach}",
                rec.r
            );
            let w = |d: f32| {
                super::super::irradiance_cache::weight(&rec, A, V::new(d, 0.0, 0.0), V::Z, wo)
            };
            assert!(w(0.9 * A * reach).is_some() && w(1.1 * A * reach).is_none());
        }
    }
}
