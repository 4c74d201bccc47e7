//! Thinning of the stance sequence (CNN IV: "the stance sequence is then refined to avoid excessive
//! numbers of footsteps, by not moving a limb if its next hold is within a threshold", 0.3 m for
//! RoboSimian). Along the body path a foot keeps its hold
//!
//! 1. while the optimal stance's hold for it lies within the threshold (CNN IV's rule), or
//! 2. while the stance with the kept hold still has at least `keep_ratio` of the optimal stance's
//!    Flex there (our addition: with holds clustered coarser than the threshold, σ*(v) can swap
//!    between neighbouring holds of similar Flex from one vertex to the next; `keep_ratio` > 1 turns
//!    this off),
//!
//! and in either case only when the stance with the kept hold is feasible (Flex > 0) at the new
//! body position. A stance is emitted only when a foot moves, and when both feet would move at once
//! an intermediate stance moving one foot first is inserted when one is feasible (a biped steps one
//! foot at a time).

use nalgebra::Vector3;

/// One stance along the route: the body vertex where it is taken, its holds, its Flex there.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Step {
    /// Index into the body path.
    pub path_index: usize,
    pub left: usize,
    pub right: usize,
    pub flex: f64,
}

/// Thins `optimal` (per body-path vertex: the optimal stance's left, right and Flex) with the
/// distance `threshold_m` between consecutive holds of one foot and the Flex ratio `keep_ratio`.
/// `holds` are the hold positions; `flex_at(path_index, left, right)` gives Flex of another stance
/// at a path vertex.
pub fn thin(
    optimal: &[(usize, usize, f64)],
    holds: &[Vector3<f64>],
    threshold_m: f64,
    keep_ratio: f64,
    flex_at: impl Fn(usize, usize, usize) -> f64,
) -> Vec<Step> {
    let Some(&(l0, r0, f0)) = optimal.first() else { return Vec::new() };
    let mut steps = vec![Step { path_index: 0, left: l0, right: r0, flex: f0 }];
    let near = |a: usize, b: usize| (holds[a] - holds[b]).norm() < threshold_m;
    for (i, &(l, r, f)) in optimal.iter().enumerate().skip(1) {
        let Some(&current) = steps.last() else { break };
        let good_enough = |flex: f64| flex > 0.0 && flex >= keep_ratio * f;
        // Both feet stay.
        let both = if (current.left, current.right) == (l, r) { f } else { flex_at(i, current.left, current.right) };
        if both > 0.0 && ((near(l, current.left) && near(r, current.right)) || good_enough(both)) {
            continue;
        }
        // One foot stays: the left (right moves to r) or the right (left moves to l).
        let mut one: Option<(usize, usize, f64)> = None;
        for (keep, left, right) in [(near(l, current.left), current.left, r), (near(r, current.right), l, current.right)] {
            if (left, right) == (l, r) {
                continue;
            }
            let flex = flex_at(i, left, right);
            if flex > 0.0 && (keep || good_enough(flex)) && one.is_none_or(|o| flex > o.2) {
                one = Some((left, right, flex));
            }
        }
        let (left, right, flex) = one.unwrap_or((l, r, f));
        if left != current.left && right != current.right {
            // Both feet would move: step with one first if that stance holds here.
            let left_first = flex_at(i, left, current.right);
            let right_first = flex_at(i, current.left, right);
            if left_first > 0.0 && left_first >= right_first {
                steps.push(Step { path_index: i, left, right: current.right, flex: left_first });
            } else if right_first > 0.0 {
                steps.push(Step { path_index: i, left: current.left, right, flex: right_first });
            }
        }
        steps.push(Step { path_index: i, left, right, flex });
    }
    steps
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Holds on a line at x = 0, 0.05, 0.12, 0.3 (left, y = +0.04) and the same for the right foot
    /// (y = −0.04, indices 4..8). The optimal stances walk forward through them.
    fn holds() -> Vec<Vector3<f64>> {
        let xs = [0.0, 0.05, 0.12, 0.3];
        xs.iter().map(|&x| Vector3::new(x, 0.04, 0.0)).chain(xs.iter().map(|&x| Vector3::new(x, -0.04, 0.0))).collect()
    }

    #[test]
    fn a_foot_stays_while_its_next_hold_is_within_the_threshold() {
        let h = holds();
        // Optimal per vertex: (0,4), (1,4), (1,5), (2,5), (2,6), (3,7).
        let optimal = [(0, 4, 0.5), (1, 4, 0.5), (1, 5, 0.5), (2, 5, 0.5), (2, 6, 0.5), (3, 7, 0.5)];
        let steps = thin(&optimal, &h, 0.1, f64::INFINITY, |_, _, _| 0.4);
        let pairs: Vec<(usize, usize)> = steps.iter().map(|s| (s.left, s.right)).collect();
        // Left: 0 → 1 is 5 cm (stay), 0 → 2 is 12 cm (move), 2 → 3 is 18 cm (move).
        // Right: 4 → 5 stays, 4 → 6 moves, 6 → 7 moves. At the last vertex both move: the left first.
        assert_eq!(pairs, vec![(0, 4), (2, 4), (2, 6), (3, 6), (3, 7)]);
        assert_eq!(steps[1].path_index, 3);
        assert_eq!(steps[2].path_index, 4);
        assert_eq!((steps[3].path_index, steps[4].path_index), (5, 5));
        // With a tiny threshold every change is a step (no thinning), still one foot at a time.
        let all = thin(&optimal, &h, 0.01, f64::INFINITY, |_, _, _| 0.4);
        assert_eq!(all.len(), 7);
        // A kept hold that no longer forms a stance is given up for the optimal one.
        let strict = thin(&optimal, &h, 0.1, f64::INFINITY, |_, l, r| if (l, r) == (0, 4) { 0.0 } else { 0.4 });
        assert_eq!((strict[1].left, strict[1].right), (1, 4));
        assert!(thin(&[], &h, 0.1, f64::INFINITY, |_, _, _| 1.0).is_empty());
    }

    /// With the Flex ratio, a foot also stays while its stance keeps enough of the optimal Flex:
    /// here the start stance keeps 0.4 ≥ 0.5 · 0.5 everywhere, so nobody moves until the stance with
    /// both old holds fails at the last vertex.
    #[test]
    fn a_foot_stays_while_its_stance_keeps_enough_flex() {
        let h = holds();
        let optimal = [(0, 4, 0.5), (1, 5, 0.5), (2, 6, 0.5), (3, 7, 0.5)];
        let flex = |i: usize, l: usize, r: usize| {
            if i == 3 && (l, r) == (0, 4) {
                0.0
            } else if (l, r) == (0, 4) {
                0.4
            } else {
                0.3
            }
        };
        let steps = thin(&optimal, &h, 0.01, 0.5, flex);
        let pairs: Vec<(usize, usize, usize)> = steps.iter().map(|s| (s.path_index, s.left, s.right)).collect();
        // At vertex 3 both old holds fail together; keeping one (0, 7) or (3, 4) keeps 0.3 ≥ 0.25:
        // the left stays (first tried at equal Flex) and the right moves.
        assert_eq!(pairs, vec![(0, 0, 4), (3, 0, 7)]);
    }
}
