//! The fixed uniform background grid, in `D` dimensions, with its boundary conditions.

/// What happens at one face of the grid (applied to the nodal velocities on that face).
#[derive(Debug, Clone, PartialEq)]
pub enum Face {
    /// Material may leave the face's nodes freely (no constraint).
    Free,
    /// Every velocity component of the face's nodes is zero (no-slip wall).
    Fixed,
    /// The normal velocity component is zero, tangential ones are free (reflective wall / roller;
    /// in 1D the two are the same).
    Reflective,
    /// Periodic with the opposite face (both faces of the axis must say so).
    Periodic,
    /// The face's nodes move with a prescribed velocity (m/s, one component per dimension).
    Piston(Vec<f64>),
}

/// A uniform grid: `cells[a]` cells of size `h[a]` along axis `a` starting at `origin[a]`.
#[derive(Debug, Clone)]
pub struct Grid<const D: usize> {
    pub origin: [f64; D],
    pub h: [f64; D],
    pub cells: [usize; D],
    /// `faces[a] = (min face, max face)`.
    pub faces: [(Face, Face); D],
}

impl<const D: usize> Grid<D> {
    pub fn periodic(&self, axis: usize) -> bool {
        self.faces[axis].0 == Face::Periodic
    }

    /// Distinct nodes along an axis (a periodic axis identifies its last node with the first).
    pub fn nodes_along(&self, axis: usize) -> usize {
        if self.periodic(axis) { self.cells[axis] } else { self.cells[axis] + 1 }
    }

    pub fn node_count(&self) -> usize {
        (0..D).map(|a| self.nodes_along(a)).product()
    }

    /// Upper corner of the grid.
    pub fn extent_max(&self) -> [f64; D] {
        std::array::from_fn(|a| self.origin[a] + self.h[a] * self.cells[a] as f64)
    }

    /// Maps an unwrapped node coordinate along `axis` to a node index, or `None` when it lies
    /// outside a non-periodic grid.
    pub fn wrap(&self, axis: usize, i: i64) -> Option<usize> {
        let n = self.nodes_along(axis) as i64;
        if self.periodic(axis) {
            Some(i.rem_euclid(n) as usize)
        } else if (0..n).contains(&i) {
            Some(i as usize)
        } else {
            None
        }
    }

    /// Linear index of a node from its per-axis indices (x fastest).
    pub fn linear(&self, idx: [usize; D]) -> usize {
        let mut lin = 0;
        for a in (0..D).rev() {
            lin = lin * self.nodes_along(a) + idx[a];
        }
        lin
    }

    /// Per-axis indices of a linear node index.
    pub fn unlinear(&self, mut lin: usize) -> [usize; D] {
        let mut idx = [0; D];
        for (a, slot) in idx.iter_mut().enumerate() {
            let n = self.nodes_along(a);
            *slot = lin % n;
            lin /= n;
        }
        idx
    }

    /// Position of a node.
    pub fn node_position(&self, idx: [usize; D]) -> [f64; D] {
        std::array::from_fn(|a| self.origin[a] + self.h[a] * idx[a] as f64)
    }

    /// Volume of one cell (length in 1D, area in 2D).
    pub fn cell_volume(&self) -> f64 {
        self.h.iter().product()
    }

    pub fn min_spacing(&self) -> f64 {
        self.h.iter().cloned().fold(f64::INFINITY, f64::min)
    }

    /// Wraps a position into a periodic grid (unchanged along non-periodic axes).
    pub fn wrap_position(&self, x: &mut [f64; D]) {
        for a in 0..D {
            if self.periodic(a) {
                let len = self.h[a] * self.cells[a] as f64;
                let rel = (x[a] - self.origin[a]).rem_euclid(len);
                x[a] = self.origin[a] + rel;
            }
        }
    }

    /// The nodes whose index along axis `a` is `side`, in increasing linear order (x fastest:
    /// `lin = outer * block + side * stride + inner`).
    fn face_nodes(&self, a: usize, side: usize) -> impl Iterator<Item = usize> {
        let stride: usize = (0..a).map(|b| self.nodes_along(b)).product();
        let block = stride * self.nodes_along(a);
        (0..self.node_count() / block).flat_map(move |outer| (0..stride).map(move |inner| outer * block + side * stride + inner))
    }

    /// Applies the boundary conditions to a nodal velocity field (`vel[node]`), returning the
    /// momentum the constraints added (net, and summed in magnitude over the faces).
    pub fn apply_boundaries(&self, mass: &[f64], vel: &mut [[f64; D]]) -> ([f64; D], f64) {
        let mut added = [0.0; D];
        let mut magnitude = 0.0;
        for a in 0..D {
            let n = self.nodes_along(a);
            for (side, face) in [(0usize, &self.faces[a].0), (n - 1, &self.faces[a].1)] {
                if matches!(face, Face::Free | Face::Periodic) {
                    continue;
                }
                for lin in self.face_nodes(a, side) {
                    let old = vel[lin];
                    match face {
                        Face::Fixed => vel[lin] = [0.0; D],
                        Face::Reflective => vel[lin][a] = 0.0,
                        Face::Piston(v) => {
                            for (c, vc) in v.iter().enumerate().take(D) {
                                vel[lin][c] = *vc;
                            }
                        }
                        Face::Free | Face::Periodic => {}
                    }
                    if mass[lin] > 0.0 {
                        for c in 0..D {
                            let dp = mass[lin] * (vel[lin][c] - old[c]);
                            added[c] += dp;
                            magnitude += dp.abs();
                        }
                    }
                }
            }
        }
        (added, magnitude)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `face_nodes` lists exactly the nodes `unlinear` puts on the face, in increasing order.
    fn check<const D: usize>(cells: [usize; D], faces: [(Face, Face); D]) {
        let g = Grid::<D> { origin: [0.0; D], h: [1.0; D], cells, faces };
        for a in 0..D {
            for side in [0, g.nodes_along(a) - 1] {
                let want: Vec<usize> = (0..g.node_count()).filter(|&l| g.unlinear(l)[a] == side).collect();
                assert_eq!(g.face_nodes(a, side).collect::<Vec<_>>(), want, "axis {a}, side {side}, cells {cells:?}");
            }
        }
    }

    #[test]
    fn face_nodes_are_the_nodes_on_the_face_in_linear_order() {
        let (f, p) = (|| (Face::Fixed, Face::Reflective), || (Face::Periodic, Face::Periodic));
        check([5], [f()]);
        check([4, 3], [f(), f()]);
        check([4, 3], [p(), f()]);
        check([3, 4, 2], [f(), p(), f()]);
        check([2, 3, 5], [p(), f(), p()]);
    }
}
