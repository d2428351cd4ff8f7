//! gRPC definitions of mscale and the code generated from them (tonic + prost, protoc
//! vendored). Generated types stay at the edge: the crates convert them to their domain types
//! with `From`/`TryFrom` and refuse bad values there.

/// The coupling protocol between the continuum coordinator and MD workers.
pub mod coupling {
    pub mod v1 {
        tonic::include_proto!("mscale.coupling.v1");
    }
}

/// The gRPC server set-up both servers share.
pub mod server;

/// The job service of `mscale serve`.
pub mod orchestrator {
    pub mod v1 {
        tonic::include_proto!("mscale.orchestrator.v1");
    }
}

/// An f64 column of the Step messages: `W` values per item (a box's stress, its velocity
/// gradient, or one scalar) as packed little-endian doubles (the wire form of a packed
/// `repeated double`), written into one allocation of the exact size. (An iterator of single
/// doubles flattened from the items gives no lower size bound, and the column's growth by
/// doubling was two of the step's megabyte copies.)
pub fn f64_column<const W: usize>(items: impl ExactSizeIterator<Item = [f64; W]>) -> Vec<u8> {
    let mut out = Vec::with_capacity(8 * W * items.len());
    for item in items {
        for v in item {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

/// Value `k` of an f64 column whose length is a whole number of doubles (panics past its end,
/// as a slice index does).
pub fn f64_at(column: &[u8], k: usize) -> f64 {
    let mut b = [0; 8];
    b.copy_from_slice(&column[8 * k..8 * k + 8]);
    f64::from_le_bytes(b)
}

/// The values of an f64 column, or `None` when its length is not a whole number of doubles.
pub fn f64_values(column: &[u8]) -> Option<Vec<f64>> {
    let chunks = column.chunks_exact(8);
    chunks.remainder().is_empty().then(|| chunks.map(|c| f64::from_le_bytes(c.try_into().unwrap_or_default())).collect())
}

/// Version of `mscale.coupling.v1` this build speaks; checked on `Open`.
pub const COUPLING_PROTOCOL_VERSION: u32 = 2;

/// Encoded file descriptor set of every service (for gRPC reflection).
pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("mscale_descriptor");

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_f64_column_is_on_the_wire_a_packed_repeated_double() {
        let values = [0.0, -1.5, f64::MIN_POSITIVE, 1e300, -0.0];
        let mut packed = Vec::new();
        prost::encoding::double::encode_packed(5, &values, &mut packed);
        let mut column = Vec::new();
        let scalars = || values.iter().map(|&v| [v]);
        prost::encoding::bytes::encode(5, &f64_column(scalars()), &mut column);
        assert_eq!(packed, column);
        // Items of several values lay them out in order, as the scalars do.
        let pairs = [[0.0, -1.5], [f64::MIN_POSITIVE, 1e300]];
        assert_eq!(f64_column(pairs.into_iter()), f64_column(scalars().take(4)));
        let back = f64_values(&f64_column(scalars())).unwrap();
        assert_eq!(back.iter().map(|v| v.to_bits()).collect::<Vec<_>>(), values.map(f64::to_bits));
        assert!(f64_values(&[0; 12]).is_none());
        assert_eq!(f64_at(&f64_column(scalars()), 3), 1e300);
    }
}
