//! AFL target `eam` (see fuzz/src/lib.rs): `scripts/afl.sh eam SECONDS`.
fn main() {
    afl::fuzz!(|data: &[u8]| mscale_fuzz::eam(data));
}
