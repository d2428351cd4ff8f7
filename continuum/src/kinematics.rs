//! Finite-deformation kinematics on the project's row-major [`Mat3`]: the polar decomposition
//! F = R U (through nalgebra's SVD) that the unrotated-frame laws use (battery thesis
//! (7.26)-(7.29)).

use crate::tensor::{IDENTITY, Mat3};
use nalgebra::Matrix3;

fn to_na(a: &Mat3) -> Matrix3<f64> {
    Matrix3::from_fn(|i, j| a[i][j])
}

fn from_na(m: &Matrix3<f64>) -> Mat3 {
    std::array::from_fn(|i| std::array::from_fn(|j| m[(i, j)]))
}

/// The polar decomposition F = R U of a deformation gradient with det F > 0: R proper
/// orthogonal, U = R^T F symmetric positive definite. `None` when F is not finite or not
/// invertible with a positive determinant.
pub fn polar(f: &Mat3) -> Option<(Mat3, Mat3)> {
    if !(crate::tensor::det(f) > 0.0) || !crate::tensor::is_finite(f) {
        return None;
    }
    let m = to_na(f);
    // F = W S V^T, so R = W V^T (det R = +1 since det F > 0 and S >= 0) and U = V S V^T.
    let svd = m.svd(true, true);
    let (w, vt) = (svd.u?, svd.v_t?);
    let r = w * vt;
    if !(r.determinant() > 0.0) {
        return None;
    }
    let u = r.transpose() * m;
    let u = (u + u.transpose()) * 0.5;
    Some((from_na(&r), from_na(&u)))
}

/// The rotation of [`polar`], the identity when F is the identity (exactly: no SVD round-off on
/// an undeformed point).
pub fn rotation(f: &Mat3) -> Option<Mat3> {
    if *f == IDENTITY {
        return Some(IDENTITY);
    }
    polar(f).map(|(r, _)| r)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tensor::{mul, transpose};

    #[test]
    fn polar_recovers_a_rotation_times_a_stretch() {
        let (c, s) = (0.3f64.cos(), 0.3f64.sin());
        let r0: Mat3 = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]];
        let u0: Mat3 = [[1.2, 0.1, 0.0], [0.1, 0.9, 0.05], [0.0, 0.05, 1.1]];
        let (r, u) = polar(&mul(&r0, &u0)).expect("regular");
        for i in 0..3 {
            for j in 0..3 {
                assert!((r[i][j] - r0[i][j]).abs() < 1e-12, "{r:?}");
                assert!((u[i][j] - u0[i][j]).abs() < 1e-12, "{u:?}");
            }
        }
        let rtr = mul(&transpose(&r), &r);
        for i in 0..3 {
            assert!((rtr[i][i] - 1.0).abs() < 1e-14);
        }
        assert!(polar(&[[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]).is_none(), "an inverted point has no polar form");
    }
}
