//! AFL target `checkpoint` (see fuzz/src/lib.rs): `scripts/afl.sh checkpoint SECONDS`.
fn main() {
    afl::fuzz!(|data: &[u8]| mscale_fuzz::checkpoint(data));
}
