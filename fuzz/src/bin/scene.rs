//! AFL target `scene` (see fuzz/src/lib.rs): `scripts/afl.sh scene SECONDS`.
fn main() {
    afl::fuzz!(|data: &[u8]| mscale_fuzz::scene(data));
}
