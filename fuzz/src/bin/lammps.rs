//! AFL target `lammps` (see fuzz/src/lib.rs): `scripts/afl.sh lammps SECONDS`.
fn main() {
    afl::fuzz!(|data: &[u8]| mscale_fuzz::lammps(data));
}
