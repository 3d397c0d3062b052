//! A glossy BRDF tabulated per outgoing direction as Haar-compressed cube maps (002 §4.2),
//! for WPBGI's wavelet BRDF × radiance product (000 §3.3).
//!
//! Each table entry is the hemicube of one ω_o in the local frame (z along the normal): the
//! +z face and the upper halves of the four side faces, `RES`² texels a face. A texel holds
//! ∫ f(ω_i, ω_o) cos θ_i dω_i over its solid angle (NOTES-002-003 A.5 leaves open where the
//! cosine and the texel's solid angle go; folded in here, the product with a radiance face
//! is a plain inner product, which Parseval carries over to the Haar coefficients). The
//! faces are transformed and truncated ([`Sparse::truncate`]).
//!
//! Deviation from 002: the BRDFs here are isotropic, so ω_o is tabulated by its elevation
//! alone, with ω_o in the local xz-plane (the receiver turns its frame to match). The four
//! nearest ω_o of 002's hemisphere grid become the two nearest elevations, interpolated
//! linearly.

use crate::material::Bsdf;
use crate::wavelet::{cube, haar, haar::Sparse};
use glam::{Vec3, Vec3A as V};
use rayon::prelude::*;

/// Texels per face side of the tables: the finest level the adaptive micro-buffer reaches.
pub const RES: usize = 64;
/// Elevations of ω_o tabulated, from 0 to [`THETA_MAX`].
const THETAS: usize = 32;
/// The last elevation tabulated: cos θ_o = 0.02 (beyond, the nearest entry is used).
const THETA_MAX: f32 = 1.550_79;
/// Sub-samples per texel side when integrating the BRDF over a texel.
const SUB: usize = 4;
/// Coefficients below this fraction of the face set's L² norm are dropped (002 §4.2's β,
/// relative here so that one value serves every roughness). It also sets how far the
/// adaptive micro-buffer refines: on the showroom 1e-3 made 1,150 leaves a gather and
/// 1e-2 440, the image's bias unchanged.
pub const THRESHOLD: f32 = 1e-2;

/// The faces of the hemicube, in [`cube::FACES`]' numbering (−z is never above).
const FACES: usize = 5;

/// One ω_o's faces and, per face and quadtree level, which cells hold a kept detail
/// coefficient in their subtree: where the BRDF varies inside a cell.
struct Entry {
    faces: Vec<Sparse<Vec3>>,
    /// The kept coefficients again, by their slot in the table's [`Support`].
    slots: Vec<(u32, Vec3)>,
    /// Per face, per level h = 1, 2, …, RES/2 (cells of RES/h texels): h² flags.
    varies: Vec<Vec<Vec<bool>>>,
}

pub struct BrdfTable {
    entries: Vec<Entry>,
    support: Support,
}

/// The coefficients some entry keeps, over all elevations: the only ones of an incident
/// light its products read, so a radiance record keeps these alone.
struct Support {
    /// Per coefficient of the FACES·RES² (face-major): its slot, or `u32::MAX`.
    slot: Vec<u32>,
    len: usize,
}

impl BrdfTable {
    /// Tabulates the BRDF `bsdf` (its lobes as `Bsdf::eval` gives them), truncating with
    /// `threshold` relative to each entry's L² norm.
    pub fn new(bsdf: &Bsdf, threshold: f32) -> BrdfTable {
        let mut entries: Vec<Entry> = (0..THETAS)
            .into_par_iter()
            .map(|i| Entry::new(bsdf, theta(i), threshold))
            .collect();
        let mut slot = vec![u32::MAX; FACES * RES * RES];
        let mut len = 0;
        for e in &mut entries {
            for (f, s) in e.faces.iter().enumerate() {
                for &(k, c) in &s.coefs {
                    let at = &mut slot[f * RES * RES + k as usize];
                    if *at == u32::MAX {
                        *at = len as u32;
                        len += 1;
                    }
                    e.slots.push((*at, c));
                }
            }
        }
        BrdfTable {
            entries,
            support: Support { slot, len },
        }
    }

    /// Incident radiance `faces` (as [`Self::product`] takes them) on the table's support.
    pub fn on_support(&self, faces: &[Vec<Vec3>]) -> Vec<Vec3> {
        let mut out = vec![Vec3::ZERO; self.support.len];
        for (k, &at) in self.support.slot.iter().enumerate() {
            if at != u32::MAX {
                out[at as usize] = faces[k / (RES * RES)][k % (RES * RES)];
            }
        }
        out
    }

    /// [`Self::product`] with incident radiance on the table's support.
    pub fn product_on(&self, theta_o: f32, coefs: &[Vec3]) -> Vec3 {
        let (a, b, t) = self.around(theta_o);
        let dot = |e: &Entry| -> Vec3 { e.slots.iter().map(|&(k, c)| c * coefs[k as usize]).sum() };
        dot(&self.entries[a]) * (1.0 - t) + dot(&self.entries[b]) * t
    }

    /// The two entries around elevation `theta_o` and the second's weight.
    fn around(&self, theta_o: f32) -> (usize, usize, f32) {
        let x = (theta_o.max(0.0) / THETA_MAX * (THETAS - 1) as f32).min((THETAS - 1) as f32);
        let i = (x as usize).min(THETAS - 2);
        (i, i + 1, x - i as f32)
    }

    /// Whether the BRDF at `theta_o` varies inside cell (x, y) of `face` at resolution
    /// `res` (the importance F_ρ of 000 §3.2, read from the table's own quadtree).
    pub fn varies(&self, theta_o: f32, face: usize, res: usize, x: usize, y: usize) -> bool {
        if res >= RES || face >= FACES {
            return false;
        }
        let level = res.trailing_zeros() as usize;
        let (a, b, _) = self.around(theta_o);
        [a, b]
            .iter()
            .any(|&e| self.entries[e].varies[face][level][y * res + x])
    }

    /// Σ_t f·cos·dω(t) L(t) over the hemicube: the product of the BRDF at `theta_o` and
    /// incident radiance `faces` (per face, RES² texels, Haar-transformed), taken on the
    /// kept coefficients.
    pub fn product(&self, theta_o: f32, faces: &[Vec<Vec3>]) -> Vec3 {
        let (a, b, t) = self.around(theta_o);
        let dot = |e: &Entry| -> Vec3 {
            e.faces
                .iter()
                .zip(faces)
                .map(|(s, l)| {
                    s.coefs
                        .iter()
                        .map(|&(k, c)| c * l[k as usize])
                        .sum::<Vec3>()
                })
                .sum()
        };
        dot(&self.entries[a]) * (1.0 - t) + dot(&self.entries[b]) * t
    }

    /// Coefficients kept over all entries (12 bytes each as RGB f32, plus a 4-byte index).
    pub fn coefficients(&self) -> usize {
        self.entries
            .iter()
            .flat_map(|e| &e.faces)
            .map(|s| s.coefs.len())
            .sum()
    }
}

/// Elevation of entry i.
fn theta(i: usize) -> f32 {
    THETA_MAX * i as f32 / (THETAS - 1) as f32
}

impl Entry {
    fn new(bsdf: &Bsdf, theta_o: f32, threshold: f32) -> Entry {
        let wo = V::new(theta_o.sin(), 0.0, theta_o.cos());
        let mut dense: Vec<Vec<Vec3>> = (0..FACES).map(|f| face_image(bsdf, wo, f)).collect();
        for d in &mut dense {
            haar::forward(d, RES);
        }
        let norm = dense
            .iter()
            .flatten()
            .map(|c| c.length_squared())
            .sum::<f32>();
        let cut = threshold * norm.sqrt();
        let faces: Vec<Sparse<Vec3>> = dense
            .iter()
            .map(|d| Sparse::truncate(d, RES, cut))
            .collect();
        let varies = faces.iter().map(varies_of).collect();
        Entry {
            faces,
            slots: Vec::new(),
            varies,
        }
    }
}

/// One face of ∫ f cos dω per texel, by SUB² points per texel on the unit-distance face
/// (where dω = dA / r³).
fn face_image(bsdf: &Bsdf, wo: V, face: usize) -> Vec<Vec3> {
    let (axis, u, v) = cube::FACES[face];
    let h = 2.0 / RES as f32;
    let da = (h / SUB as f32).powi(2);
    let mut out = vec![Vec3::ZERO; RES * RES];
    for y in 0..RES {
        for x in 0..RES {
            let mut sum = Vec3::ZERO;
            for j in 0..SUB {
                for i in 0..SUB {
                    let s = -1.0 + h * (x as f32 + (i as f32 + 0.5) / SUB as f32);
                    let t = -1.0 + h * (y as f32 + (j as f32 + 0.5) / SUB as f32);
                    let p = axis + u * s + v * t;
                    let r = p.length();
                    let wi = V::from(p / r);
                    if wi.z > 0.0 {
                        let f = Vec3::from(bsdf.eval(wo, wi).0);
                        sum += f * (wi.z * da / (r * r * r));
                    }
                }
            }
            out[y * RES + x] = sum;
        }
    }
    out
}

/// Per level h (h² cells of RES/h texels), whether a cell's subtree keeps a detail.
fn varies_of(s: &Sparse<Vec3>) -> Vec<Vec<bool>> {
    let levels = RES.trailing_zeros() as usize;
    let mut v: Vec<Vec<bool>> = (0..levels).map(|l| vec![false; 1 << (2 * l)]).collect();
    for &(k, _) in &s.coefs {
        let (row, col) = (k as usize / RES, k as usize % RES);
        if k == 0 {
            continue;
        }
        // The detail's level: the h with row or col in [h, 2h) and the other below 2h.
        let h = 1usize << row.max(col).ilog2();
        let (x, y) = (col % h, row % h);
        v[h.trailing_zeros() as usize][y * h + x] = true;
    }
    for l in (1..levels).rev() {
        let h = 1usize << l;
        for y in 0..h {
            for x in 0..h {
                if v[l][y * h + x] {
                    v[l - 1][(y / 2) * (h / 2) + x / 2] = true;
                }
            }
        }
    }
    v
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    pub(in super::super) fn gold(alpha: f32) -> Bsdf {
        Bsdf {
            f0: V::new(1.0, 0.78, 0.34),
            f90: V::ONE,
            alpha,
            eta: 1.5,
            ..Bsdf::lambert(V::ZERO)
        }
    }

    /// The product with a uniform radiance of 1 is the directional albedo: against a
    /// Monte Carlo estimate of ∫ f cos dω from the BRDF's own sampling.
    #[test]
    fn the_product_with_uniform_light_is_the_albedo() {
        let bsdf = gold(0.09);
        let table = BrdfTable::new(&bsdf, 0.0);
        let mut ones: Vec<Vec<Vec3>> = (0..FACES)
            .map(|f| {
                (0..RES * RES)
                    .map(|k| {
                        let upper = f == 4 || k / RES >= RES / 2;
                        if upper {
                            Vec3::ONE
                        } else {
                            Vec3::ZERO
                        }
                    })
                    .collect()
            })
            .collect();
        for f in &mut ones {
            haar::forward(f, RES);
        }
        let mut rng = crate::test_rng::TestRng::new(5);
        for i in [0, 10, 20] {
            let th = theta(i);
            let wo = V::new(th.sin(), 0.0, th.cos());
            let n = 200_000;
            let mut mc = V::ZERO;
            for _ in 0..n {
                if let Some(s) = bsdf.sample(wo, rng.f32(), [rng.f32(), rng.f32()]) {
                    mc += s.weight;
                }
            }
            let mc = Vec3::from(mc / n as f32);
            let got = table.product(th, &ones);
            let rel = ((got - mc) / mc).abs().max_element();
            assert!(rel < 0.01, "θ {th}: {got} against {mc}");
        }
    }

    /// Fewer coefficients as the threshold grows, and cells flagged as varying only where
    /// a coarser cell is flagged too.
    #[test]
    fn coefficients_fall_as_the_threshold_grows() {
        let bsdf = gold(0.04);
        let counts: Vec<usize> = [0.0, 1e-4, 1e-3, 1e-2]
            .iter()
            .map(|&t| BrdfTable::new(&bsdf, t).coefficients())
            .collect();
        assert!(counts.windows(2).all(|w| w[0] > w[1]), "{counts:?}");
        let table = BrdfTable::new(&bsdf, THRESHOLD);
        for e in &table.entries {
            for levels in &e.varies {
                for l in 1..levels.len() {
                    let h = 1 << l;
                    for k in 0..h * h {
                        let (x, y) = (k % h, k / h);
                        if levels[l][k] {
                            assert!(levels[l - 1][(y / 2) * (h / 2) + x / 2]);
                        }
                    }
                }
            }
        }
    }

    /// Random incident light on the hemicube's faces, Haar-transformed.
    pub(in super::super) fn random_faces(seed: u64) -> Vec<Vec<Vec3>> {
        let mut rng = crate::test_rng::TestRng::new(seed);
        (0..FACES)
            .map(|_| {
                let mut f: Vec<Vec3> = (0..RES * RES).map(|_| rng.v(1.0).into()).collect();
                haar::forward(&mut f, RES);
                f
            })
            .collect()
    }

    /// The support holds every coefficient a product reads: the product with the light
    /// kept on it is the product with the whole light, at every elevation.
    #[test]
    fn the_product_on_the_support_is_the_whole_product() {
        let table = BrdfTable::new(&gold(0.09), THRESHOLD);
        let faces = random_faces(7);
        let kept = table.on_support(&faces);
        assert!(kept.len() < FACES * RES * RES / 4, "{}", kept.len());
        for i in 0..4 * THETAS {
            let th = THETA_MAX * i as f32 / (4 * THETAS) as f32;
            let (whole, on) = (table.product(th, &faces), table.product_on(th, &kept));
            assert!(
                (whole - on).abs().max_element() <= 1e-5 * whole.abs().max_element(),
                "θ {th}: {whole} against {on}"
            );
        }
    }
}
