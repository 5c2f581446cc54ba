#!/usr/bin/env bash
# Firmware in the loop: build the RP2040 firmware, run it in rp2040js (harness.mjs), print
# the first moves of a G-code file through the cell's real node graph into it over UART0
# (mcu_bridge on the harness's Unix socket), then compare every recorded pin edge with the
# planner's decoder (examples/firmware_edges.rs). Exit 0 when every check holds.
#
#   tests/firmware/run.sh [--speed K] [--profile FILE] [GCODE] [MOVES]
#
# Defaults: polartest.gcode, its first 300 moves, speed 1 (emulated time = wall time; a
# slower speed gives a loaded machine's emulator room to keep up, the timeline is the same).
# --profile writes the firmware's instructions per function (sampled) to FILE.
#
# Builds and installs first (network needed), then, as root, re-runs itself in a private
# network namespace (loopback only) for the print, like tests/run-all.sh.
set -euo pipefail
cd "$(dirname "$0")/../.."
original_args=("$@")
speed=1
profile=()
while [[ $# -gt 0 && $1 == --* ]]; do
  case $1 in
    --speed) speed=$2; shift 2 ;;
    --profile) profile=(--profile "$(realpath -m "$2")"); shift 2 ;;
    *) echo "unknown option $1" >&2; exit 64 ;;
  esac
done
gcode=${1:-../shared/fixtures/gcode/polartest.gcode}
moves=${2:-300}

if [[ "${POLAR_CELL_NETNS:-}" == "" ]]; then
  (cd firmware && cargo build --release --locked --quiet)
  cargo build --release --locked --quiet --workspace --bins --example firmware_edges
  (cd tests/firmware && npm ci --silent --no-audit --no-fund)
  if [[ $(id -u) == 0 ]] && unshare -n true 2>/dev/null; then
    exec env POLAR_CELL_NETNS=1 unshare -n "$0" "${original_args[@]}"
  fi
  export POLAR_CELL_NETNS=host
fi
if [[ "${POLAR_CELL_NETNS}" == "1" ]]; then
  ip link set lo up
  ip link set lo multicast on
fi
work=$(mktemp -d /tmp/polar-cell-firmware.XXXXXX)
harness=
# POLAR_CELL_KEEP=1 keeps the bag, the edges and the harness's output for a closer look.
trap '[[ -n $harness ]] && kill $harness 2>/dev/null; [[ -n ${POLAR_CELL_KEEP:-} ]] && echo "kept $work" || rm -rf "$work"' EXIT

# The first G1/G0 moves of the file (and everything before them: units, modes).
awk -v n="$moves" '/^[ \t]*G[01][ \t]/ {k++} k > n {exit} {print}' "$gcode" > "$work/part.gcode"

node tests/firmware/harness.mjs --elf firmware/target/thumbv6m-none-eabi/release/polar_cell_firmware \
  --socket "$work/uart0.sock" --edges "$work/edges.csv" --speed "$speed" "${profile[@]}" > "$work/harness.out" 2> "$work/harness.err" &
harness=$!
for _ in $(seq 50); do [[ -S "$work/uart0.sock" ]] && break; sleep 0.1; done
env -u RUST_BACKTRACE target/release/polar-cell print "$work/part.gcode" --device "unix:$work/uart0.sock" \
  --bag "$work/print.mcap" --speed "$speed" --no-progress 2>&1 | grep -v '^  /'
kill -INT $harness
wait $harness || true
echo "rp2040js: $(tail -1 "$work/harness.out")"
target/release/examples/firmware_edges "$work/print.mcap" "$work/edges.csv"
