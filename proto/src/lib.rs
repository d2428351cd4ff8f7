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

/// An f64 column of the Step messages: the values as packed little-endian doubles (the wire
/// form of a packed `repeated double`).
pub fn f64_column(values: impl IntoIterator<Item = f64>) -> Vec<u8> {
    let values = values.into_iter();
    let mut out = Vec::with_capacity(8 * values.size_hint().0);
    for v in values {
        out.extend_from_slice(&v.to_le_bytes());
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
        prost::encoding::bytes::encode(5, &f64_column(values), &mut column);
        assert_eq!(packed, column);
        let back = f64_values(&f64_column(values)).unwrap();
        assert_eq!(back.iter().map(|v| v.to_bits()).collect::<Vec<_>>(), values.map(f64::to_bits));
        assert!(f64_values(&[0; 12]).is_none());
        assert_eq!(f64_at(&f64_column(values), 3), 1e300);
    }
}
