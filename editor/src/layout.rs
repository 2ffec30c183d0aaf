//! The automatic layout of a pipeline without a saved one: a layered
//! (Sugiyama-style) drawing. Columns are the longest path from a source, so
//! every wire runs left to right; the order within a column is improved by
//! barycentre sweeps (each node moves towards the mean row of its
//! neighbours, which removes most crossings); each node is then placed level
//! with the mean of its inputs' nodes, as near as the nodes above it allow,
//! so wires stay short. Heights come from the ports a node has, so tall
//! nodes (Relight's nine inputs) never overlap the next one.

/// Horizontal distance between layout columns (canvas points).
pub const COLUMN_WIDTH: f64 = 320.0;
/// Free space between two nodes of one column.
pub const ROW_GAP: f64 = 30.0;

/// The canvas height of a node with `ports` rows of pins (the larger of its
/// input and output counts): header, pin rows and the status lines of its
/// body.
pub fn node_height(ports: usize) -> f64 {
    90.0 + 24.0 * ports as f64
}

/// Options of [`layered`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LayoutParams {
    /// Barycentre sweeps (each one down the columns and back up); 0 keeps
    /// the order of the file.
    pub sweeps: usize,
    /// Place each node level with its inputs' nodes (else stacked from the
    /// top of its column).
    pub align: bool,
}

impl Default for LayoutParams {
    fn default() -> Self {
        Self {
            sweeps: 4,
            align: true,
        }
    }
}

/// Column of every node: the longest path from a source. Iterated to a
/// fixpoint, at most `n + 1` rounds, so a cycle (which a checked pipeline
/// never has) still ends; columns are capped at `n`.
pub fn columns(n: usize, edges: &[(usize, usize)]) -> Vec<usize> {
    let mut col = vec![0usize; n];
    for _ in 0..=n {
        let mut changed = false;
        for &(from, to) in edges {
            if from < n && to < n && from != to {
                let want = (col[from] + 1).min(n);
                if col[to] < want {
                    col[to] = want;
                    changed = true;
                }
            }
        }
        if !changed {
            break;
        }
    }
    col
}

/// Top-left corner of every node (`heights[i]` tall; `edges` are
/// `(from, to)` indices, wires from an output of `from` to an input of `to`).
pub fn layered(
    n: usize,
    edges: &[(usize, usize)],
    heights: &[f64],
    params: &LayoutParams,
) -> Vec<[f64; 2]> {
    let height = |i: usize| heights.get(i).copied().unwrap_or(node_height(1));
    let col = columns(n, edges);
    let ncols = col.iter().copied().max().map_or(0, |m| m + 1);
    let mut cols: Vec<Vec<usize>> = vec![Vec::new(); ncols];
    for (i, &c) in col.iter().enumerate() {
        cols[c].push(i);
    }
    let preds = |v: usize| edges.iter().filter(move |e| e.1 == v).map(|e| e.0);
    // Row of each node within its column.
    let mut row = vec![0usize; n];
    let renumber = |cols: &Vec<Vec<usize>>, row: &mut Vec<usize>| {
        for c in cols {
            for (r, &v) in c.iter().enumerate() {
                row[v] = r;
            }
        }
    };
    renumber(&cols, &mut row);
    // Barycentre of `v` over its inputs' rows (`down`) or its outputs' rows,
    // or its own row when it has none (so it keeps its place). Guard: a mean
    // over at least one row.
    let bary = |v: usize, row: &[usize], down: bool| {
        let (sum, k) = edges
            .iter()
            .filter_map(|&(a, b)| match down {
                true if b == v => Some(a),
                false if a == v => Some(b),
                _ => None,
            })
            .fold((0.0, 0usize), |(s, k), u| (s + row[u] as f64, k + 1));
        if k > 0 { sum / k as f64 } else { row[v] as f64 }
    };
    let down: Vec<(usize, bool)> = (1..ncols).map(|c| (c, true)).collect();
    let up: Vec<(usize, bool)> = (0..ncols.saturating_sub(1))
        .rev()
        .map(|c| (c, false))
        .collect();
    for _ in 0..params.sweeps {
        for &(c, dir) in down.iter().chain(&up) {
            let mut keyed: Vec<(f64, usize)> =
                cols[c].iter().map(|&v| (bary(v, &row, dir), v)).collect();
            keyed.sort_by(|a, b| a.0.total_cmp(&b.0));
            cols[c] = keyed.into_iter().map(|k| k.1).collect();
            renumber(&cols, &mut row);
        }
    }
    let mut pos = vec![[0.0, 0.0]; n];
    for (c, members) in cols.iter().enumerate() {
        let mut next_free = 0.0f64;
        for &v in members {
            let mut y = next_free;
            if params.align && c > 0 {
                let (sum, k) = preds(v).fold((0.0, 0usize), |(s, k), u| {
                    (s + pos[u][1] + 0.5 * height(u), k + 1)
                });
                if k > 0 {
                    // Guard: k >= 1. The node's centre level with its inputs'.
                    y = y.max(sum / k as f64 - 0.5 * height(v));
                }
            }
            pos[v] = [c as f64 * COLUMN_WIDTH, y];
            next_free = y + height(v) + ROW_GAP;
        }
    }
    pos
}

/// The layout with the fewest crossings, then the shortest wires, among
/// [`layered`] with barycentre sweeps or the file's order, each aligned or
/// stacked: alignment and sweeps shorten wires on most graphs, and this
/// keeps the rare graph they do not help as the file has it.
pub fn best_layered(n: usize, edges: &[(usize, usize)], heights: &[f64]) -> Vec<[f64; 2]> {
    let candidates = [
        LayoutParams::default(),
        LayoutParams {
            align: false,
            ..LayoutParams::default()
        },
        LayoutParams {
            sweeps: 0,
            align: true,
        },
        LayoutParams {
            sweeps: 0,
            align: false,
        },
    ];
    let mut best: Option<(usize, f64, Vec<[f64; 2]>)> = None;
    for p in &candidates {
        let pos = layered(n, edges, heights, p);
        let score = (crossings(&pos, edges), wire_length(&pos, edges, heights));
        let better = best
            .as_ref()
            .is_none_or(|b| score.0 < b.0 || (score.0 == b.0 && score.1 < b.1 - 1e-9));
        if better {
            best = Some((score.0, score.1, pos));
        }
    }
    best.map(|b| b.2).unwrap_or_default()
}

/// Total vertical length of the wires (between node centres): what the
/// layout keeps short.
pub fn wire_length(pos: &[[f64; 2]], edges: &[(usize, usize)], heights: &[f64]) -> f64 {
    let centre = |i: usize| pos[i][1] + 0.5 * heights.get(i).copied().unwrap_or(0.0);
    edges
        .iter()
        .filter(|e| e.0 < pos.len() && e.1 < pos.len())
        .map(|&(a, b)| (centre(a) - centre(b)).abs())
        .sum()
}

/// Number of pairs of wires between the same two adjacent columns that
/// cross (their ends in opposite vertical order).
pub fn crossings(pos: &[[f64; 2]], edges: &[(usize, usize)]) -> usize {
    let mut count = 0;
    for (i, a) in edges.iter().enumerate() {
        for b in &edges[i + 1..] {
            let same_columns = pos[a.0][0] == pos[b.0][0] && pos[a.1][0] == pos[b.1][0];
            if !same_columns || a.0 == b.0 || a.1 == b.1 {
                continue;
            }
            let top = (pos[a.0][1] - pos[b.0][1]).signum();
            let bottom = (pos[a.1][1] - pos[b.1][1]).signum();
            if top * bottom < 0.0 {
                count += 1;
            }
        }
    }
    count
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn columns_follow_the_longest_path_and_cycles_end() {
        assert_eq!(
            columns(4, &[(0, 1), (1, 2), (0, 2), (2, 3)]),
            vec![0, 1, 2, 3]
        );
        let c = columns(2, &[(0, 1), (1, 0)]);
        assert!(c.iter().all(|&x| x <= 2));
    }

    #[test]
    fn sweeps_remove_a_crossing_and_nodes_never_overlap() {
        // a0 -> b1, a1 -> b0, written in the order that crosses.
        let edges = [(0, 3), (1, 2)];
        let heights = [100.0, 100.0, 150.0, 150.0];
        let naive = layered(
            4,
            &edges,
            &heights,
            &LayoutParams {
                sweeps: 0,
                align: false,
            },
        );
        assert_eq!(crossings(&naive, &edges), 1);
        let good = layered(4, &edges, &heights, &LayoutParams::default());
        assert_eq!(crossings(&good, &edges), 0);
        for (i, a) in good.iter().enumerate() {
            for (j, b) in good.iter().enumerate() {
                if i != j && a[0] == b[0] {
                    let apart = a[1] + heights[i] + ROW_GAP <= b[1] + 1e-9
                        || b[1] + heights[j] + ROW_GAP <= a[1] + 1e-9;
                    assert!(apart, "nodes {i} and {j} overlap: {a:?} {b:?}");
                }
            }
        }
    }
}
