//! FPBGI's receiver clusters (003 ch. 3): the receivers of one tile grouped by k-means on
//! position and normal, D(x, c) = |p_x − p_c|² + α·|n_x − n_c|² (Cohen-Steiner et al. as
//! cited there). α is the squared diagonal of the receivers' box: the thesis's α is a
//! length multiplying a unitless term (NOTES-002-003 B.2), and squaring it keeps D an area.

use glam::Vec3A as V;

/// One cluster: its members (indices into the receivers) and the active receiver x_C,
/// the member nearest the final centre.
#[derive(Clone, Debug, PartialEq)]
pub struct Cluster {
    pub active: usize,
    pub members: Vec<usize>,
}

/// k-means iterations (the thesis does not give its count).
const ITERATIONS: usize = 8;

/// Groups receivers at `p` with unit normals `n` into at most `k` clusters. Deterministic:
/// the first centres are receivers spread evenly through the list (tiles list pixels in
/// rows, so they spread over the tile). k ≥ the receiver count gives one cluster each.
pub fn kmeans(p: &[V], n: &[V], k: usize) -> Vec<Cluster> {
    let count = p.len();
    let k = k.clamp(1, count.max(1));
    if count == 0 {
        return Vec::new();
    }
    let alpha = alpha(p);
    let mut centres: Vec<(V, V)> = (0..k)
        .map(|j| {
            let i = j * count / k;
            (p[i], n[i])
        })
        .collect();
    let mut label = vec![0usize; count];
    for _ in 0..ITERATIONS {
        for (i, l) in label.iter_mut().enumerate() {
            *l = nearest(&centres, p[i], n[i], alpha);
        }
        let mut sums = vec![(V::ZERO, V::ZERO, 0u32); k];
        for (i, &l) in label.iter().enumerate() {
            sums[l].0 += p[i];
            sums[l].1 += n[i];
            sums[l].2 += 1;
        }
        for (c, (sp, sn, m)) in centres.iter_mut().zip(sums) {
            if m > 0 {
                *c = (sp / m as f32, sn.normalize_or(c.1));
            }
        }
    }
    let mut members = vec![Vec::new(); k];
    for (i, &l) in label.iter().enumerate() {
        members[l].push(i);
    }
    members
        .into_iter()
        .zip(centres)
        .filter(|(m, _)| !m.is_empty())
        .map(|(members, centre)| {
            // The first of equals: members are in receiver order.
            let active = *members
                .iter()
                .min_by(|&&a, &&b| {
                    distance(centre, p[a], n[a], alpha)
                        .total_cmp(&distance(centre, p[b], n[b], alpha))
                })
                .expect("a non-empty cluster");
            Cluster { active, members }
        })
        .collect()
}

/// k-means's α: the squared diagonal of the receivers' box (`p` non-empty).
fn alpha(p: &[V]) -> f32 {
    let (lo, hi) = p
        .iter()
        .fold((p[0], p[0]), |(lo, hi), &q| (lo.min(q), hi.max(q)));
    (hi - lo).length_squared()
}

fn distance((pc, nc): (V, V), p: V, n: V, alpha: f32) -> f32 {
    (p - pc).length_squared() + alpha * (n - nc).length_squared()
}

fn nearest(centres: &[(V, V)], p: V, n: V, alpha: f32) -> usize {
    let mut best = (f32::INFINITY, 0);
    for (j, &c) in centres.iter().enumerate() {
        let d = distance(c, p, n, alpha);
        if d < best.0 {
            best = (d, j);
        }
    }
    best.1
}

/// Σ D(x, centre of x's cluster), the objective k-means lowers (for tests).
#[cfg(test)]
fn objective(p: &[V], n: &[V], clusters: &[Cluster]) -> f32 {
    let alpha = alpha(p);
    clusters
        .iter()
        .map(|c| {
            let m = c.members.len() as f32;
            let pc = c.members.iter().map(|&i| p[i]).sum::<V>() / m;
            let nc = c
                .members
                .iter()
                .map(|&i| n[i])
                .sum::<V>()
                .normalize_or_zero();
            c.members
                .iter()
                .map(|&i| distance((pc, nc), p[i], n[i], alpha))
                .sum::<f32>()
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_rng::TestRng;

    fn receivers(seed: u64, count: usize) -> (Vec<V>, Vec<V>) {
        let mut rng = TestRng::new(seed);
        // Two walls meeting at a corner: positions on both, normals per wall.
        (0..count)
            .map(|i| {
                let (a, b) = (rng.f32(), rng.f32());
                if i % 3 == 0 {
                    (V::new(0.0, a, b), V::X)
                } else {
                    (V::new(a, b, 0.0), V::Z)
                }
            })
            .unzip()
    }

    #[test]
    fn clusters_partition_the_receivers_and_singletons_come_from_k_at_least_n() {
        let (p, n) = receivers(1, 256);
        for k in [1, 7, 25, 100] {
            let c = kmeans(&p, &n, k);
            assert!(c.len() <= k);
            let mut seen: Vec<usize> = c.iter().flat_map(|c| c.members.clone()).collect();
            seen.sort_unstable();
            assert_eq!(seen, (0..256).collect::<Vec<_>>(), "k {k}");
            assert!(c.iter().all(|c| c.members.contains(&c.active)));
        }
        let c = kmeans(&p, &n, 256);
        assert_eq!(c.len(), 256);
        assert!(c.iter().all(|c| c.members == [c.active]));
        assert!(kmeans(&[], &[], 5).is_empty());
    }

    #[test]
    fn clusters_do_not_mix_the_two_walls_and_beat_one_cluster() {
        let (p, n) = receivers(2, 300);
        let c = kmeans(&p, &n, 10);
        for cl in &c {
            let first = n[cl.members[0]];
            assert!(
                cl.members.iter().all(|&i| n[i] == first),
                "a cluster spans both walls"
            );
        }
        let one = kmeans(&p, &n, 1);
        assert!(objective(&p, &n, &c) < 0.5 * objective(&p, &n, &one));
    }
}
