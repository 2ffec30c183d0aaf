//! Exact ray-cast visibility against triangle meshes: a bounding volume
//! hierarchy (BVH) and any-hit shadow rays. The reference of `Relight`'s
//! imperfect shadow maps ([`crate::relight::reference`]).
//!
//! The BVH is binary, split at the median centroid along the longest axis
//! of each node's centroid bounds, with up to [`Bvh::LEAF`] triangles per
//! leaf. A ray is tested against a node's box with the slab method and
//! against triangles with the Möller–Trumbore test, in f64.

use depthgraph_graph::value::Mesh;
use glam::DVec3;

/// An axis-aligned box.
#[derive(Debug, Clone, Copy)]
struct Aabb {
    lo: DVec3,
    hi: DVec3,
}

impl Aabb {
    const EMPTY: Aabb = Aabb {
        lo: DVec3::splat(f64::INFINITY),
        hi: DVec3::splat(f64::NEG_INFINITY),
    };

    fn grow(&mut self, p: DVec3) {
        self.lo = self.lo.min(p);
        self.hi = self.hi.max(p);
    }

    /// Whether the ray `o + t d` (`inv = 1 / d` per component) meets the
    /// box for some `t` in `[t0, t1]` (slab method; IEEE infinities for
    /// zero components).
    #[inline]
    fn hit(&self, o: DVec3, inv: DVec3, t0: f64, t1: f64) -> bool {
        let a = (self.lo - o) * inv;
        let b = (self.hi - o) * inv;
        let (near, far) = (a.min(b), a.max(b));
        let t_enter = near.max_element().max(t0);
        let t_exit = far.min_element().min(t1);
        // NaN (0 * inf on a slab's plane) fails the test: conservative
        // enough for a box, the triangle test decides
        t_enter <= t_exit || (t_enter.is_nan() || t_exit.is_nan())
    }
}

#[derive(Debug, Clone, Copy)]
struct Node {
    bounds: Aabb,
    /// Leaf: first triangle in `order`; inner: index of the left child
    /// (the right one follows its subtree).
    first: u32,
    /// Leaf: triangle count (> 0); inner: 0, and `right` is the right child.
    count: u32,
    right: u32,
}

/// A BVH over the triangles of a mesh (module docs).
#[derive(Debug, Clone)]
pub struct Bvh {
    tris: Vec<[DVec3; 3]>,
    nodes: Vec<Node>,
}

impl Bvh {
    /// Triangles per leaf, at most.
    pub const LEAF: usize = 4;

    /// The BVH of `mesh`'s triangles (those with an index out of range
    /// are skipped).
    pub fn new(mesh: &Mesh) -> Self {
        let v = |i: u32| {
            mesh.positions
                .get(i as usize)
                .map(|p| DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64))
        };
        let tris: Vec<[DVec3; 3]> = mesh
            .triangles
            .iter()
            .filter_map(|t| Some([v(t[0])?, v(t[1])?, v(t[2])?]))
            .collect();
        Self::from_triangles(tris)
    }

    /// The BVH of the given triangles.
    pub fn from_triangles(mut tris: Vec<[DVec3; 3]>) -> Self {
        let mut nodes = Vec::with_capacity(2 * tris.len() / Self::LEAF + 1);
        if !tris.is_empty() {
            let n = tris.len();
            build(&mut tris, 0, n, &mut nodes);
        }
        Self { tris, nodes }
    }

    /// Number of triangles.
    pub fn len(&self) -> usize {
        self.tris.len()
    }

    /// Whether there is no triangle.
    pub fn is_empty(&self) -> bool {
        self.tris.is_empty()
    }

    /// Whether the ray `o + t d`, `t in (t_min, t_max)`, meets a triangle.
    pub fn occluded(&self, o: DVec3, d: DVec3, t_min: f64, t_max: f64) -> bool {
        if self.nodes.is_empty() {
            return false;
        }
        let inv = d.recip();
        let mut stack = [0u32; 64];
        let mut top = 1usize;
        while top > 0 {
            top -= 1;
            let node = &self.nodes[stack[top] as usize];
            if !node.bounds.hit(o, inv, t_min, t_max) {
                continue;
            }
            if node.count > 0 {
                let (a, b) = (node.first as usize, (node.first + node.count) as usize);
                if self.tris[a..b]
                    .iter()
                    .any(|t| intersect(o, d, t).is_some_and(|s| s > t_min && s < t_max))
                {
                    return true;
                }
            } else if top + 2 <= stack.len() {
                stack[top] = node.first;
                stack[top + 1] = node.right;
                top += 2;
            }
        }
        false
    }
}

/// Builds the subtree of `tris[a..b]`, returns its node index.
fn build(tris: &mut [[DVec3; 3]], a: usize, b: usize, nodes: &mut Vec<Node>) -> u32 {
    let mut bounds = Aabb::EMPTY;
    let mut cb = Aabb::EMPTY;
    for t in &tris[a..b] {
        for p in t {
            bounds.grow(*p);
        }
        cb.grow((t[0] + t[1] + t[2]) / 3.0);
    }
    let idx = nodes.len() as u32;
    nodes.push(Node {
        bounds,
        first: a as u32,
        count: (b - a) as u32,
        right: 0,
    });
    if b - a <= Bvh::LEAF {
        return idx;
    }
    let ext = cb.hi - cb.lo;
    let axis = if ext.x >= ext.y && ext.x >= ext.z {
        0
    } else if ext.y >= ext.z {
        1
    } else {
        2
    };
    let mid = (b - a) / 2;
    let key = |t: &[DVec3; 3]| t[0][axis] + t[1][axis] + t[2][axis];
    tris[a..b].select_nth_unstable_by(mid, |x, y| key(x).total_cmp(&key(y)));
    let left = build(tris, a, a + mid, nodes);
    let right = build(tris, a + mid, b, nodes);
    nodes[idx as usize] = Node {
        bounds,
        first: left,
        count: 0,
        right,
    };
    idx
}

/// Möller–Trumbore: the ray parameter `t` where `o + t d` meets the
/// triangle (either side), `None` when it misses or is parallel.
#[inline]
fn intersect(o: DVec3, d: DVec3, t: &[DVec3; 3]) -> Option<f64> {
    let (e1, e2) = (t[1] - t[0], t[2] - t[0]);
    let p = d.cross(e2);
    let det = e1.dot(p);
    // guard: a parallel ray (or a degenerate triangle) has det ~ 0
    if det.abs() < 1e-18 {
        return None;
    }
    let inv = 1.0 / det;
    let s = o - t[0];
    let u = s.dot(p) * inv;
    if !(0.0..=1.0).contains(&u) {
        return None;
    }
    let q = s.cross(e1);
    let v = d.dot(q) * inv;
    if v < 0.0 || u + v > 1.0 {
        return None;
    }
    Some(e2.dot(q) * inv)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A random soup of triangles: the BVH's answer is the brute-force one
    /// for every ray.
    #[test]
    fn the_bvh_agrees_with_testing_every_triangle() {
        let mut rng = crate::kit::rng::SplitMix64(3);
        let mut r = || rng.next_f64() * 2.0 - 1.0;
        let tris: Vec<[DVec3; 3]> = (0..500)
            .map(|_| {
                let c = DVec3::new(r(), r(), r()) * 3.0;
                [
                    c + DVec3::new(r(), r(), r()) * 0.3,
                    c + DVec3::new(r(), r(), r()) * 0.3,
                    c + DVec3::new(r(), r(), r()) * 0.3,
                ]
            })
            .collect();
        let bvh = Bvh::from_triangles(tris.clone());
        assert_eq!(bvh.len(), 500);
        let (mut hits, mut n) = (0, 0);
        for _ in 0..2000 {
            let o = DVec3::new(r(), r(), r()) * 4.0;
            let d = DVec3::new(r(), r(), r()).normalize_or_zero();
            if d == DVec3::ZERO {
                continue;
            }
            let t_max = 2.0 + r();
            let brute = tris
                .iter()
                .any(|t| intersect(o, d, t).is_some_and(|s| s > 1e-9 && s < t_max));
            assert_eq!(bvh.occluded(o, d, 1e-9, t_max), brute, "{o} {d}");
            hits += brute as usize;
            n += 1;
        }
        // both answers occur often
        assert!(hits > 50 && hits < n - 50, "{hits} of {n}");
        // axis-parallel rays (zero direction components) too
        let unit = Bvh::from_triangles(vec![[DVec3::ZERO, DVec3::X, DVec3::Y]]);
        assert!(unit.occluded(DVec3::new(0.2, 0.2, 1.0), DVec3::NEG_Z, 0.0, 10.0));
        assert!(!unit.occluded(DVec3::new(0.8, 0.8, 1.0), DVec3::NEG_Z, 0.0, 10.0));
        assert!(!unit.occluded(DVec3::new(0.2, 0.2, 1.0), DVec3::Z, 0.0, 10.0));
        assert!(!Bvh::from_triangles(Vec::new()).occluded(DVec3::ZERO, DVec3::X, 0.0, 1.0));
    }
}
