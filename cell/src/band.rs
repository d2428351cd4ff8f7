//! LU with partial pivoting of a banded matrix (LAPACK's `dgbtf2`/`dgbtrs` scheme), the linear
//! solver of the cell's BDF integration.
//!
//! The cell's Jacobian couples cell i to cells i-2..=i+2 only: with three unknowns per cell it
//! has 8 sub- and 8 super-diagonals whatever the cell count. A general sparse LU (faer's, with
//! its fill-reducing ordering and supernodes) spent ~3 ms per solve of 3e4 unknowns on it; the
//! banded factorisation costs n kl (kl + ku) and the solve n (2 kl + ku) flops, linear in the
//! cells, so 1e5 cells (3e5 unknowns) stay affordable. Partial pivoting keeps it stable on the
//! mixed differential / algebraic rows; it only ever fills the kl extra super-diagonals LAPACK
//! reserves for the row swaps.
//!
//! Storage: column j holds rows j - (kl + ku) ..= j + kl at `ab[j * ld + (kl + ku + i - j)]`,
//! ld = 2 kl + ku + 1.

/// A banded matrix and, after [`BandLu::factor`], its LU factors.
#[derive(Debug, Clone, Default)]
pub struct BandLu {
    n: usize,
    kl: usize,
    ku: usize,
    ld: usize,
    ab: Vec<f64>,
    ipiv: Vec<usize>,
    /// The first column whose pivot was zero (the matrix is singular), if any.
    singular: Option<usize>,
    /// The factors packed for the solves, column by column: `l[j kl + r]` = L(j+1+r, j)
    /// (r < kl), `u[j (kd+1) + r]` = U(j - kd + r, j) (r <= kd = kl + ku, the last the
    /// diagonal). A solve then streams each factor once and no padding: in `ab` a column's
    /// L and U share cache lines with the next column's, and the forward and backward sweeps
    /// each read all of `ab` (the solves are bound by that memory traffic, not by flops).
    l: Vec<f64>,
    u: Vec<f64>,
}

impl BandLu {
    /// An n x n matrix of zeros with `kl` sub- and `ku` super-diagonals.
    pub fn new(n: usize, kl: usize, ku: usize) -> BandLu {
        let ld = 2 * kl + ku + 1;
        BandLu { n, kl, ku, ld, ab: vec![0.0; n * ld], ipiv: vec![0; n], singular: None, l: vec![], u: vec![] }
    }

    /// The bandwidths (lower, upper) of a CSC pattern.
    pub fn bandwidths(col_ptr: &[usize], row_idx: &[usize]) -> (usize, usize) {
        let (mut kl, mut ku) = (0, 0);
        for j in 0..col_ptr.len().saturating_sub(1) {
            for &i in &row_idx[col_ptr[j]..col_ptr[j + 1]] {
                kl = kl.max(i.saturating_sub(j));
                ku = ku.max(j.saturating_sub(i));
            }
        }
        (kl, ku)
    }

    pub fn n(&self) -> usize {
        self.n
    }

    fn at(&self, i: usize, j: usize) -> usize {
        j * self.ld + (self.kl + self.ku + i - j)
    }

    /// Loads a CSC matrix (its entries must lie within the band) and factorises it.
    pub fn factor_csc(&mut self, col_ptr: &[usize], row_idx: &[usize], val: &[f64]) {
        self.ab.iter_mut().for_each(|v| *v = 0.0);
        for j in 0..self.n {
            for k in col_ptr[j]..col_ptr[j + 1] {
                let i = row_idx[k];
                debug_assert!(i + self.ku >= j && i <= j + self.kl, "entry ({i}, {j}) outside the band");
                let at = self.at(i, j);
                self.ab[at] = val[k];
            }
        }
        self.factor();
        self.pack();
    }

    /// Copies the factors out of `ab` into the packed `l` and `u` the solves read.
    fn pack(&mut self) {
        let (n, kl, ld) = (self.n, self.kl, self.ld);
        let kd = self.kl + self.ku;
        self.l.clear();
        self.u.clear();
        self.l.reserve(n * kl);
        self.u.reserve(n * (kd + 1));
        for j in 0..n {
            let col = j * ld;
            // Rows j+1..=j+kl (those past n - 1 are zero in ab) and rows j-kd..=j (those
            // above row 0 are zero in ab).
            self.l.extend_from_slice(&self.ab[col + kd + 1..col + kd + 1 + kl]);
            self.u.extend_from_slice(&self.ab[col..=col + kd]);
        }
    }

    /// In-place LU with partial pivoting: P A = L U. Every inner loop runs over a contiguous
    /// piece of one column (the multipliers of column j, rows j+1..=j+kl; column k's rows in
    /// the same range).
    fn factor(&mut self) {
        let (n, kl, ku, ld) = (self.n, self.kl, self.ku, self.ld);
        let diag = kl + ku;
        self.singular = None;
        for j in 0..n {
            let below = kl.min(n - 1 - j);
            let col = j * ld + diag;
            let mut p = 0;
            let mut best = self.ab[col].abs();
            for (r, v) in self.ab[col + 1..=col + below].iter().enumerate() {
                if v.abs() > best {
                    (p, best) = (r + 1, v.abs());
                }
            }
            self.ipiv[j] = j + p;
            if best == 0.0 {
                self.singular.get_or_insert(j);
                continue;
            }
            let reach = (j + kl + ku).min(n - 1);
            if p != 0 {
                for k in j..=reach {
                    let (a, b) = (self.at(j, k), self.at(j + p, k));
                    self.ab.swap(a, b);
                }
            }
            let inv = 1.0 / self.ab[col];
            self.ab[col + 1..=col + below].iter_mut().for_each(|v| *v *= inv);
            for k in j + 1..=reach {
                let u = self.ab[self.at(j, k)];
                if u != 0.0 {
                    // Column k, rows j+1..=j+below, and column j's multipliers (k > j: disjoint).
                    let (left, right) = self.ab.split_at_mut(k * ld);
                    let l = &left[col + 1..=col + below];
                    let start = diag + j + 1 - k;
                    for (a, l) in right[start..start + below].iter_mut().zip(l) {
                        *a -= l * u;
                    }
                }
            }
        }
    }

    /// The first zero pivot's column when the matrix is singular.
    pub fn singular(&self) -> Option<usize> {
        self.singular
    }

    /// Solves A x = b in place.
    pub fn solve(&self, b: &mut [f64]) {
        self.solve_many(&mut [b]);
    }

    /// Solves A x_k = b_k in place for every k in one sweep over the factors (for each vector,
    /// the same operations in the same order as [`BandLu::solve`], so bit for bit its result).
    pub fn solve_many(&self, bs: &mut [&mut [f64]]) {
        let (n, kl) = (self.n, self.kl);
        let kd = kl + self.ku;
        let w = kd + 1;
        debug_assert!(bs.iter().all(|b| b.len() == n));
        for j in 0..n {
            let below = kl.min(n - 1 - j);
            let l = &self.l[j * kl..j * kl + below];
            let p = self.ipiv[j];
            for b in bs.iter_mut() {
                b.swap(j, p);
                let bj = b[j];
                if bj != 0.0 {
                    for (bi, l) in b[j + 1..=j + below].iter_mut().zip(l) {
                        *bi -= l * bj;
                    }
                }
            }
        }
        for j in (0..n).rev() {
            let above = kd.min(j);
            let col = &self.u[j * w + kd - above..=j * w + kd];
            let (u, d) = col.split_at(above);
            let d = d[0];
            for b in bs.iter_mut() {
                b[j] /= d;
                let bj = b[j];
                for (bi, u) in b[j - above..j].iter_mut().zip(u) {
                    *bi -= u * bj;
                }
            }
        }
    }

    /// Solves A^T x = b in place.
    pub fn solve_transpose(&self, b: &mut [f64]) {
        let (n, kl, ku, ld) = (self.n, self.kl, self.ku, self.ld);
        let diag = kl + ku;
        // U^T y = b, then L^T z = y with the swaps undone in reverse.
        for j in 0..n {
            let above = diag.min(j);
            let u = &self.ab[j * ld + diag - above..j * ld + diag];
            let s: f64 = b[j - above..j].iter().zip(u).map(|(bi, u)| bi * u).sum();
            b[j] = (b[j] - s) / self.ab[j * ld + diag];
        }
        for j in (0..n).rev() {
            let below = kl.min(n - 1 - j);
            let l = &self.ab[j * ld + diag + 1..=j * ld + diag + below];
            let s: f64 = b[j + 1..=j + below].iter().zip(l).map(|(bi, l)| bi * l).sum();
            b[j] -= s;
            b.swap(j, self.ipiv[j]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A random banded matrix in CSC with its dense copy (zero diagonal entries here and there,
    /// so that pivoting is needed).
    fn random(n: usize, kl: usize, ku: usize, seed: u64) -> (Vec<usize>, Vec<usize>, Vec<f64>, Vec<Vec<f64>>) {
        let mut s = seed;
        let mut next = || {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
        };
        let mut dense = vec![vec![0.0; n]; n];
        let (mut col_ptr, mut row_idx, mut val) = (vec![0], Vec::new(), Vec::new());
        for j in 0..n {
            for i in j.saturating_sub(ku)..=(j + kl).min(n - 1) {
                // (A triangular matrix, kl or ku = 0, with a zero diagonal would be singular.)
                let v = if i == j && j % 4 == 1 && kl > 0 && ku > 0 { 0.0 } else { next() };
                dense[i][j] = v;
                row_idx.push(i);
                val.push(v);
            }
            col_ptr.push(row_idx.len());
        }
        (col_ptr, row_idx, val, dense)
    }

    #[test]
    fn solves_banded_systems_with_pivoting_and_their_transposes() {
        for (n, kl, ku) in [(1, 0, 0), (7, 1, 2), (40, 8, 8), (33, 3, 0), (25, 0, 4)] {
            let (cp, ri, v, a) = random(n, kl, ku, n as u64);
            assert_eq!(BandLu::bandwidths(&cp, &ri), (kl.min(n - 1), ku.min(n - 1)));
            let mut lu = BandLu::new(n, kl, ku);
            lu.factor_csc(&cp, &ri, &v);
            assert_eq!(lu.singular(), None);
            let x: Vec<f64> = (0..n).map(|i| 1.0 + i as f64 * 0.25).collect();
            let ax: Vec<f64> = (0..n).map(|i| (0..n).map(|j| a[i][j] * x[j]).sum()).collect();
            let atx: Vec<f64> = (0..n).map(|i| (0..n).map(|j| a[j][i] * x[j]).sum()).collect();
            let (mut b, mut bt) = (ax.clone(), atx.clone());
            lu.solve(&mut b);
            lu.solve_transpose(&mut bt);
            // Backward stability (what partial pivoting guarantees, whatever the conditioning):
            // the residual is round-off of |A| |x|.
            for (sol, rhs, t) in [(&b, &ax, false), (&bt, &atx, true)] {
                for i in 0..n {
                    let (mut r, mut scale) = (rhs[i], 0.0f64);
                    for j in 0..n {
                        let aij = if t { a[j][i] } else { a[i][j] };
                        r -= aij * sol[j];
                        scale += (aij * sol[j]).abs();
                    }
                    assert!(r.abs() <= 1e-12 * scale.max(1.0), "n {n} kl {kl} ku {ku} transpose {t}: residual {r:e} of row {i}");
                }
            }
        }
    }

    #[test]
    fn solving_several_right_hand_sides_at_once_is_bitwise_solving_each() {
        for (n, kl, ku) in [(40, 8, 8), (7, 1, 2), (33, 3, 0)] {
            let (cp, ri, v, _) = random(n, kl, ku, 3 + n as u64);
            let mut lu = BandLu::new(n, kl, ku);
            lu.factor_csc(&cp, &ri, &v);
            let rhs: Vec<Vec<f64>> = (0..3).map(|k| (0..n).map(|i| ((i * 7 + k * 13) as f64).sin()).collect()).collect();
            let mut many = rhs.clone();
            lu.solve_many(&mut many.iter_mut().map(|b| b.as_mut_slice()).collect::<Vec<_>>());
            for (b, m) in rhs.iter().zip(&many) {
                let mut one = b.clone();
                lu.solve(&mut one);
                assert_eq!(one.iter().map(|v| v.to_bits()).collect::<Vec<_>>(), m.iter().map(|v| v.to_bits()).collect::<Vec<_>>());
                assert!(one.iter().zip(b).any(|(x, b)| x != b), "a solve changed something");
            }
        }
    }

    #[test]
    fn a_singular_matrix_is_reported_with_its_column() {
        // Column 2 of a tridiagonal matrix is zero.
        let n: usize = 5;
        let (mut cp, mut ri, mut v) = (vec![0], Vec::new(), Vec::new());
        for j in 0..n {
            for i in j.saturating_sub(1)..=(j + 1).min(n - 1) {
                ri.push(i);
                v.push(if j == 2 { 0.0 } else { 1.0 + (i + j) as f64 });
            }
            cp.push(ri.len());
        }
        let mut lu = BandLu::new(n, 1, 1);
        lu.factor_csc(&cp, &ri, &v);
        assert_eq!(lu.singular(), Some(2));
    }
}
