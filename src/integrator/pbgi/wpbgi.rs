//! WPBGI's glossy gather (000 §3.2–3.3) for what rough specular lobes reflect (rough
//! metals, glossy coats, rough dielectrics): the cut into the adaptive micro-buffer
//! (refined in rounds by the light importance when it is on) in a frame turned so that
//! ω_o lies in its xz-plane, far nodes sending their wavelet radiance (`glossy.rs`), then
//! the wavelet BRDF × radiance product with the BRDF's table, which holds the upper
//! hemisphere only. A rough dielectric's transmission keeps its exact lobe rays: the
//! point cloud holds no light inside a glass.

use super::amb::BRDF_LEVELS;
use super::brdf_table::{BrdfTable, RES, THRESHOLD};
use super::cut::Fill;
use super::surface::Surface;
use super::{PbgiIntegrator, Scratch, Strata, SCRATCH};
use crate::integrator::Scene;
use crate::material::{Bsdf, Frame};
use crate::trace::Tracer;
use glam::Vec3A as V;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::{Arc, Mutex, PoisonError};

/// How a glossy receiver takes its indirect glossy light (`--pbgi-glossy-bounce`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum GlossyBounce {
    /// Exact rays sampled from its lobes.
    Rays,
    /// WPBGI: the cut into the adaptive micro-buffer and the wavelet BRDF product, for
    /// the reflected light (a dielectric's transmission keeps its rays).
    Wavelet,
    /// WPBGI's gathers kept as radiance records shared between pixels (002 §4.3), each
    /// sample taking its own BRDF product with them; a receiver no record covers gathers
    /// as `wavelet` does.
    Cache,
}

/// One WPBGI gather's incident light, in the frame turned so that ω_o lies in its
/// xz-plane.
pub(super) struct Incident {
    pub table: Arc<BrdfTable>,
    /// Haar-transformed faces ([`super::amb::Amb::faces`]).
    pub faces: Vec<Vec<glam::Vec3>>,
    pub theta_o: f32,
    /// The leaves' harmonic mean distance to what they saw.
    pub depth: f32,
}

/// BRDF tables built on first use, one per distinct reflecting lobe.
#[derive(Default)]
pub struct Tables(Mutex<Vec<([u32; 18], Arc<BrdfTable>)>>);

impl Tables {
    fn get(&self, g: &Bsdf, threshold: f32) -> Arc<BrdfTable> {
        let key = g.glossy_key();
        let mut list = self.0.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some((_, t)) = list.iter().find(|(k, _)| *k == key) {
            return t.clone();
        }
        let t = Arc::new(BrdfTable::new(g, threshold));
        list.push((key, t.clone()));
        t
    }

    /// Tables built and their kept coefficients.
    pub fn sizes(&self) -> (usize, usize) {
        let list = self.0.lock().unwrap_or_else(PoisonError::into_inner);
        (list.len(), list.iter().map(|(_, t)| t.coefficients()).sum())
    }
}

/// The light importance's γ (`--pbgi-light-importance`): 0, off. On the showroom at
/// 20 s, 000 §3.2's "typically 1" had 1.40× the squared error of the BRDF alone, 0.3
/// 1.07×, and splitting wherever any light arrived 1.15× (docs/pbgi.md).
pub const LIGHT_GAMMA: f32 = 0.0;

/// Whether WPBGI gathers this receiver's reflected glossy light: it has rough lobes (a
/// rough dielectric's transmission keeps its lobe rays).
pub(super) fn gathers_wavelets(s: &Surface) -> bool {
    s.has_rough_lobes()
}

impl PbgiIntegrator {
    /// The receiver's indirect light through its rough specular lobes, by WPBGI.
    pub(super) fn gather_wavelet(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        s: &Surface,
        strata: Strata,
    ) -> V {
        let i = self.gather_incident(scene, tr, s, strata);
        V::from(i.table.product(i.theta_o, &i.faces))
    }

    /// The table of the receiver's reflecting lobe.
    pub(super) fn table_of(&self, s: &Surface) -> Arc<BrdfTable> {
        let threshold = self.settings.brdf_threshold.unwrap_or(THRESHOLD);
        self.tables.get(&s.glossy(), threshold)
    }

    /// The incident light of one WPBGI gather at the receiver.
    pub(super) fn gather_incident(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        s: &Surface,
        strata: Strata,
    ) -> Incident {
        let table = self.table_of(s);
        let theta_o = s.wo_l.z.clamp(-1.0, 1.0).acos();
        let frame = turned_frame(s);
        let turned = Surface { frame, ..*s };
        let gamma = self.settings.light_gamma.unwrap_or(LIGHT_GAMMA);
        let base = self.settings.resolution;
        SCRATCH.with_borrow_mut(|sc| {
            // γ = 0: no light importance, so the BRDF refines the whole way at once.
            let deepest = if gamma > 0.0 {
                base << BRDF_LEVELS
            } else {
                RES
            };
            sc.amb.init(base, |f, r, x, y| {
                r < deepest && table.varies(theta_o, f, r, x, y)
            });
            self.leaf_rays(sc, &frame, s, 0, strata);
            self.fill_texels(scene, tr, &turned, None, sc, strata, Fill::Adaptive);
            let mut incident = sc.amb.resolve();
            let light = (gamma, self.settings.rays());
            let brdf = |f, r, x, y| table.varies(theta_o, f, r, x, y);
            while let Some((first, nodes)) = (gamma > 0.0)
                .then(|| sc.amb.refine(&incident, light, brdf))
                .flatten()
            {
                self.leaf_rays(sc, &frame, s, first, strata);
                self.refill_leaves(scene, tr, &turned, sc, strata, &nodes);
                incident = sc.amb.resolve();
            }
            self.tally
                .amb_leaves
                .fetch_add(sc.amb.leaf_count() as u64, Relaxed);
            self.tally
                .light_splits
                .fetch_add(sc.amb.light_splits, Relaxed);
            self.tally.wavelet_gathers.fetch_add(1, Relaxed);
            Incident {
                faces: sc.amb.faces(&incident),
                depth: sc.amb.harmonic_depth(),
                table: table.clone(),
                theta_o,
            }
        })
    }

    /// The rays of the adaptive micro-buffer's leaves from `first` on, in world space,
    /// into `sc.rays`.
    fn leaf_rays(
        &self,
        sc: &mut Scratch,
        frame: &Frame,
        s: &Surface,
        first: usize,
        strata: Strata,
    ) {
        sc.rays.clear();
        let rays = sc.amb.rays(first, |k| strata.jitter(k));
        sc.rays
            .extend(rays.into_iter().filter_map(|(k, local, weight)| {
                let w = frame.to_world(V::from(local)).normalize();
                (w.dot(s.n) > 0.0).then_some((k, w, weight))
            }));
    }
}

/// The receiver's frame turned about its normal so that ω_o lies in the xz-plane.
pub(super) fn turned_frame(s: &Surface) -> Frame {
    let wo = s.frame.to_world(s.wo_l);
    let tangent = wo - s.n * wo.dot(s.n);
    let t = if tangent.length_squared() > 1e-12 {
        tangent.normalize()
    } else {
        s.frame.t
    };
    Frame {
        t,
        b: s.n.cross(t),
        n: s.n,
    }
}
