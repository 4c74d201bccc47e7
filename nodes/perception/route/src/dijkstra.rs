//! Dijkstra's algorithm on an 8-connected grid (CNN IV: "each vertex is connected to its 8
//! neighbouring pixels"), directed: the cost of the edge u → v is given by a function of (u, v), and
//! `None` means no edge (v impassable or the step too long). Ties are broken by vertex index, so the
//! path is deterministic.

use std::cmp::Ordering;
use std::collections::BinaryHeap;

/// The cheapest path and what the search saw.
#[derive(Debug, Clone, PartialEq)]
pub struct Search {
    /// Vertex indices from start to goal (row-major); `None` when the goal was not reached.
    pub path: Option<Vec<usize>>,
    /// Total cost of the path.
    pub cost: f64,
    /// Vertices settled (reachable from the start).
    pub settled: usize,
}

#[derive(PartialEq)]
struct Entry {
    cost: f64,
    vertex: usize,
}

impl Eq for Entry {}

impl Ord for Entry {
    fn cmp(&self, other: &Self) -> Ordering {
        // Min-heap on cost, then on vertex index.
        other.cost.total_cmp(&self.cost).then_with(|| other.vertex.cmp(&self.vertex))
    }
}

impl PartialOrd for Entry {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

/// The 8 neighbour offsets (row, column).
const NEIGHBOURS: [(isize, isize); 8] = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)];

/// Cheapest path from `start` to `goal` on a rows × cols grid; `edge(u, v)` is the cost of u → v
/// (non-negative) or `None`. Costs that are negative or NaN are treated as no edge.
pub fn shortest_path(rows: usize, cols: usize, start: usize, goal: usize, edge: impl Fn(usize, usize) -> Option<f64>) -> Search {
    let n = rows * cols;
    if start >= n || goal >= n {
        return Search { path: None, cost: f64::INFINITY, settled: 0 };
    }
    let mut dist = vec![f64::INFINITY; n];
    let mut previous = vec![usize::MAX; n];
    let mut done = vec![false; n];
    let mut heap = BinaryHeap::new();
    dist[start] = 0.0;
    heap.push(Entry { cost: 0.0, vertex: start });
    let mut settled = 0;
    while let Some(Entry { cost, vertex }) = heap.pop() {
        if done[vertex] {
            continue;
        }
        done[vertex] = true;
        settled += 1;
        if vertex == goal {
            break;
        }
        let (r, c) = ((vertex / cols) as isize, (vertex % cols) as isize);
        for (dr, dc) in NEIGHBOURS {
            let (nr, nc) = (r + dr, c + dc);
            if nr < 0 || nc < 0 || nr >= rows as isize || nc >= cols as isize {
                continue;
            }
            let next = nr as usize * cols + nc as usize;
            if done[next] {
                continue;
            }
            let Some(w) = edge(vertex, next) else { continue };
            if w.is_nan() || w < 0.0 {
                continue;
            }
            let candidate = cost + w;
            if candidate < dist[next] {
                dist[next] = candidate;
                previous[next] = vertex;
                heap.push(Entry { cost: candidate, vertex: next });
            }
        }
    }
    if !done[goal] {
        return Search { path: None, cost: f64::INFINITY, settled };
    }
    let mut path = vec![goal];
    let mut at = goal;
    while at != start {
        at = previous[at];
        path.push(at);
    }
    path.reverse();
    Search { path: Some(path), cost: dist[goal], settled }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 3 × 4 toy grid with vertex costs (the cost of entering v, times the step length 1 or √2):
    ///
    /// ```text
    ///   S  1  1  1
    ///   1  9  X  1
    ///   1  2  2  G
    /// ```
    /// X is impassable. By hand: top row then the diagonal (0,2)→(1,3) and down:
    /// 1 + 1 + √2 + 1 = 4.41; the whole top row and down: 5; along the bottom:
    /// 1 + 2√2 + 2 + 1 = 6.83 (or 1 + 1 + 2 + 2 + 1 = 7); through the 9 dearer still.
    #[test]
    fn toy_grid_gives_the_hand_computed_path() {
        let enter = [1.0, 1.0, 1.0, 1.0, 1.0, 9.0, f64::NAN, 1.0, 1.0, 2.0, 2.0, 1.0];
        let edge = |u: usize, v: usize| {
            let c = enter[v];
            if c.is_nan() {
                return None;
            }
            let diagonal = u / 4 != v / 4 && u % 4 != v % 4;
            Some(c * if diagonal { std::f64::consts::SQRT_2 } else { 1.0 })
        };
        let search = shortest_path(3, 4, 0, 11, edge);
        assert_eq!(search.path, Some(vec![0, 1, 2, 7, 11]));
        assert!((search.cost - (3.0 + std::f64::consts::SQRT_2)).abs() < 1e-12, "{}", search.cost);
    }

    #[test]
    fn a_wall_leaves_the_goal_unreached() {
        // Column 1 impassable on a 3 × 3 grid.
        let edge = |_u: usize, v: usize| (v % 3 != 1).then_some(1.0);
        let search = shortest_path(3, 3, 0, 8, edge);
        assert_eq!(search.path, None);
        assert_eq!(search.settled, 3);
        // Start = goal.
        assert_eq!(shortest_path(3, 3, 4, 4, |_, _| Some(1.0)).path, Some(vec![4]));
        assert_eq!(shortest_path(3, 3, 9, 4, |_, _| Some(1.0)).path, None);
    }
}
