//! gRPC definitions of mscale and the code generated from them. The coupling protocol
//! (`mscale.coupling.v1`) and the orchestrator protocol (`mscale.orchestrator.v1`) are added
//! by the coupling-service and orchestrator work; nothing here is generated yet.
