//! AFL target `users` (see fuzz/src/lib.rs): `scripts/afl.sh users SECONDS`.
fn main() {
    afl::fuzz!(|data: &[u8]| mscale_fuzz::users(data));
}
