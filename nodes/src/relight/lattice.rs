//! Smooth shading terms evaluated on a lattice of pixels and interpolated
//! between them where that is safe (the scene-cached path's bounce, fill
//! and object irradiance, [`crate::relight::scene_cached`]).
//!
//! Indirect light varies over the distance to its sources, centimetres to
//! metres, far more slowly than the pixel grid: evaluating it at every
//! pixel repeats nearly the same sum of hundreds of VPLs. Interactive
//! instant radiosity evaluates such terms sparsely and reconstructs them
//! with a geometry-aware filter (the interleaved sampling of the
//! relighting paper's VPL renderer). Here a term is evaluated at every
//! `step`-th pixel in x and y (the **nodes**, plus the last column and
//! row), and a pixel between nodes takes the bilinear blend of those of
//! its two or four bracketing nodes that
//!
//! - have a value (a surface, inside the term's reach) and
//! - lie on the pixel's surface (`same`: the caller's test, normals and
//!   positions),
//!
//! their bilinear weights renormalized (a geometry-aware blend: a node
//! across a depth edge does not bleed into the pixel), **if** at least one
//! is left (all of them with [`Agreement::whole`]) and their values agree: per component, `max - min <= rel ·
//! max|v| + abs`. Otherwise ([`Lattice::at`] returns `None`) the caller
//! evaluates the pixel exactly, so a surface without nodes of its own (a
//! thin pole) and fast changes (the contact of an object with the floor)
//! keep full resolution. Where the blend is used, the values it blends
//! differ by at most the tolerance, so it is within that of each of them.

use std::sync::OnceLock;
use std::sync::atomic::{AtomicBool, Ordering};

use depthgraph_graph::prelude::NodeError;
use rayon::prelude::*;

/// The interpolation's tolerance: nodes within `rel · max|v| + abs` of
/// each other per component are blended (module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Agreement {
    /// Relative part.
    pub rel: f64,
    /// Absolute floor (the term's units), so that near-zero values blend.
    pub abs: f64,
    /// Every bracketing node must take part: no node may drop out (a
    /// pixel is then interpolated, never extrapolated from the nodes on
    /// one side: for terms that follow the normal closely, like direct
    /// irradiance on a curved object's rim).
    pub whole: bool,
}

/// An `N`-component term at every `step`-th pixel of a `w x h` image
/// (module docs), each node evaluated once, when a pixel first asks for
/// it (from any thread: a node's value depends on the node alone).
#[derive(Debug)]
pub struct Lattice<const N: usize> {
    step: usize,
    w: usize,
    h: usize,
    cols: usize,
    cells: Vec<OnceLock<Option<[f64; N]>>>,
}

/// The node coordinate of `x` on an axis of `len` pixels (last node at
/// `len - 1`): the bracketing nodes `(a, b)` and the weight of `b`; `a ==
/// b` with weight 0 on a node.
fn bracket(x: usize, step: usize, len: usize) -> (usize, usize, f64) {
    let a = x / step;
    let xa = a * step;
    if xa == x {
        return (a, a, 0.0);
    }
    let xb = ((a + 1) * step).min(len - 1);
    if xb == x {
        // the last node, at len - 1
        return (a + 1, a + 1, 0.0);
    }
    // guard: xb > x > xa here (x < len, x not on a node), so xb - xa >= 2
    (a, a + 1, (x - xa) as f64 / (xb - xa) as f64)
}

impl<const N: usize> Lattice<N> {
    /// Nodes every `step` pixels (at least 1; 1 makes every pixel a node)
    /// of a `w x h` image, none evaluated yet.
    pub fn new(w: usize, h: usize, step: usize) -> Self {
        let step = step.max(1);
        // nodes at 0, step, 2 step, ... and at len - 1
        let nodes = |len: usize| {
            if len == 0 {
                0
            } else {
                (len - 1).div_ceil(step) + 1
            }
        };
        let (cols, rows) = (nodes(w), nodes(h));
        Self {
            step,
            w,
            h,
            cols,
            cells: (0..cols * rows).map(|_| OnceLock::new()).collect(),
        }
    }

    /// The pixel index of node `(nx, ny)`.
    fn pixel(&self, nx: usize, ny: usize) -> usize {
        let x = (nx * self.step).min(self.w - 1);
        let y = (ny * self.step).min(self.h - 1);
        y * self.w + x
    }

    /// The pixel indices of the nodes pixel `(x, y)` blends (itself
    /// where it is a node; none outside the image), without allocating.
    pub fn corners(&self, x: usize, y: usize) -> impl Iterator<Item = usize> {
        let mut out = [0usize; 4];
        let mut n = 0;
        if x < self.w && y < self.h {
            let (xa, xb, tx) = bracket(x, self.step, self.w);
            let (ya, yb, ty) = bracket(y, self.step, self.h);
            out[0] = self.pixel(xa, ya);
            n = 1;
            if tx > 0.0 {
                out[n] = self.pixel(xb, ya);
                n += 1;
            }
            if ty > 0.0 {
                out[n] = self.pixel(xa, yb);
                n += 1;
            }
            if tx > 0.0 && ty > 0.0 {
                out[n] = self.pixel(xb, yb);
                n += 1;
            }
        }
        out.into_iter().take(n)
    }

    /// The value of the node at pixel index `i` (evaluated by `eval` if
    /// no pixel asked for it yet); `None` when `i` is not a node.
    pub fn node_value(
        &self,
        i: usize,
        eval: &(impl Fn(usize) -> Option<[f64; N]> + ?Sized),
    ) -> Option<Option<[f64; N]>> {
        // guard: w > 0 whenever a pixel index exists
        let (x, y) = (i % self.w.max(1), i / self.w.max(1));
        if !self.is_node(x, y) {
            return None;
        }
        let (nx, ny) = (x.div_ceil(self.step), y.div_ceil(self.step));
        Some(*self.cells[ny * self.cols + nx].get_or_init(|| eval(i)))
    }

    /// The cell of the node at pixel index `i` (`None`: not a node).
    fn cell(&self, i: usize) -> Option<&OnceLock<Option<[f64; N]>>> {
        // guard: w > 0 whenever a pixel index exists
        let (x, y) = (i % self.w.max(1), i / self.w.max(1));
        if !self.is_node(x, y) {
            return None;
        }
        let (nx, ny) = (x.div_ceil(self.step), y.div_ceil(self.step));
        self.cells.get(ny * self.cols + nx)
    }

    /// Whether the node at pixel index `i` has its value yet (`false` for
    /// a pixel that is not a node).
    pub fn is_known(&self, i: usize) -> bool {
        self.cell(i).is_some_and(|c| c.get().is_some())
    }

    /// Gives the node at pixel index `i` the value `v` (a batch evaluated
    /// it), unless it has one already; nothing for a pixel that is not a
    /// node.
    pub fn preset(&self, i: usize, v: Option<[f64; N]>) {
        if let Some(c) = self.cell(i) {
            let _ = c.set(v);
        }
    }

    /// Whether pixel `(x, y)` is a node.
    pub fn is_node(&self, x: usize, y: usize) -> bool {
        x < self.w
            && y < self.h
            && (x.is_multiple_of(self.step) || x == self.w - 1)
            && (y.is_multiple_of(self.step) || y == self.h - 1)
    }

    /// The term at pixel `(x, y)`: a node's own value, the blend of its
    /// bracketing nodes where the module docs allow it, else `None` (the
    /// caller evaluates the pixel). `eval(pixel index)` gives a node's
    /// value (`None`: no surface, out of the term's reach); `same(node
    /// pixel index)` says whether a node lies on the pixel's surface.
    pub fn at(
        &self,
        x: usize,
        y: usize,
        eval: &(impl Fn(usize) -> Option<[f64; N]> + ?Sized),
        same: impl Fn(usize) -> bool,
        tol: Agreement,
    ) -> Option<[f64; N]> {
        if x >= self.w || y >= self.h {
            return None;
        }
        let (xa, xb, tx) = bracket(x, self.step, self.w);
        let (ya, yb, ty) = bracket(y, self.step, self.h);
        let value = |nx: usize, ny: usize| {
            *self.cells[ny * self.cols + nx].get_or_init(|| eval(self.pixel(nx, ny)))
        };
        if tx == 0.0 && ty == 0.0 {
            return value(xa, ya);
        }
        let corners = [
            (xa, ya, (1.0 - tx) * (1.0 - ty)),
            (xb, ya, tx * (1.0 - ty)),
            (xa, yb, (1.0 - tx) * ty),
            (xb, yb, tx * ty),
        ];
        let mut out = [0.0f64; N];
        let mut total = 0.0f64;
        let (mut lo, mut hi, mut big) = ([f64::INFINITY; N], [f64::NEG_INFINITY; N], [0.0f64; N]);
        for (nx, ny, wgt) in corners {
            if wgt == 0.0 {
                continue;
            }
            let v = if same(self.pixel(nx, ny)) {
                value(nx, ny)
            } else {
                None
            };
            let Some(v) = v else {
                if tol.whole {
                    return None;
                }
                continue;
            };
            total += wgt;
            for c in 0..N {
                out[c] += wgt * v[c];
                lo[c] = lo[c].min(v[c]);
                hi[c] = hi[c].max(v[c]);
                big[c] = big[c].max(v[c].abs());
            }
        }
        // guard: total > 0 (some weight > 0 was kept) before dividing
        (total > 0.0 && (0..N).all(|c| hi[c] - lo[c] <= tol.rel * big[c] + tol.abs))
            .then(|| out.map(|v| v / total))
    }
}

/// A batch evaluation of a term: pixel indices to their values (`None`
/// where the term has none).
pub type Batch<'e, const N: usize> =
    dyn FnMut(&[usize]) -> Result<Vec<Option<[f64; N]>>, NodeError> + 'e;

/// Two lattices of one term, every `2 step` and every `step` pixels: a
/// pixel takes the coarse blend where the coarse nodes allow it (module
/// docs), else the fine one's, else it is the caller's. A smooth term far
/// from its sources is then evaluated at `1 / (2 step)²` of the pixels,
/// and where it changes faster (near the object) at `1 / step²`; every
/// node once (the coarse nodes are fine nodes too, and share the value).
#[derive(Debug)]
pub struct Nested<const N: usize> {
    coarse: Lattice<N>,
    fine: Lattice<N>,
}

impl<const N: usize> Nested<N> {
    /// The two lattices of a `w x h` image, the finer every `step` pixels
    /// (at least 1; at 1 both are every pixel: the term is exact).
    pub fn new(w: usize, h: usize, step: usize) -> Self {
        let step = step.max(1);
        Self {
            coarse: Lattice::new(w, h, if step == 1 { 1 } else { 2 * step }),
            fine: Lattice::new(w, h, step),
        }
    }

    /// [`Lattice::at`] on the coarse lattice, else on the fine one.
    pub fn at(
        &self,
        x: usize,
        y: usize,
        eval: &(impl Fn(usize) -> Option<[f64; N]> + ?Sized),
        same: impl Fn(usize) -> bool,
        tol: Agreement,
    ) -> Option<[f64; N]> {
        // a fine node that is a coarse one takes the coarse lattice's value
        // (evaluated once in all)
        let fine_eval = |i: usize| self.coarse.node_value(i, eval).unwrap_or_else(|| eval(i));
        self.coarse
            .at(x, y, eval, &same, tol)
            .or_else(|| self.fine.at(x, y, &fine_eval, &same, tol))
    }

    /// [`Nested::at`] at each pixel index of `pixels`, falling back to the
    /// pixel's own value, with every value evaluated in batches by `many`
    /// (pixel indices to their values, `None` where the term has none):
    /// the coarse nodes the pixels read, then the fine nodes of the pixels
    /// the coarse lattice does not serve, then the pixels neither serves.
    /// Each node once; the same values as `at` (and the pixel's own value
    /// where it gives none) with `many` asked one pixel at a time, whatever
    /// the batches. `same(pixel, node)`: whether the node lies on the
    /// pixel's surface.
    pub fn batch(
        &self,
        pixels: &[usize],
        many: &mut Batch<N>,
        same: &(dyn Fn(usize, usize) -> bool + Sync),
        tol: Agreement,
    ) -> Result<Vec<Option<[f64; N]>>, NodeError> {
        let w = self.fine.w.max(1);
        let mut ask = |list: &[usize]| -> Result<Vec<Option<[f64; N]>>, NodeError> {
            let v = many(list)?;
            if v.len() != list.len() {
                return Err(NodeError::Internal(format!(
                    "a lattice batch gave {} values for {} pixels",
                    v.len(),
                    list.len()
                )));
            }
            Ok(v)
        };
        // the nodes are all evaluated before the lattices read them
        let missed = AtomicBool::new(false);
        let never = |_: usize| {
            missed.store(true, Ordering::Relaxed);
            None
        };
        // the coarse nodes the pixels read (`at` reads a corner on the
        // pixel's surface, or the pixel itself where it is a node)
        let reads = |i: usize, n: usize| n == i || same(i, n);
        let mut need: Vec<usize> = pixels
            .iter()
            .flat_map(|&i| {
                self.coarse
                    .corners(i % w, i / w)
                    .filter(move |&n| reads(i, n))
            })
            .filter(|&n| !self.coarse.is_known(n))
            .collect();
        need.sort_unstable();
        need.dedup();
        for (&n, v) in need.iter().zip(ask(&need)?) {
            self.coarse.preset(n, v);
        }
        let coarse: Vec<Option<[f64; N]>> = pixels
            .par_iter()
            .map(|&i| self.coarse.at(i % w, i / w, &never, |n| same(i, n), tol))
            .collect();
        // the fine nodes of the pixels left (a coarse node's value is the
        // coarse lattice's)
        let open: Vec<usize> = (0..pixels.len()).filter(|&k| coarse[k].is_none()).collect();
        let mut need: Vec<usize> = open
            .iter()
            .flat_map(|&k| {
                let i = pixels[k];
                self.fine
                    .corners(i % w, i / w)
                    .filter(move |&n| reads(i, n))
            })
            .filter(|&n| {
                let (x, y) = (n % w, n / w);
                if self.coarse.is_node(x, y) {
                    !self.coarse.is_known(n)
                } else {
                    !self.fine.is_known(n)
                }
            })
            .collect();
        need.sort_unstable();
        need.dedup();
        for (&n, v) in need.iter().zip(ask(&need)?) {
            if self.coarse.is_node(n % w, n / w) {
                self.coarse.preset(n, v);
            } else {
                self.fine.preset(n, v);
            }
        }
        let fine_eval = |i: usize| {
            self.coarse
                .node_value(i, &never)
                .unwrap_or_else(|| never(i))
        };
        let mut out: Vec<Option<[f64; N]>> = coarse;
        let fine: Vec<Option<[f64; N]>> = open
            .par_iter()
            .map(|&k| {
                let i = pixels[k];
                self.fine.at(i % w, i / w, &fine_eval, |n| same(i, n), tol)
            })
            .collect();
        let mut rest = Vec::new();
        for (&k, v) in open.iter().zip(fine) {
            match v {
                Some(v) => out[k] = Some(v),
                None => rest.push(k),
            }
        }
        // the pixels neither lattice serves: their own values
        let own: Vec<usize> = rest.iter().map(|&k| pixels[k]).collect();
        for (&k, v) in rest.iter().zip(ask(&own)?) {
            out[k] = v;
        }
        if missed.load(Ordering::Relaxed) {
            return Err(NodeError::Internal(
                "a lattice read a node its batch did not evaluate".into(),
            ));
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const EXACT: Agreement = Agreement {
        rel: 0.0,
        abs: 0.0,
        whole: false,
    };

    /// A linear term is reproduced exactly between nodes (bilinear blend of
    /// a plane); nodes return their own values; the last column and row
    /// are nodes whatever the step.
    #[test]
    fn a_plane_is_interpolated_exactly() {
        let (w, h) = (23, 17);
        let f = |i: usize| [(i % w) as f64 * 0.5 + (i / w) as f64 * 2.0 + 1.0];
        let loose = Agreement {
            rel: 1.0,
            abs: 0.0,
            whole: false,
        };
        for step in [1, 2, 3, 4, 8, 40] {
            let l = Lattice::new(w, h, step);
            let eval = |i: usize| Some(f(i));
            for y in 0..h {
                for x in 0..w {
                    assert_eq!(
                        l.is_node(x, y),
                        l.at(x, y, &eval, |_| false, EXACT).is_some()
                    );
                    let v = l.at(x, y, &eval, |_| true, loose).unwrap();
                    assert!(
                        (v[0] - f(y * w + x)[0]).abs() < 1e-12,
                        "step {step} ({x}, {y})"
                    );
                }
            }
            // with no tolerance only the nodes answer
            assert!(l.at(w - 1, h - 1, &eval, |_| false, EXACT).is_some());
            if step > 1 {
                assert!(l.at(1, 0, &eval, |_| true, EXACT).is_none());
            }
        }
    }

    /// Nodes without a value or on another surface drop out of the blend;
    /// a pixel with none left, or whose nodes disagree beyond the
    /// tolerance, is left to the caller.
    #[test]
    fn missing_and_foreign_nodes_drop_out_and_disagreement_refuses() {
        let (w, h) = (9, 9);
        let tol = Agreement {
            rel: 0.1,
            abs: 1e-3,
            whole: false,
        };
        // a step between x = 4 and x = 5
        let l = Lattice::new(w, h, 4);
        let eval = |i: usize| {
            if i % w == 8 && i / w == 8 {
                None
            } else if i % w >= 5 {
                Some([2.0, 0.0])
            } else {
                Some([1.0, 0.0])
            }
        };
        // (2, 0) between nodes x = 0 and 4: same value, blended
        assert_eq!(l.at(2, 0, &eval, |_| true, tol), Some([1.0, 0.0]));
        // a node on another surface drops out of the blend; with none
        // left the pixel is the caller's
        assert_eq!(l.at(2, 0, &eval, |n| n != 4, tol), Some([1.0, 0.0]));
        assert_eq!(l.at(2, 0, &eval, |_| false, tol), None);
        // across the step, with the far node on another surface, the
        // near one alone answers
        assert_eq!(l.at(6, 0, &eval, |n| n != 8, tol), Some([1.0, 0.0]));
        // (6, 0) between x = 4 (1.0) and x = 8 (2.0): 1.0 apart > 0.2
        assert_eq!(l.at(6, 0, &eval, |_| true, tol), None);
        // (7, 7) without the missing node (8, 8): (4, 4) and (4, 8) hold
        // 1.0, (8, 4) 2.0, they disagree; with the x = 4 nodes on another
        // surface (8, 4) alone answers
        assert_eq!(l.at(7, 7, &eval, |_| true, tol), None);
        assert_eq!(l.at(7, 7, &eval, |n| n % 9 != 4, tol), Some([2.0, 0.0]));
        // within tolerance the blend is the bilinear weight
        let loose = Agreement {
            rel: 1.0,
            abs: 0.0,
            whole: false,
        };
        assert_eq!(l.at(6, 0, &eval, |_| true, loose), Some([1.5, 0.0]));
        // outside the image
        assert_eq!(l.at(9, 0, &eval, |_| true, loose), None);
    }

    /// Degenerate sizes do not panic.
    #[test]
    fn tiny_and_empty_images() {
        let eval = |_: usize| Some([3.0]);
        let l = Lattice::<1>::new(1, 1, 4);
        assert_eq!(l.at(0, 0, &eval, |_| true, EXACT), Some([3.0]));
        let e = Lattice::<1>::new(0, 0, 4);
        assert_eq!(e.at(0, 0, &eval, |_| true, EXACT), None);
    }

    /// The nested lattices blend on the coarse lattice where it agrees
    /// and fall back to the fine one where it does not.
    #[test]
    fn nested_lattices_fall_back_to_the_fine_one() {
        let (w, h) = (17, 1);
        // a kink at x = 8: flat to its left, a ramp to its right
        let f = |i: usize| Some([if i <= 8 { 1.0 } else { 1.0 + (i - 8) as f64 }]);
        let tol = Agreement {
            rel: 0.25,
            abs: 0.0,
            whole: false,
        };
        let n = Nested::<1>::new(w, h, 2);
        // x = 2 between the coarse nodes 0 and 4, both 1.0
        assert_eq!(n.at(2, 0, &f, |_| true, tol), Some([1.0]));
        // x = 13 between coarse nodes 12 (5.0) and 16 (9.0): too far apart;
        // the fine nodes 12 (5.0) and 14 (7.0) too (2 > 0.25 x 7); 15
        // between 14 and 16 (7.0, 9.0: 2 <= 2.25) blends
        assert_eq!(n.at(13, 0, &f, |_| true, tol), None);
        assert_eq!(n.at(15, 0, &f, |_| true, tol), Some([8.0]));
        // x = 10: coarse nodes 8 (1.0) and 12 (5.0) disagree; 10 is a fine node
        assert_eq!(n.at(10, 0, &f, |_| true, tol), Some([3.0]));
    }

    /// With `whole`, a pixel whose bracketing nodes are not all there (on
    /// its surface, with a value) is the caller's.
    #[test]
    fn whole_blends_only_between_all_nodes() {
        let l = Lattice::<1>::new(9, 1, 4);
        let eval = |i: usize| Some([i as f64]);
        let whole = Agreement {
            rel: 1.0,
            abs: 0.0,
            whole: true,
        };
        assert_eq!(l.at(2, 0, &eval, |_| true, whole), Some([2.0]));
        assert_eq!(l.at(2, 0, &eval, |n| n != 4, whole), None);
        let part = Agreement {
            whole: false,
            ..whole
        };
        assert_eq!(l.at(2, 0, &eval, |n| n != 4, part), Some([0.0]));
    }

    /// The nested lattices evaluate every node once, the coarse nodes'
    /// values serving the fine lattice too.
    #[test]
    fn nested_lattices_evaluate_each_node_once() {
        let (w, h) = (13, 9);
        let asked = std::cell::RefCell::new(Vec::new());
        // a ramp steep enough that the coarse blend refuses everywhere
        let eval = |i: usize| {
            asked.borrow_mut().push(i);
            Some([(i % w) as f64 * 10.0 + 1.0])
        };
        let tol = Agreement {
            rel: 0.3,
            abs: 0.0,
            whole: false,
        };
        let n = Nested::<1>::new(w, h, 2);
        for y in 0..h {
            for x in 0..w {
                let _ = n.at(x, y, &eval, |_| true, tol);
            }
        }
        let mut a = asked.into_inner();
        let all = a.len();
        a.sort_unstable();
        a.dedup();
        assert_eq!(a.len(), all, "a node was evaluated twice");
        // the fine lattice was used (its nodes at odd multiples of 2)
        assert!(a.contains(&2));
    }

    /// Batches give what `at` gives pixel by pixel (with the pixel's own
    /// value where no lattice serves it), each node and pixel asked once,
    /// in three batches: a term smooth on the left half and stepping on
    /// the right, a depth edge (`same`) down the middle.
    #[test]
    fn batches_give_what_at_gives() {
        let (w, h) = (29, 21);
        let f = |i: usize| -> Option<[f64; 2]> {
            let (x, y) = ((i % w) as f64, (i / w) as f64);
            let step = if x > 14.0 && (y as usize).is_multiple_of(3) {
                5.0
            } else {
                0.0
            };
            (i != 3 * w + 7).then_some([1.0 + 0.01 * x + 0.02 * y + step, 2.0])
        };
        let same = |p: usize, n: usize| (p % w < 12) == (n % w < 12);
        let tol = Agreement {
            rel: 0.05,
            abs: 0.0,
            whole: false,
        };
        let pixels: Vec<usize> = (0..w * h).filter(|i| i % 5 != 1).collect();
        let want: Vec<Option<[f64; 2]>> = {
            let grid = Nested::<2>::new(w, h, 2);
            pixels
                .iter()
                .map(|&i| {
                    grid.at(i % w, i / w, &f, |n| same(i, n), tol)
                        .or_else(|| f(i))
                })
                .collect()
        };
        let grid = Nested::<2>::new(w, h, 2);
        let mut asked: Vec<Vec<usize>> = Vec::new();
        let mut many = |list: &[usize]| -> Result<Vec<Option<[f64; 2]>>, NodeError> {
            asked.push(list.to_vec());
            Ok(list.iter().map(|&i| f(i)).collect())
        };
        let got = grid.batch(&pixels, &mut many, &same, tol).unwrap();
        assert_eq!(got, want);
        assert_eq!(asked.len(), 3, "{} batches", asked.len());
        // nodes once: the two lattices' batches share nothing
        let mut nodes: Vec<usize> = asked[0].iter().chain(&asked[1]).copied().collect();
        let n = nodes.len();
        nodes.sort_unstable();
        nodes.dedup();
        assert_eq!(nodes.len(), n, "a node was asked twice");
        // the stepping half needed the fine lattice and pixels of its own
        assert!(!asked[1].is_empty() && !asked[2].is_empty());
    }
}
