//! The walk down the paged tree: children in visiting order, page links, instance leaves.

use super::*;

/// The wide node `w`'s children whose lanes are set in `mask`, in the order a walk visits
/// them: the first is returned, the rest pushed on `stack` (as children of page `pid`,
/// or as the root of the child page they link to) so that they pop in order.
///
/// A closest-hit walk goes nearest first (equal distances: the higher lane first). An
/// any-hit walk goes first to the boxes the ray enters from outside, then to those it
/// starts inside (entry distance 0), each group from the highest lane down: a ray leaving
/// a surface rarely hits the surface's own neighbourhood, which nearest first would open
/// to the leaves first. On sponza's bounce rays this order was 3.0× faster than the
/// lanes' own order, itself 2.4× faster than nearest first.
#[inline(always)]
pub(super) fn visit_order(
    w: &Wide,
    enter: Vec4,
    mask: u32,
    any: bool,
    pid: u32,
    stack: &mut Stack,
) -> Option<(u32, f32)> {
    let entry = |c: u32, t: f32| match c & wide::KIND {
        wide::PAGE => (c & !wide::KIND, wide::WIDE, t),
        _ => (pid, c, t),
    };
    if mask & mask.wrapping_sub(1) == 0 {
        let lane = mask.trailing_zeros() as usize;
        return (mask != 0).then(|| (w.child[lane], enter[lane]));
    }
    let t = enter.to_array();
    let mut hits = [(0.0f32, 0u32); 4];
    let mut n = 0;
    let outside = match any {
        true => enter.cmpgt(Vec4::ZERO).bitmask() & mask,
        false => mask,
    };
    for mut group in [outside, mask & !outside] {
        while group != 0 {
            let lane = 31 - group.leading_zeros() as usize;
            group &= !(1 << lane);
            hits[n] = (t[lane], w.child[lane]);
            n += 1;
        }
    }
    if !any {
        for i in 1..n {
            let mut j = i;
            while j > 0 && hits[j].0 < hits[j - 1].0 {
                hits.swap(j, j - 1);
                j -= 1;
            }
        }
    }
    for &(t, c) in hits[1..n].iter().rev() {
        stack.push(entry(c, t));
    }
    Some((hits[0].1, hits[0].0))
}

/// The walk's stack: (page, entry as `Wide::child` codes it, box entry distance).
pub(super) type Stack = Vec<(u32, u32, f32)>;

/// One exact ray's walk: what stays the same through the world tree and the instances'
/// prototypes.
pub(super) struct Walk<'w> {
    pub(super) cache: &'w PageCache,
    pub(super) ray: &'w Ray,
    pub(super) any: bool,
}

impl Walk<'_> {
    /// Walks the four-wide tree under page `start`'s roots with `self.ray`, front to back,
    /// going on to the first child to visit without a trip through `stack`. With
    /// `INSTANCED`, an instance leaf is walked with `inner` as its stack; without (inside a
    /// prototype, where the converter writes no instance, or in an archive without
    /// instances) it is skipped. Kept apart from the cone's walk:
    /// with the cone's binary steps in, even unused, the trace bench's exact rays were
    /// 5–16% slower.
    #[inline(always)]
    pub(super) fn exact<const INSTANCED: bool>(
        &self,
        held: &mut Held,
        stack: &mut Stack,
        mut inner: Option<&mut Stack>,
        start: u32,
        on_tri: &mut impl FnMut(TriRef),
    ) -> bool {
        let (cache, any) = (self.cache, self.any);
        let lanes = Prep4::new(self.ray);
        let mut t_max = self.ray.t_max;
        stack.clear();
        let mut page: &Page = held.get(cache, start);
        // The child of `page` to walk next, as `Wide::child` codes it.
        let mut next = (!page.wide.is_empty()).then_some(wide::WIDE);
        let mut found = false;
        'walk: loop {
            let r = match next.take() {
                Some(r) => r,
                None => loop {
                    let Some((pid, r, tn)) = stack.pop() else {
                        break 'walk;
                    };
                    if tn <= t_max {
                        if page.id != pid {
                            page = held.get(cache, pid);
                        }
                        break r;
                    }
                },
            };
            let index = r & !wide::KIND;
            match r & wide::KIND {
                wide::LEAF if INSTANCED && index & wide::INSTANCE != 0 => {
                    let pid = page.id;
                    if self.enter(held, inner.as_deref_mut(), pid, index, &mut t_max, on_tri) {
                        found = true;
                        if any {
                            break 'walk;
                        }
                    }
                    page = held.get(cache, pid);
                }
                wide::LEAF => {
                    if lanes.leaf(page, index, &mut t_max, on_tri, any) {
                        found = true;
                        if any {
                            break 'walk;
                        }
                    }
                }
                wide::PAGE => {
                    page = held.get(cache, index);
                    if page.roots >= 2 && !page.wide.is_empty() {
                        next = Some(wide::WIDE);
                    }
                }
                _ => {
                    let Some(w) = page.wide.get(index as usize) else {
                        continue;
                    };
                    let (enter, mask) = lanes.hit(w, t_max);
                    next =
                        visit_order(w, enter, mask & w.used, any, page.id, stack).map(|(c, _)| c);
                }
            }
        }
        found
    }

    /// The walk of `exact` into the instance leaf `index` of page `pid`, out of its loop.
    #[inline(never)]
    pub(super) fn enter(
        &self,
        held: &mut Held,
        inner: Option<&mut Stack>,
        pid: u32,
        index: u32,
        t_max: &mut f32,
        on_tri: &mut dyn FnMut(TriRef),
    ) -> bool {
        let Some(inner) = inner else {
            return false;
        };
        match instance_at(held.get(self.cache, pid), index) {
            Some(inst) => self.instance(held, inner, inst, t_max, on_tri),
            None => false,
        }
    }

    /// Walks the prototype of instance `placed` (reached through the leaf `via`) with the
    /// ray moved into its object space (`Instance::ray_to_object`): hits go to `on_tri` at
    /// their world distance, tagged with the instance, and close `t_max`.
    #[inline(never)]
    pub(super) fn instance(
        &self,
        held: &mut Held,
        stack: &mut Stack,
        (placed, via): (Instance, u64),
        t_max: &mut f32,
        on_tri: &mut dyn FnMut(TriRef),
    ) -> bool {
        let (o, d, dt) = instance::ray_to_object(&placed, self.ray.o, self.ray.d);
        let local = Ray {
            o,
            d,
            t_max: *t_max - dt,
        };
        let walk = Walk {
            cache: self.cache,
            ray: &local,
            any: self.any,
        };
        let mut nearest = None;
        let mut tagged = |mut r: TriRef| {
            r.t += dt;
            r.instance = placed.number;
            r.via = via;
            nearest = Some(r.t);
            on_tri(r)
        };
        let found = walk.exact::<false>(held, stack, None, placed.page, &mut tagged);
        if let Some(t) = nearest {
            *t_max = t_max.min(t);
        }
        found
    }
}

/// The instance binary node `node` of `page` places and the node's global number, if it
/// is an instance leaf.
#[inline]
pub(super) fn instance_at(page: &Page, node: u32) -> Option<(Instance, u64)> {
    let via = page.first_node + (node & !wide::INSTANCE) as u64;
    Some((page.instance_of(via)?.clone(), via))
}

/// A stack entry whose kind is `EMPTY` (which no lane pushes) is a binary node of its page.
pub(super) const BINARY: u32 = wide::EMPTY;

/// Pushes the binary nodes `kids` of `page` that the ray meets before `t_max`, the nearer
/// last (popped first).
#[inline]
pub(super) fn push_pair(prep: &Prep, page: &Page, [l, r]: [u32; 2], t_max: f32, stack: &mut Stack) {
    let (Some(ln), Some(rn)) = (page.bvh.get(l as usize), page.bvh.get(r as usize)) else {
        return;
    };
    let id = page.id;
    match (prep.box_hit(ln, t_max), prep.box_hit(rn, t_max)) {
        (Some(a), Some(b)) => {
            let (near, far) = if a <= b {
                ((l, a), (r, b))
            } else {
                ((r, b), (l, a))
            };
            stack.push((id, BINARY | far.0, far.1));
            stack.push((id, BINARY | near.0, near.1));
        }
        (Some(a), None) => stack.push((id, BINARY | l, a)),
        (None, Some(b)) => stack.push((id, BINARY | r, b)),
        (None, None) => {}
    }
}

pub(super) fn inside(p: V, n: &TNode) -> bool {
    p.cmpge(V::from(n.lo)).all() && p.cmple(V::from(n.hi)).all()
}
