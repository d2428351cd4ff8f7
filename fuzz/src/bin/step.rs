//! AFL target `step` (see fuzz/src/lib.rs): `scripts/afl.sh step SECONDS`.
fn main() {
    afl::fuzz!(|data: &[u8]| mscale_fuzz::step(data));
}
