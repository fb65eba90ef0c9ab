#!/usr/bin/env bash
# Fuzzes scancorr's untrusted-input paths for a fixed time budget per target (not part of CI):
#
#   scripts/fuzz.sh [SECONDS_PER_TARGET] [TARGET...]     (default: 60 s, all four targets)
#
# Targets (fuzz/fuzz_targets/, bodies in fuzz/src/targets.rs):
#   wire_decode  protobuf raw batches of the four streams -> scancorr_core::wire::decode -> Corrector
#   calibration  JSON -> Calibration::from_json -> build -> Corrector on a short scan
#   expr         a custom effect's expression -> Expr::parse -> eval
#   bag_reader   a file -> scancorr_bag::BagReader::open -> every message read and decoded
#
# Uses cargo-fuzz (libFuzzer, AddressSanitizer), installed with `cargo install cargo-fuzz
# --locked` when missing. It needs nightly compiler flags: on the stable toolchain they are
# allowed with RUSTC_BOOTSTRAP=1 (set here, for the fuzz build only). The fuzz build has its own
# workspace and target directory (fuzz/target): sanitizer builds cannot share artifacts.
#
# Each target starts from its committed seeds (fuzz/seeds/<target>/, made by
# `cd fuzz && cargo run --example seeds`) plus the corpus grown by earlier runs
# (fuzz/corpus/<target>/, not committed). Every crash, timeout or out-of-memory input found is
# copied to fuzz/regressions/<target>/, where `cargo test -p scancorr-tests --test
# fuzz_regressions` runs it from then on: commit it with the fix. Prints per target the
# executions, corpus size and crashes; exits non-zero if any target crashed.
#
# FUZZ_ARGS adds libFuzzer flags, e.g. FUZZ_ARGS='-malloc_limit_mb=8192' to look past a known
# huge allocation, or FUZZ_ARGS='-jobs=2 -workers=2'.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$PWD

secs=${1:-60}
shift || true
case "$secs" in
'' | *[!0-9]*)
    echo "usage: scripts/fuzz.sh [SECONDS_PER_TARGET] [TARGET...]" >&2
    exit 2
    ;;
esac
all_targets=(wire_decode calibration expr bag_reader)
if [ $# -gt 0 ]; then targets=("$@"); else targets=("${all_targets[@]}"); fi

if ! command -v cargo-fuzz >/dev/null 2>&1; then
    echo "fuzz.sh: installing cargo-fuzz" >&2
    cargo install cargo-fuzz --locked
fi

export RUSTC_BOOTSTRAP=1
export CARGO_TARGET_DIR="$root/fuzz/target"
# The bag target writes its input to a file per run: keep that in memory when possible.
if [ -z "${TMPDIR:-}" ] && [ -d /dev/shm ] && [ -w /dev/shm ]; then export TMPDIR=/dev/shm; fi

logs="$root/fuzz/target/logs"
mkdir -p "$logs"

echo "fuzz.sh: building the fuzz targets (release, AddressSanitizer)" >&2
for t in "${targets[@]}"; do cargo fuzz build --release --fuzz-dir "$root/fuzz" "$t" >&2; done

list_findings() { # the crash/timeout/oom/leak files of a target's artifact directory
    local dir="$root/fuzz/artifacts/$1"
    [ -d "$dir" ] || return 0
    find "$dir" -maxdepth 1 -type f \( -name 'crash-*' -o -name 'timeout-*' -o -name 'oom-*' \
        -o -name 'leak-*' \) -printf '%f\n' | sort
}

summary=()
failed=0
runfail=0
for t in "${targets[@]}"; do
    corpus="$root/fuzz/corpus/$t"
    seeds="$root/fuzz/seeds/$t"
    mkdir -p "$corpus" "$seeds"
    before=$(list_findings "$t")
    log="$logs/$t.log"
    echo "fuzz.sh: $t for ${secs}s (log: ${log#"$root"/})" >&2
    set +e
    cargo fuzz run --release --fuzz-dir "$root/fuzz" "$t" "$corpus" "$seeds" -- \
        -max_total_time="$secs" -rss_limit_mb=2048 -timeout=10 -print_final_stats=1 \
        ${FUZZ_ARGS:-} >"$log" 2>&1
    rc=$?
    set -e
    # Executions: libFuzzer's final stats, else its "Done N runs", else the last status line.
    execs=$(grep -oE 'stat::number_of_executed_units: *[0-9]+' "$log" | tail -1 | grep -oE '[0-9]+$' || true)
    [ -n "$execs" ] || execs=$(grep -oE 'Done [0-9]+ runs' "$log" | tail -1 | grep -oE '[0-9]+' || true)
    [ -n "$execs" ] || execs=$(grep -oE '^#[0-9]+' "$log" | tail -1 | tr -d '#' || true)
    execs=${execs:-0}
    size=$(find "$corpus" -maxdepth 1 -type f | wc -l)
    after=$(list_findings "$t")
    new=$(comm -13 <(printf '%s\n' "$before" | sed '/^$/d') <(printf '%s\n' "$after" | sed '/^$/d'))
    crashes=$(printf '%s\n' "$new" | sed '/^$/d' | wc -l)
    shown=$crashes
    if [ "$rc" -ne 0 ] && [ "$crashes" -eq 0 ]; then
        # libFuzzer did not run to the end and left no input (e.g. the build failed): not a
        # crash, but a failed run all the same.
        shown="run failed"
        runfail=1
        echo "fuzz.sh: $t exited with $rc and left no input; see $log" >&2
        tail -n 30 "$log" >&2
    fi
    if [ -n "$new" ]; then
        mkdir -p "$root/fuzz/regressions/$t"
        while read -r f; do
            [ -n "$f" ] || continue
            cp "$root/fuzz/artifacts/$t/$f" "$root/fuzz/regressions/$t/$f"
            echo "fuzz.sh: $t: NEW FINDING kept as fuzz/regressions/$t/$f" >&2
        done <<<"$new"
        grep -m1 -B2 -A40 -E "panicked at|ERROR: (libFuzzer|AddressSanitizer)|==ERROR|deadly signal" \
            "$log" >&2 || tail -n 40 "$log" >&2
    fi
    [ "$crashes" -eq 0 ] || failed=1
    summary+=("$(printf '%-12s %12s %8s %8s' "$t" "$execs" "$size" "$shown")")
done

printf '%-12s %12s %8s %8s\n' target executions corpus crashes
printf '%s\n' "${summary[@]}"
if [ "$failed" -ne 0 ]; then
    echo "fuzz.sh: crashes found: their inputs are in fuzz/regressions/<target>/ (run" \
        "'cargo test --release -p scancorr-tests --test fuzz_regressions'); fix, then commit them" >&2
    exit 1
fi
if [ "$runfail" -ne 0 ]; then
    echo "fuzz.sh: a target did not run (see its log above)" >&2
    exit 1
fi
