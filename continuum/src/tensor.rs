//! Small 3x3 tensor helpers. Every point carries full 3x3 velocity gradients, deformation
//! gradients and stresses whatever the dimension: a 1D elastic closure still has a full
//! diagonal stress. Vectors in `D` dimensions embed into 3D with zeros.
//!
//! The storage stays a plain row-major array (`[[f64; 3]; 3]`): it is the layout of the
//! per-point arrays, of checkpoints (serde) and of the wire's packed tensor columns, and the
//! closed-form products, determinant and cofactor inverse below are summed in a fixed order
//! that the pinned digests depend on. Iterative algorithms come from nalgebra (the symmetric
//! eigensolver here, the SVD and polar decomposition of `kinematics`, the moment matrices of
//! `mls`); see ARCHITECTURE.md, "Linear algebra".

/// A 3x3 tensor, row major: `t[i][j]`.
pub type Mat3 = [[f64; 3]; 3];

pub const IDENTITY: Mat3 = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
pub const ZERO: Mat3 = [[0.0; 3]; 3];

pub fn mul(a: &Mat3, b: &Mat3) -> Mat3 {
    let mut c = ZERO;
    for i in 0..3 {
        for j in 0..3 {
            c[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
        }
    }
    c
}

pub fn transpose(a: &Mat3) -> Mat3 {
    let mut t = ZERO;
    for i in 0..3 {
        for j in 0..3 {
            t[i][j] = a[j][i];
        }
    }
    t
}

pub fn det(a: &Mat3) -> f64 {
    a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1]) - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
        + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0])
}

/// Inverse, or `None` when the determinant is not a normal positive or negative number.
pub fn inverse(a: &Mat3) -> Option<Mat3> {
    let d = det(a);
    if !d.is_normal() {
        return None;
    }
    let mut inv = ZERO;
    for i in 0..3 {
        for j in 0..3 {
            let (i1, i2, j1, j2) = ((j + 1) % 3, (j + 2) % 3, (i + 1) % 3, (i + 2) % 3);
            inv[i][j] = (a[i1][j1] * a[i2][j2] - a[i1][j2] * a[i2][j1]) / d;
        }
    }
    Some(inv)
}

/// Eigenvalues and unit eigenvectors (columns of the returned matrix) of a symmetric tensor
/// (nalgebra's symmetric QR eigensolver; only the lower triangle of `a` is read).
pub fn sym_eigen(a: &Mat3) -> ([f64; 3], Mat3) {
    let e = nalgebra::SymmetricEigen::new(nalgebra::Matrix3::from_fn(|i, j| a[i][j]));
    let v = &e.eigenvectors;
    ([e.eigenvalues[0], e.eigenvalues[1], e.eigenvalues[2]], std::array::from_fn(|i| std::array::from_fn(|j| v[(i, j)])))
}

pub fn trace(a: &Mat3) -> f64 {
    a[0][0] + a[1][1] + a[2][2]
}

/// Symmetric part (rate of deformation D from a velocity gradient L).
pub fn sym(a: &Mat3) -> Mat3 {
    let mut s = ZERO;
    for i in 0..3 {
        for j in 0..3 {
            s[i][j] = 0.5 * (a[i][j] + a[j][i]);
        }
    }
    s
}

/// Double contraction a:b.
pub fn ddot(a: &Mat3, b: &Mat3) -> f64 {
    let mut s = 0.0;
    for i in 0..3 {
        for j in 0..3 {
            s += a[i][j] * b[i][j];
        }
    }
    s
}

pub fn add_scaled(a: &Mat3, b: &Mat3, s: f64) -> Mat3 {
    let mut c = *a;
    for i in 0..3 {
        for j in 0..3 {
            c[i][j] += s * b[i][j];
        }
    }
    c
}

/// Voigt order used in every output: xx, yy, zz, xy, xz, yz.
pub fn to_voigt(a: &Mat3) -> [f64; 6] {
    [a[0][0], a[1][1], a[2][2], a[0][1], a[0][2], a[1][2]]
}

pub fn is_finite(a: &Mat3) -> bool {
    a.iter().flatten().all(|v| v.is_finite())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inverse_and_eigen_reproduce_the_tensor() {
        let a: Mat3 = [[2.0, 0.3, -0.1], [0.3, -1.0, 0.4], [-0.1, 0.4, 0.5]];
        let inv = inverse(&a).expect("regular");
        let id = mul(&a, &inv);
        for i in 0..3 {
            for j in 0..3 {
                assert!((id[i][j] - IDENTITY[i][j]).abs() < 1e-14);
            }
        }
        let (l, v) = sym_eigen(&a);
        // A = V diag(l) V^T.
        let mut back = ZERO;
        for k in 0..3 {
            for i in 0..3 {
                for j in 0..3 {
                    back[i][j] += l[k] * v[i][k] * v[j][k];
                }
            }
        }
        for i in 0..3 {
            for j in 0..3 {
                assert!((back[i][j] - a[i][j]).abs() < 1e-12, "{back:?}");
            }
        }
    }
}
