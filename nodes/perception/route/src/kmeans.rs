//! k-means clustering of the holds (CNN IV: "we first employ k-means clustering algorithm to cluster
//! both foothold and handhold predictions (we use k = 30)"): many predictions of one foothold become
//! one hold, which both sharpens the positions and bounds the number of stances to try.
//!
//! Deterministic: k-means++ seeding from a seeded generator (the first centre is the best-scoring
//! hold), then Lloyd iterations until no assignment changes. Centres are score-weighted means; a
//! cluster's score is the mean score of its members. A cluster that loses every member is re-seeded
//! at the point farthest from its centre. With fewer holds than k every hold is its own cluster.

use nalgebra::Vector3;
use rand::{Rng, SeedableRng};

use crate::error::RouteError;
use crate::hold::Hold;

/// The result of clustering: one hold per cluster and each input's cluster.
#[derive(Debug, Clone, PartialEq)]
pub struct Clusters {
    /// Cluster centres as holds (score = the members' mean score), in cluster order.
    pub holds: Vec<Hold>,
    /// For each input hold, the index of its cluster.
    pub assignment: Vec<usize>,
    /// Lloyd iterations run.
    pub iterations: usize,
}

/// Lloyd iterations at most (k-means on a few thousand points converges in tens).
const MAX_ITERATIONS: usize = 200;

/// Clusters `holds` (already checked: finite, scores in [0, 1]) into at most `k` clusters.
pub fn kmeans(holds: &[Hold], k: usize, seed: u64) -> Result<Clusters, RouteError> {
    if k == 0 {
        return Err(RouteError::ZeroClusters);
    }
    if holds.is_empty() {
        return Err(RouteError::NoHolds);
    }
    let points: Vec<Vector3<f64>> = holds.iter().map(Hold::point).collect();
    // Weights: the score, with a floor so a zero-score hold still moves its centre a little.
    let weights: Vec<f64> = holds.iter().map(|h| h.score.max(1e-6)).collect();
    if holds.len() <= k {
        return Ok(Clusters { holds: holds.to_vec(), assignment: (0..holds.len()).collect(), iterations: 0 });
    }
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let mut centres = plus_plus_seeds(&points, holds, k, &mut rng);
    let mut assignment = vec![usize::MAX; points.len()];
    let mut iterations = 0;
    while iterations < MAX_ITERATIONS {
        iterations += 1;
        let mut changed = false;
        for (i, p) in points.iter().enumerate() {
            let nearest = nearest_centre(&centres, p);
            if assignment[i] != nearest {
                assignment[i] = nearest;
                changed = true;
            }
        }
        if !changed {
            break;
        }
        let mut sums = vec![Vector3::zeros(); k];
        let mut mass = vec![0.0; k];
        for ((p, &c), &w) in points.iter().zip(&assignment).zip(&weights) {
            sums[c] += p * w;
            mass[c] += w;
        }
        for c in 0..k {
            if mass[c] > 0.0 {
                centres[c] = sums[c] / mass[c];
            } else if let Some(far) = farthest_from_centre(&points, &assignment, &centres) {
                // Empty cluster: move it onto the worst-served point; the next pass reassigns.
                centres[c] = points[far];
                assignment[far] = c;
            }
        }
    }
    let mut score_sum = vec![0.0; k];
    let mut count = vec![0usize; k];
    for (hold, &c) in holds.iter().zip(&assignment) {
        score_sum[c] += hold.score;
        count[c] += 1;
    }
    // Drop clusters that ended empty and renumber the assignment.
    let mut index_of = vec![usize::MAX; k];
    let mut out = Vec::with_capacity(k);
    for c in 0..k {
        if count[c] > 0 {
            index_of[c] = out.len();
            out.push(Hold::new(centres[c], score_sum[c] / count[c] as f64));
        }
    }
    let assignment = assignment.iter().map(|&c| index_of[c]).collect();
    Ok(Clusters { holds: out, assignment, iterations })
}

/// k-means++ (Arthur & Vassilvitskii): first centre the best-scoring hold, each next one drawn
/// with probability ∝ squared distance to the nearest centre so far.
fn plus_plus_seeds(points: &[Vector3<f64>], holds: &[Hold], k: usize, rng: &mut impl Rng) -> Vec<Vector3<f64>> {
    let first = holds.iter().enumerate().fold(0, |best, (i, h)| if h.score > holds[best].score { i } else { best });
    let mut centres = vec![points[first]];
    let mut d2: Vec<f64> = points.iter().map(|p| (p - points[first]).norm_squared()).collect();
    while centres.len() < k {
        let total: f64 = d2.iter().sum();
        let next = if total > 0.0 {
            let mut target = rng.random::<f64>() * total;
            let mut chosen = d2.len() - 1;
            for (i, &d) in d2.iter().enumerate() {
                if target < d {
                    chosen = i;
                    break;
                }
                target -= d;
            }
            chosen
        } else {
            // All remaining points coincide with centres: any point (duplicates end as empty clusters).
            centres.len() % points.len()
        };
        centres.push(points[next]);
        for (d, p) in d2.iter_mut().zip(points) {
            *d = d.min((p - points[next]).norm_squared());
        }
    }
    centres
}

fn nearest_centre(centres: &[Vector3<f64>], p: &Vector3<f64>) -> usize {
    let mut best = (0, f64::INFINITY);
    for (c, centre) in centres.iter().enumerate() {
        let d = (p - centre).norm_squared();
        if d < best.1 {
            best = (c, d);
        }
    }
    best.0
}

fn farthest_from_centre(points: &[Vector3<f64>], assignment: &[usize], centres: &[Vector3<f64>]) -> Option<usize> {
    let mut best: Option<(usize, f64)> = None;
    for (i, (p, &c)) in points.iter().zip(assignment).enumerate() {
        let d = (p - centres[c]).norm_squared();
        if best.is_none_or(|(_, bd)| d > bd) {
            best = Some((i, d));
        }
    }
    best.map(|(i, _)| i)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand_distr::{Distribution, Normal};

    /// Three well-separated blobs of 40 points each (σ = 1 cm): k = 3 finds their means.
    #[test]
    fn three_known_clusters_are_found() {
        let truth = [Vector3::new(0.0, 0.0, 0.0), Vector3::new(1.0, 0.0, 0.1), Vector3::new(0.5, 1.0, -0.1)];
        let noise = Normal::new(0.0, 0.01).unwrap();
        let mut rng = rand::rngs::StdRng::seed_from_u64(9);
        let mut holds = Vec::new();
        for i in 0..120 {
            let centre = truth[i % 3];
            let p = centre + Vector3::new(noise.sample(&mut rng), noise.sample(&mut rng), noise.sample(&mut rng));
            holds.push(Hold::new(p, 1.0));
        }
        let clusters = kmeans(&holds, 3, 1).unwrap();
        assert_eq!(clusters.holds.len(), 3);
        for t in truth {
            let nearest = clusters.holds.iter().map(|h| (h.point() - t).norm()).fold(f64::INFINITY, f64::min);
            assert!(nearest < 0.005, "centre {t:?} missed by {nearest}");
        }
        // Every blob's members share one cluster, distinct per blob.
        for b in 0..3 {
            let c = clusters.assignment[b];
            assert!((b..120).step_by(3).all(|i| clusters.assignment[i] == c));
        }
        let ids: std::collections::BTreeSet<usize> = clusters.assignment[..3].iter().copied().collect();
        assert_eq!(ids.len(), 3);
        // Deterministic for a seed.
        assert_eq!(kmeans(&holds, 3, 1).unwrap(), clusters);
    }

    #[test]
    fn centres_are_score_weighted_and_scores_averaged() {
        let holds = vec![Hold::new(Vector3::new(0.0, 0.0, 0.0), 1.0), Hold::new(Vector3::new(0.3, 0.0, 0.0), 0.5)];
        // k = 1 with two points: the weighted mean 0.1 and the mean score 0.75.
        let clusters = kmeans(&holds, 1, 0).unwrap();
        assert!((clusters.holds[0].point() - Vector3::new(0.1, 0.0, 0.0)).norm() < 1e-12);
        assert!((clusters.holds[0].score - 0.75).abs() < 1e-12);
    }

    #[test]
    fn fewer_holds_than_k_and_duplicates() {
        let holds = [Hold::new(Vector3::new(1.0, 2.0, 3.0), 0.6); 5];
        let few = kmeans(&holds[..2], 30, 0).unwrap();
        assert_eq!(few.holds.len(), 2);
        // Ten identical points, k = 3: one non-empty cluster, no NaN.
        let same = vec![Hold::new(Vector3::new(1.0, 2.0, 3.0), 0.6); 10];
        let c = kmeans(&same, 3, 0).unwrap();
        assert!(c.holds.iter().all(|h| h.point().iter().all(|v| v.is_finite())));
        assert!(c.assignment.iter().all(|&a| a < c.holds.len()));
        assert_eq!(kmeans(&same, 0, 0), Err(RouteError::ZeroClusters));
        assert_eq!(kmeans(&[], 3, 0), Err(RouteError::NoHolds));
    }
}
