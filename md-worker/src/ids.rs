//! Maps keyed by point id, for the per-box state of the step path.

use crate::backend::PointId;
use std::collections::HashMap;

/// Hasher of point ids for the per-box maps of the step path: one multiply (Fibonacci
/// hashing). Point ids come from the coordinator itself, so SipHash's resistance to chosen
/// keys buys nothing here, and it was a visible part of a 20,000-box step's cost.
#[derive(Debug, Default, Clone, Copy)]
pub struct IdHasher(u64);

impl std::hash::Hasher for IdHasher {
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_u64(u64::from(b));
        }
    }
    fn write_u64(&mut self, v: u64) {
        self.0 = (self.0.rotate_left(5) ^ v).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    }
    fn finish(&self) -> u64 {
        self.0 ^ (self.0 >> 32)
    }
}

/// A map keyed by point id with [`IdHasher`].
pub type IdMap<V> = HashMap<PointId, V, std::hash::BuildHasherDefault<IdHasher>>;
