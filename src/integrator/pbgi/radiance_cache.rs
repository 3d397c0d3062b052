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
        let light: usize = self.light.iter().map(|l| l.coefs.capacity() * 12).sum();
        self.records.bytes() + light as u64
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
}
