#!/usr/bin/env bash
# Coverage-guided fuzzing of one target with cargo-afl (AFL++ on stable Rust):
#
#   scripts/afl.sh TARGET SECONDS [--update-corpus]
#
# TARGET: scene, eam, lammps, checkpoint, users or step (fuzz/src/lib.rs says what each
# reaches). Builds fuzz/ (its own workspace, target directory fuzz/target) with AFL's
# instrumentation, seeds the run from fuzz/corpus/TARGET (the committed, minimised corpus) or,
# when that is empty, from fuzz/seeds.sh's seeds (the mutation corpora of */tests/fuzz-corpus/
# and shipped files), fuzzes on one core for SECONDS, and prints one line of figures (execs,
# corpus, edges, crashes, hangs, peak memory of the target). A hang is a run over 10 s
# (-t 10000), the memory bound 2 GiB (-m 2048). With --update-corpus the queue is minimised
# with afl-cmin into fuzz/corpus/TARGET. Exit code 1 when AFL saved a crash or a hang (they are
# under fuzz/target/afl/TARGET/default/crashes and hangs). Needs `bash deploy/setup.sh afl`.
set -euo pipefail
cd "$(dirname "$0")/.."
usage="usage: scripts/afl.sh TARGET SECONDS [--update-corpus] (TARGET: scene eam lammps checkpoint users step)"
target=${1:?$usage}
secs=${2:?$usage}
update=${3:-}
case "$target" in scene|eam|lammps|checkpoint|users|step) ;; *) echo "afl.sh: unknown target '$target'; $usage" >&2; exit 2 ;; esac
[[ "$secs" =~ ^[0-9]+$ ]] || { echo "afl.sh: SECONDS must be a whole number, not '$secs'" >&2; exit 2; }
command -v cargo-afl >/dev/null || { echo "afl.sh: cargo-afl is not installed: run 'bash deploy/setup.sh afl'" >&2; exit 2; }
cd fuzz
cargo afl build --release --bin "$target" >&2
bin=target/release/$target
out=target/afl/$target
corpus=corpus/$target
seeds=$corpus
if [ -z "$(ls -A "$corpus" 2>/dev/null)" ]; then
  seeds=$PWD/target/seeds/$target
  bash seeds.sh "$target" "$seeds" >&2
fi
rm -rf "$out"
mkdir -p "$out"
# No UI; AFL++'s checks of the CPU governor and core pattern are not ours to change here.
export AFL_NO_UI=1 AFL_SKIP_CPUFREQ=1 AFL_I_DONT_CARE_ABOUT_MISSING_CRASHES=1 AFL_NO_AFFINITY=1
cargo afl fuzz -i "$seeds" -o "$out" -V "$secs" -t 10000 -m 2048 "$bin" > "$out/fuzz.log" 2>&1 || {
  echo "afl.sh: afl-fuzz failed; the end of its log:" >&2
  tail -n 30 "$out/fuzz.log" >&2
  exit 1
}
stats=$out/default/fuzzer_stats
get() { awk -F' *: *' -v k="$1" '$1 == k { print $2 }' "$stats"; }
echo "afl $target: run_time $(get run_time) s, execs $(get execs_done), execs/s $(get execs_per_sec), corpus $(get corpus_count), edges $(get edges_found) of $(get total_edges) ($(get bitmap_cvg)), crashes $(get saved_crashes), hangs $(get saved_hangs), peak RSS $(get peak_rss_mb) MB"
# The target's peak resident memory over the queue (each input run once, without AFL).
peak=0
for f in "$out"/default/queue/id:*; do
  /usr/bin/time -o "$out/rss" -f %M "$bin" < "$f" >/dev/null 2>&1 || true
  kb=$(tail -n 1 "$out/rss")
  [[ "$kb" =~ ^[0-9]+$ ]] && [ "$kb" -gt "$peak" ] && peak=$kb
done
echo "afl $target: peak RSS of the target over its queue $((peak / 1024)) MiB"
if [ "$update" = --update-corpus ]; then
  # afl-cmin.bash (the Python afl-cmin finds no tuples with these binaries).
  cmin=$(ls -d "$HOME"/.local/share/afl.rs/rustc-*/afl.rs-*/afl/bin 2>/dev/null | tail -n 1)
  rm -rf "$corpus.min"
  AFL_PATH=$cmin "$cmin/afl-cmin.bash" -i "$out/default/queue" -o "$corpus.min" -t 10000 -m 2048 -- "$bin" > "$out/cmin.log" 2>&1
  rm -rf "$corpus"
  mv "$corpus.min" "$corpus"
  echo "afl $target: $(ls "$corpus" | wc -l) inputs in fuzz/corpus/$target ($(du -sh "$corpus" | cut -f1))"
fi
[ "$(get saved_crashes)" = 0 ] && [ "$(get saved_hangs)" = 0 ]
