#!/usr/bin/env bash
# Run every fuzz target: `tests/fuzz/run.sh RUNS` (inputs per target, fixed seed, so the run
# is repeatable; tests/run-all.sh uses a short smoke run) or `tests/fuzz/run.sh --time SECONDS`
# for a campaign. Needs cargo-fuzz (`cargo install cargo-fuzz`); the project's one stable
# toolchain builds the targets with RUSTC_BOOTSTRAP=1 (cargo-fuzz passes -Z flags).
#
# Limits: 2 GB of RSS; single allocations up to 4.4 GB, because the `mcap` crate reserves a
# string's declared length (a u32, so at most 4 GiB) before it reads it. That reservation is
# never touched when the read then fails, so it costs address space, not memory.
set -euo pipefail
cd "$(dirname "$0")/../.."
export RUSTC_BOOTSTRAP=1 RUST_BACKTRACE=0

if [[ "${1:-}" == "--time" ]]; then
  budget=(-max_total_time="${2:?seconds}")
else
  budget=(-runs="${1:-20000}" -seed=1)
fi
targets=(gcode bag cdr text_inputs move_stream mcu_protocol)

cargo fuzz build --fuzz-dir tests/fuzz -O
for target in "${targets[@]}"; do
  log=$(mktemp)
  if cargo fuzz run --fuzz-dir tests/fuzz -O "$target" -- "${budget[@]}" \
      -rss_limit_mb=2048 -malloc_limit_mb=4400 >"$log" 2>&1; then
    echo "fuzz $target: $(grep -E '^#[0-9]+' "$log" | tail -1 | cut -c1-100)"
  else
    cat "$log"
    echo "fuzz $target FAILED: the input is in tests/fuzz/artifacts/$target/" >&2
    rm -f "$log"
    exit 1
  fi
  rm -f "$log"
done
