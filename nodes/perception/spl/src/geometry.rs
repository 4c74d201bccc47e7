//! Pose geometry of IROS II: exponential/log maps, their Jacobians, 5-DoF rotations, pose chains and
//! covariance propagation.
//!
//! Rotations are orientation vectors `r` (exponential map, IROS eq 2); poses are `(r, t)` pairs (eq 1)
//! that take points from a local frame to a world frame (eq 3). Everything here is allocation-free
//! except the chain Jacobian, whose size depends on the chain length.

use nalgebra::{DMatrix, Matrix2x3, Matrix3, Matrix6, Rotation3, Vector2, Vector3};

/// Angle below which the series expansions of IROS footnotes 3 and 11 are used.
const SMALL_ANGLE: f64 = 1e-4;

/// Skew-symmetric cross-product matrix `[v]×` (IROS eq 2).
pub fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// Inverse of [`skew`]: the vector of the skew-symmetric part of `m`.
pub fn vee(m: &Matrix3<f64>) -> Vector3<f64> {
    Vector3::new(m[(2, 1)] - m[(1, 2)], m[(0, 2)] - m[(2, 0)], m[(1, 0)] - m[(0, 1)]) * 0.5
}

/// `(α, β) = (sin θ / θ, (1 − cos θ) / θ²)` of eq 2, with the small-angle series of footnote 3.
fn alpha_beta(theta: f64) -> (f64, f64) {
    if theta < SMALL_ANGLE {
        let t2 = theta * theta;
        (1.0 - t2 / 6.0, 0.5 - t2 / 24.0)
    } else {
        (theta.sin() / theta, (1.0 - theta.cos()) / (theta * theta))
    }
}

/// Exponential map `R(r)` by Rodrigues' formula (IROS eq 2).
pub fn exp_map(r: &Vector3<f64>) -> Matrix3<f64> {
    let (alpha, beta) = alpha_beta(r.norm());
    let k = skew(r);
    Matrix3::identity() + k * alpha + k * k * beta
}

/// `∂[r]×/∂r_i` (IROS eq 44).
fn skew_basis(i: usize) -> Matrix3<f64> {
    let mut e = Vector3::zeros();
    if let Some(v) = e.get_mut(i) {
        *v = 1.0;
    }
    skew(&e)
}

/// Jacobian of the exponential map `∂R/∂r` as three 3×3 matrices `∂R/∂r_x, ∂R/∂r_y, ∂R/∂r_z`
/// (IROS eq 44; finite as θ → 0 by the series of footnote 11).
pub fn exp_map_jacobian(r: &Vector3<f64>) -> [Matrix3<f64>; 3] {
    let theta = r.norm();
    let (alpha, beta) = alpha_beta(theta);
    // dα/dr = a r^T, dβ/dr = b r^T
    let (a, b) = if theta < SMALL_ANGLE {
        let t2 = theta * theta;
        (t2 / 30.0 - 1.0 / 3.0, t2 / 180.0 - 1.0 / 12.0)
    } else {
        let (s, c) = theta.sin_cos();
        let t3 = theta * theta * theta;
        ((theta * c - s) / t3, (theta * s + 2.0 * c - 2.0) / (t3 * theta))
    };
    let k = skew(r);
    let k2 = k * k;
    let mut out = [Matrix3::zeros(); 3];
    for (i, slot) in out.iter_mut().enumerate() {
        let dk = skew_basis(i);
        let dk2 = k * dk + dk * k;
        *slot = k * (a * r[i]) + dk * alpha + k2 * (b * r[i]) + dk2 * beta;
    }
    out
}

/// Right Jacobian of SO(3): `R(r + dr) ≈ R(r) exp([J_r(r) dr]×)`.
pub fn right_jacobian(r: &Vector3<f64>) -> Matrix3<f64> {
    let theta = r.norm();
    let (alpha, beta) = alpha_beta(theta);
    let gamma = if theta < SMALL_ANGLE { 1.0 / 6.0 - theta * theta / 120.0 } else { (1.0 - alpha) / (theta * theta) };
    let k = skew(r);
    Matrix3::identity() - k * beta + k * k * gamma
}

/// Inverse of [`right_jacobian`]: maps a right (body-frame) rotation perturbation `δ` to the change of
/// the orientation vector, `dr = J_r(r)⁻¹ δ`. Singular only at θ = π (the log map is, too).
pub fn right_jacobian_inverse(r: &Vector3<f64>) -> Matrix3<f64> {
    let theta = r.norm();
    let coef = if theta < SMALL_ANGLE {
        1.0 / 12.0 + theta * theta / 720.0
    } else {
        1.0 / (theta * theta) - (1.0 + theta.cos()) / (2.0 * theta * theta.sin())
    };
    let k = skew(r);
    Matrix3::identity() + k * 0.5 + k * k * coef
}

/// Grassia's canonical orientation vector with `‖r‖ ≤ π` (IROS II-B).
pub fn canonical(r: &Vector3<f64>) -> Vector3<f64> {
    let theta = r.norm();
    if theta <= std::f64::consts::PI {
        return *r;
    }
    let two_pi = 2.0 * std::f64::consts::PI;
    let wrapped = theta % two_pi;
    let axis = r / theta;
    if wrapped <= std::f64::consts::PI {
        axis * wrapped
    } else {
        axis * (wrapped - two_pi)
    }
}

/// Log map `r(R)` by the numerically stable algorithm of IROS Appendix II (result has `‖r‖ ≤ π`).
pub fn log_map(rot: &Matrix3<f64>) -> Vector3<f64> {
    const EPS_DELTA: f64 = 1e-8;
    const EPS_THETA: f64 = 1e-6;
    let v = Vector3::new(rot[(2, 1)] - rot[(1, 2)], rot[(0, 2)] - rot[(2, 0)], rot[(1, 0)] - rot[(0, 1)]);
    let tr = rot.trace();
    let c = (tr - 1.0) / 2.0;
    let s = v.norm() / 2.0;
    let theta = s.atan2(c);
    // i: index of the largest diagonal element; (i, j, k) a cyclic permutation of (x, y, z).
    let diag = [rot[(0, 0)], rot[(1, 1)], rot[(2, 2)]];
    let i = if diag[0] >= diag[1] && diag[0] >= diag[2] {
        0
    } else if diag[1] >= diag[2] {
        1
    } else {
        2
    };
    let j = (i + 1) % 3;
    let k = (i + 2) % 3;
    let delta = 1.0 + rot[(i, i)] - rot[(j, j)] - rot[(k, k)];
    if delta > EPS_DELTA && theta > EPS_THETA {
        let gamma = theta / (3.0 - tr).max(f64::MIN_POSITIVE).sqrt();
        let d = delta.sqrt();
        let mut r = Vector3::zeros();
        r[i] = d * gamma;
        r[j] = gamma * (rot[(j, i)] + rot[(i, j)]) / d;
        r[k] = gamma * (rot[(k, i)] + rot[(i, k)]) / d;
        if theta < std::f64::consts::PI - EPS_THETA {
            // Resolve the sign by testing the action of R on a vector orthogonal to r.
            let mut p = r.cross(&Vector3::z());
            if p.dot(&p) < 0.25 * r.dot(&r) {
                p = r.cross(&Vector3::y());
            }
            if (rot * p).dot(&r.cross(&p)) < 0.0 {
                r = -r;
            }
        }
        r
    } else {
        let alpha = if theta > EPS_THETA { s / theta } else { 1.0 - theta * theta / 6.0 };
        v / (2.0 * alpha)
    }
}

/// Rotation whose third column (local z axis) is `normal`, with zero twist: `R([r_xy 0])` (eq 6–8).
pub fn rotation_from_normal(normal: &Vector3<f64>) -> Matrix3<f64> {
    let r = r_xy_from_normal(normal);
    exp_map(&Vector3::new(r.x, r.y, 0.0))
}

/// `r_xy` for the unit local z axis `z_l` (IROS eq 8).
pub fn r_xy_from_normal(z_l: &Vector3<f64>) -> Vector2<f64> {
    let cross = Vector3::z().cross(z_l);
    let sin = cross.norm();
    let theta = sin.atan2(z_l.z);
    if std::f64::consts::PI - theta < 1e-9 {
        // θ_xy ≈ π: rotate by π about x (any in-plane axis is valid).
        return Vector2::new(std::f64::consts::PI, 0.0);
    }
    let alpha = if theta < SMALL_ANGLE { 1.0 - theta * theta / 6.0 } else { sin / theta };
    Vector2::new(cross.x / alpha, cross.y / alpha)
}

/// 5-DoF orientation `r_xy(r)` with `R([r_xy 0]) ẑ = R(r) ẑ` (IROS eq 7–8).
pub fn r_xy(r: &Vector3<f64>) -> Vector2<f64> {
    let z_l = exp_map(r).column(2).into_owned();
    let theta = Vector3::z().cross(&z_l).norm().atan2(z_l.z);
    if std::f64::consts::PI - theta < 1e-6 {
        return Vector2::new(r.x, r.y);
    }
    r_xy_from_normal(&z_l)
}

/// Jacobian `∂r_xy/∂r` (2×3) of [`r_xy`] (IROS eq 45), derived by the chain rule through
/// `z_l = R(r) ẑ`: `r_xy = (θ_xy / sin θ_xy) Π_xy (ẑ × z_l)`.
pub fn r_xy_jacobian(r: &Vector3<f64>) -> Matrix2x3<f64> {
    let rot = exp_map(r);
    let z_l = rot.column(2).into_owned();
    let dr = exp_map_jacobian(r);
    let v = Vector3::z().cross(&z_l);
    let s = v.norm();
    let c = z_l.z;
    let theta = s.atan2(c);
    if std::f64::consts::PI - theta < 1e-6 {
        return Matrix2x3::new(1.0, 0.0, 0.0, 0.0, 1.0, 0.0);
    }
    let mut out = Matrix2x3::zeros();
    for i in 0..3 {
        let dz = dr[i] * Vector3::z();
        let dv = Vector3::z().cross(&dz);
        let col = if s < 1e-6 {
            // θ/s → 1 + θ²/6: first-order term only.
            dv
        } else {
            let ds = v.dot(&dv) / s;
            let dc = dz.z;
            let dtheta = c * ds - s * dc;
            let ratio = theta / s;
            let dratio = dtheta / s - theta * ds / (s * s);
            dv * ratio + v * dratio
        };
        out[(0, i)] = col.x;
        out[(1, i)] = col.y;
    }
    out
}

/// A rigid pose `(r, t)` (IROS eq 1): takes points from its local frame to the parent frame.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Pose {
    /// Orientation vector (exponential map).
    pub r: Vector3<f64>,
    /// Translation (origin of the local frame in the parent frame).
    pub t: Vector3<f64>,
}

impl Pose {
    /// Pose from its orientation vector and translation.
    pub fn new(r: Vector3<f64>, t: Vector3<f64>) -> Self {
        Self { r, t }
    }

    /// Identity pose.
    pub fn identity() -> Self {
        Self { r: Vector3::zeros(), t: Vector3::zeros() }
    }

    /// Rotation matrix `R(r)`.
    pub fn rotation(&self) -> Matrix3<f64> {
        exp_map(&self.r)
    }

    /// Forward transform `X_f(q_l) = R q_l + t` (eq 3).
    pub fn transform_forward(&self, q_local: &Vector3<f64>) -> Vector3<f64> {
        self.rotation() * q_local + self.t
    }

    /// Reverse transform `X_r(q_w) = Rᵀ(q_w − t)` (eq 4).
    pub fn transform_reverse(&self, q_world: &Vector3<f64>) -> Vector3<f64> {
        self.rotation().transpose() * (q_world - self.t)
    }

    /// Inverse pose `(−r, −Rᵀ t)` (eq 5).
    pub fn inverse(&self) -> Self {
        Self { r: -self.r, t: -(self.rotation().transpose() * self.t) }
    }

    /// `∂X_r/∂r` (3×3) of the reverse transform (eq 11): columns `∂Rᵀ/∂r_i (q_w − t)`.
    pub fn reverse_jacobian_r(&self, q_world: &Vector3<f64>) -> Matrix3<f64> {
        let d = exp_map_jacobian(&self.r);
        let diff = q_world - self.t;
        Matrix3::from_columns(&[d[0].transpose() * diff, d[1].transpose() * diff, d[2].transpose() * diff])
    }
}

/// One link of a pose chain (eq 9): a pose used forward (`φ = +1`) or inverted (`φ = −1`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ChainLink {
    /// The pose `(r_j, t_j)`.
    pub pose: Pose,
    /// `true` for `φ_j = −1` (apply `X_r`), `false` for `φ_j = +1` (apply `X_f`).
    pub inverted: bool,
}

impl ChainLink {
    fn rotation(&self) -> Matrix3<f64> {
        let r = self.pose.rotation();
        if self.inverted {
            r.transpose()
        } else {
            r
        }
    }

    fn apply(&self, q: &Vector3<f64>) -> Vector3<f64> {
        if self.inverted {
            self.pose.transform_reverse(q)
        } else {
            self.pose.transform_forward(q)
        }
    }
}

/// Composite pose of a chain (eq 10). `links[0]` is link 1 (applied first, at the patch end),
/// `links[n-1]` is link n (next to the base): `R_c = R_n ⋯ R_1`, `t_c = (X_n ∘ ⋯ ∘ X_1)(0)`.
pub fn compose_chain(links: &[ChainLink]) -> Pose {
    let mut rot = Matrix3::identity();
    let mut t = Vector3::zeros();
    for link in links {
        rot = link.rotation() * rot;
        t = link.apply(&t);
    }
    Pose { r: log_map(&rot), t }
}

/// Chain Jacobian `J_c` (6 × 6n) of eq 46: columns `6j..6j+6` are `∂(r_c, t_c)/∂(r_j, t_j)` for
/// `links[j]`. `∂r_c/∂R_c` is applied on the tangent space of SO(3) as `J_r(r_c)⁻¹ vee(R_cᵀ dR_c)`,
/// which equals Appendix II's `∂r/∂R` contracted with the (tangent) `dR_c` of eq 46.
pub fn chain_jacobian(links: &[ChainLink]) -> DMatrix<f64> {
    let n = links.len();
    let mut jac = DMatrix::zeros(6, 6 * n);
    let rots: Vec<Matrix3<f64>> = links.iter().map(ChainLink::rotation).collect();
    let composite = compose_chain(links);
    let rc = composite.rotation();
    let jr_inv = right_jacobian_inverse(&composite.r);
    for j in 0..n {
        let (Some(link), Some(rot_j)) = (links.get(j), rots.get(j)) else { continue };
        // R_r = R_{j-1} ⋯ R_1, t_r = (X_{j-1} ∘ ⋯ ∘ X_1)(0); R_l = R_n ⋯ R_{j+1}.
        let mut r_right = Matrix3::identity();
        let mut t_r = Vector3::zeros();
        for (l, rl) in links.iter().zip(rots.iter()).take(j) {
            r_right = rl * r_right;
            t_r = l.apply(&t_r);
        }
        let mut r_left = Matrix3::identity();
        for rl in rots.iter().skip(j + 1) {
            r_left = rl * r_left;
        }
        let d = exp_map_jacobian(&link.pose.r);
        for i in 0..3 {
            let d_rot_j = if link.inverted { d[i].transpose() } else { d[i] };
            let d_rc = r_left * d_rot_j * r_right;
            let dr = jr_inv * vee(&(rc.transpose() * d_rc));
            let dt = if link.inverted { r_left * d_rot_j * (t_r - link.pose.t) } else { r_left * d_rot_j * t_r };
            for row in 0..3 {
                jac[(row, 6 * j + i)] = dr[row];
                jac[(row + 3, 6 * j + i)] = dt[row];
            }
        }
        let dt_dt = if link.inverted { -(r_left * rot_j) } else { r_left };
        for row in 0..3 {
            for col in 0..3 {
                jac[(row + 3, 6 * j + 3 + col)] = dt_dt[(row, col)];
            }
        }
    }
    jac
}

/// Covariance of the composite pose, `Σ_c = J_c S J_cᵀ` with `S = diag(S_j)` (eq 42).
/// `covariances[j]` is the 6×6 covariance of `links[j]` over `(r_j, t_j)`.
/// Returns `None` if the slices have different lengths.
pub fn propagate_chain_covariance(links: &[ChainLink], covariances: &[Matrix6<f64>]) -> Option<Matrix6<f64>> {
    if links.len() != covariances.len() {
        return None;
    }
    let jac = chain_jacobian(links);
    let mut out = Matrix6::zeros();
    for (j, s) in covariances.iter().enumerate() {
        let block = jac.fixed_view::<6, 6>(0, 6 * j);
        out += block * s * block.transpose();
    }
    Some(out)
}

/// 5-DoF covariance `Σ_c5 = J_5 Σ_c J_5ᵀ` over `(r_xy, t)` (eq 43).
pub fn covariance_to_5dof(r: &Vector3<f64>, sigma6: &Matrix6<f64>) -> nalgebra::Matrix5<f64> {
    let mut j5 = nalgebra::SMatrix::<f64, 5, 6>::zeros();
    j5.fixed_view_mut::<2, 3>(0, 0).copy_from(&r_xy_jacobian(r));
    j5.fixed_view_mut::<3, 3>(2, 3).copy_from(&Matrix3::identity());
    j5 * sigma6 * j5.transpose()
}

/// Rotation nearest to `m` in the Frobenius sense (SVD, reflection removed).
pub fn nearest_rotation(m: &Matrix3<f64>) -> Option<Rotation3<f64>> {
    let svd = m.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let sign = (u * v_t).determinant().signum();
    let correction = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, sign));
    Some(Rotation3::from_matrix_unchecked(u * correction * v_t))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn random_r(rng: &mut rand::rngs::StdRng, max_angle: f64) -> Vector3<f64> {
        let axis = Vector3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0));
        axis.normalize() * rng.random_range(0.0..max_angle)
    }

    #[test]
    // 3.14 below is a rotation-angle bound just under π, not an approximation of π.
    #[allow(clippy::approx_constant)]
    fn exp_map_is_rotation_and_log_round_trips() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        let mut cases: Vec<Vector3<f64>> = (0..200).map(|_| random_r(&mut rng, 3.14)).collect();
        cases.push(Vector3::zeros());
        cases.push(Vector3::new(1e-9, -2e-9, 3e-10));
        cases.push(Vector3::new(1e-5, 0.0, 0.0));
        cases.push(Vector3::new(0.0, std::f64::consts::PI - 1e-7, 0.0));
        cases.push(Vector3::new(0.3, 0.4, 0.5).normalize() * (std::f64::consts::PI - 1e-9));
        for r in cases {
            let rot = exp_map(&r);
            assert!((rot.transpose() * rot - Matrix3::identity()).norm() < 1e-12);
            assert!((rot.determinant() - 1.0).abs() < 1e-12);
            let back = log_map(&rot);
            assert!((exp_map(&back) - rot).norm() < 1e-9, "r {r:?} back {back:?}");
            assert!(back.norm() <= std::f64::consts::PI + 1e-12);
            if r.norm() < 3.1 {
                assert!((back - r).norm() < 1e-7, "r {r:?} back {back:?}");
            }
        }
    }

    #[test]
    fn canonical_keeps_rotation() {
        let r = Vector3::new(4.0, -1.0, 2.0);
        let c = canonical(&r);
        assert!(c.norm() <= std::f64::consts::PI);
        assert!((exp_map(&c) - exp_map(&r)).norm() < 1e-12);
    }

    #[test]
    fn exp_map_jacobian_matches_finite_differences() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(2);
        let mut cases: Vec<Vector3<f64>> = (0..50).map(|_| random_r(&mut rng, 3.0)).collect();
        cases.push(Vector3::zeros());
        cases.push(Vector3::new(3e-5, -1e-5, 2e-5));
        for r in cases {
            let analytic = exp_map_jacobian(&r);
            for i in 0..3 {
                let mut e = Vector3::zeros();
                e[i] = 1e-6;
                let fd = (exp_map(&(r + e)) - exp_map(&(r - e))) / 2e-6;
                assert!((fd - analytic[i]).norm() < 1e-7, "i {i} r {r:?}");
            }
        }
    }

    #[test]
    fn right_jacobian_inverse_is_inverse_and_correct() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        for _ in 0..50 {
            let r = random_r(&mut rng, 2.5);
            let jr = right_jacobian(&r);
            assert!((jr * right_jacobian_inverse(&r) - Matrix3::identity()).norm() < 1e-10);
            let dr = Vector3::new(1e-6, -2e-6, 0.5e-6);
            let lhs = exp_map(&(r + dr));
            let rhs = exp_map(&r) * exp_map(&(jr * dr));
            assert!((lhs - rhs).norm() < 1e-11);
        }
    }

    #[test]
    fn r_xy_keeps_normal_and_jacobian_matches_fd() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(4);
        for _ in 0..50 {
            let r = random_r(&mut rng, 2.8);
            let rxy = r_xy(&r);
            let z1 = exp_map(&Vector3::new(rxy.x, rxy.y, 0.0)).column(2).into_owned();
            let z2 = exp_map(&r).column(2).into_owned();
            assert!((z1 - z2).norm() < 1e-9);
            let jac = r_xy_jacobian(&r);
            for i in 0..3 {
                let mut e = Vector3::zeros();
                e[i] = 1e-6;
                let fd = (r_xy(&(r + e)) - r_xy(&(r - e))) / 2e-6;
                assert!((fd - jac.column(i)).norm() < 1e-6, "r {r:?} i {i} fd {fd:?} an {:?}", jac.column(i));
            }
        }
        // Near zero tilt.
        let r = Vector3::new(1e-8, -2e-8, 0.3);
        let jac = r_xy_jacobian(&r);
        for i in 0..3 {
            let mut e = Vector3::zeros();
            e[i] = 1e-6;
            let fd = (r_xy(&(r + e)) - r_xy(&(r - e))) / 2e-6;
            assert!((fd - jac.column(i)).norm() < 1e-5);
        }
    }

    #[test]
    fn pose_inverse_and_transforms() {
        let pose = Pose::new(Vector3::new(0.2, -0.5, 1.0), Vector3::new(1.0, 2.0, -3.0));
        let q = Vector3::new(0.3, 0.1, -0.7);
        let w = pose.transform_forward(&q);
        assert!((pose.transform_reverse(&w) - q).norm() < 1e-12);
        assert!((pose.inverse().transform_forward(&w) - q).norm() < 1e-12);
        let jac = pose.reverse_jacobian_r(&w);
        for i in 0..3 {
            let mut e = Vector3::zeros();
            e[i] = 1e-6;
            let p1 = Pose::new(pose.r + e, pose.t);
            let p0 = Pose::new(pose.r - e, pose.t);
            let fd = (p1.transform_reverse(&w) - p0.transform_reverse(&w)) / 2e-6;
            assert!((fd - jac.column(i)).norm() < 1e-8);
        }
    }

    fn chain_params(links: &[ChainLink]) -> Vec<f64> {
        links.iter().flat_map(|l| l.pose.r.iter().chain(l.pose.t.iter()).copied().collect::<Vec<_>>()).collect()
    }

    fn chain_from_params(template: &[ChainLink], p: &[f64]) -> Vec<ChainLink> {
        template
            .iter()
            .enumerate()
            .map(|(j, l)| ChainLink {
                pose: Pose::new(Vector3::new(p[6 * j], p[6 * j + 1], p[6 * j + 2]), Vector3::new(p[6 * j + 3], p[6 * j + 4], p[6 * j + 5])),
                inverted: l.inverted,
            })
            .collect()
    }

    #[test]
    fn chain_composition_and_jacobian_match_fd() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let links: Vec<ChainLink> = (0..3)
            .map(|j| ChainLink {
                pose: Pose::new(
                    random_r(&mut rng, 1.0),
                    Vector3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)),
                ),
                inverted: j == 1,
            })
            .collect();
        // Composition equals applying the links in order.
        let q = Vector3::new(0.1, 0.2, 0.3);
        let mut expected = q;
        for l in &links {
            expected = l.apply(&expected);
        }
        let c = compose_chain(&links);
        assert!((c.transform_forward(&q) - expected).norm() < 1e-12);
        let jac = chain_jacobian(&links);
        let p = chain_params(&links);
        for col in 0..p.len() {
            let mut pp = p.clone();
            let mut pm = p.clone();
            pp[col] += 1e-6;
            pm[col] -= 1e-6;
            let cp = compose_chain(&chain_from_params(&links, &pp));
            let cm = compose_chain(&chain_from_params(&links, &pm));
            let fd_r = (cp.r - cm.r) / 2e-6;
            let fd_t = (cp.t - cm.t) / 2e-6;
            for row in 0..3 {
                assert!((fd_r[row] - jac[(row, col)]).abs() < 1e-6, "r row {row} col {col}");
                assert!((fd_t[row] - jac[(row + 3, col)]).abs() < 1e-6, "t row {row} col {col}");
            }
        }
        let covs = vec![Matrix6::identity() * 1e-4; 3];
        let sigma = propagate_chain_covariance(&links, &covs).unwrap_or_else(Matrix6::zeros);
        assert!(sigma.symmetric_eigenvalues().min() > 0.0);
        let s5 = covariance_to_5dof(&c.r, &sigma);
        assert!(s5.symmetric_eigenvalues().min() > 0.0);
        assert!(propagate_chain_covariance(&links, &covs[..2]).is_none());
    }
}
