//! Solving the LM normal equations (IROS eq 36) on the leading `m × m` block of the fixed-size
//! `MAX_FREE` system: Cholesky factorisation, solve and inverse in fixed-size code per model size,
//! with nalgebra's algorithm and operation order so the values are bit-identical to the dense
//! `cholesky()` of the padded matrix.

use super::{Free, FreeMatrix, MAX_FREE};

/// `A⁻¹ b` for the symmetric positive definite leading `m × m` block of `a` (the free parameters;
/// zero beyond `m`), `None` if its Cholesky factorisation fails. Fixed-size code per model size
/// with nalgebra's Cholesky algorithm and operation order, so the values are bit-identical to
/// `a.cholesky()?.solve(b)` on the block padded with the identity as `normal::accumulate` returns it,
/// without the work on the padding.
pub(crate) fn solve_leading(m: usize, a: &FreeMatrix, b: &Free) -> Option<Free> {
    match m {
        3 => Cholesky::<3>::new(a).map(|c| c.solve(b)),
        4 => Cholesky::<4>::new(a).map(|c| c.solve(b)),
        5 => Cholesky::<5>::new(a).map(|c| c.solve(b)),
        6 => Cholesky::<6>::new(a).map(|c| c.solve(b)),
        _ => Cholesky::<MAX_FREE>::new(a).map(|c| c.solve(b)),
    }
}

/// The inverse of the leading `m × m` block of `a` (zero elsewhere), as [`solve_leading`] for
/// the unit vectors (nalgebra's `Cholesky::inverse`, bit-identical on the block).
pub(crate) fn inverse_leading(m: usize, a: &FreeMatrix) -> Option<FreeMatrix> {
    match m {
        3 => Cholesky::<3>::new(a).map(|c| c.inverse()),
        4 => Cholesky::<4>::new(a).map(|c| c.inverse()),
        5 => Cholesky::<5>::new(a).map(|c| c.inverse()),
        6 => Cholesky::<6>::new(a).map(|c| c.inverse()),
        _ => Cholesky::<MAX_FREE>::new(a).map(|c| c.inverse()),
    }
}

/// Lower Cholesky factor of a leading `M × M` block, column-major (`l[column][row]`).
struct Cholesky<const M: usize> {
    l: [[f64; M]; M],
}

impl<const M: usize> Cholesky<M> {
    /// nalgebra's right-looking factorisation of the lower triangle: column `j` minus `L_jk` times
    /// column `k` for `k < j`, then `√` of the diagonal (`None` unless positive) and the division
    /// of the column below it.
    #[inline(always)]
    fn new(a: &FreeMatrix) -> Option<Self> {
        let mut l = [[0.0; M]; M];
        for (c, column) in l.iter_mut().enumerate() {
            for (r, v) in column.iter_mut().enumerate().skip(c) {
                *v = a[(r, c)];
            }
        }
        // Column j is updated from the columns k < j of the same array: indices, not iterators.
        #[allow(clippy::needless_range_loop)]
        for j in 0..M {
            for k in 0..j {
                let factor = -l[k][j];
                for i in j..M {
                    // IEEE addition is commutative: the same value as nalgebra's `factor * l_k + l_j`.
                    l[j][i] += factor * l[k][i];
                }
            }
            let diag = l[j][j];
            if diag.is_nan() || diag <= 0.0 {
                return None;
            }
            let denom = diag.sqrt();
            l[j][j] = denom;
            for i in j + 1..M {
                l[j][i] /= denom;
            }
        }
        Some(Self { l })
    }

    /// `L Lᵀ x = b` over the first `M` entries (forward substitution by columns, back substitution
    /// by dot products in increasing index order, as nalgebra's `Cholesky::solve`).
    #[inline(always)]
    fn solve(&self, b: &Free) -> Free {
        let l = &self.l;
        let mut x = [0.0; M];
        for (i, v) in x.iter_mut().enumerate() {
            *v = b[i];
        }
        for i in 0..M {
            let coeff = x[i] / l[i][i];
            x[i] = coeff;
            for r in i + 1..M {
                x[r] += -coeff * l[i][r];
            }
        }
        for i in (0..M).rev() {
            let mut dot = 0.0;
            for k in i + 1..M {
                dot += l[i][k] * x[k];
            }
            x[i] = (x[i] - dot) / l[i][i];
        }
        Free::from_fn(|r, _| x.get(r).copied().unwrap_or(0.0))
    }

    /// The inverse of the block (zero beyond it), column by column as [`Cholesky::solve`].
    fn inverse(&self) -> FreeMatrix {
        let mut out = FreeMatrix::zeros();
        for c in 0..M {
            let e = Free::from_fn(|r, _| if r == c { 1.0 } else { 0.0 });
            out.set_column(c, &self.solve(&e));
        }
        out
    }
}
