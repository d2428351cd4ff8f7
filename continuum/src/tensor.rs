//! Small 3x3 tensor helpers. Every point carries full 3x3 velocity gradients, deformation
//! gradients and stresses whatever the dimension: a 1D elastic closure still has a full
//! diagonal stress. Vectors in `D` dimensions embed into 3D with zeros.

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
