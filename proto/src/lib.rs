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

/// Version of `mscale.coupling.v1` this build speaks; checked on `Open`.
pub const COUPLING_PROTOCOL_VERSION: u32 = 2;

/// Encoded file descriptor set of every service (for gRPC reflection).
pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("mscale_descriptor");
