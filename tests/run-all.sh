#!/usr/bin/env bash
# Every test of the suite: format, lints, Rust unit/integration tests, the interop tests
# against independent peers (Cyclone DDS, mcap-ros2-support, rosbags, Pinocchio, check_urdf),
# the RP2040 firmware in the loop (rp2040js) and a fuzz smoke run.
#
# DDS tests run inside a private network namespace (loopback only) so they never touch a real
# network: as root, this script re-executes itself under `unshare -n`.
set -euo pipefail
self=$(realpath "$0")
cd "$(dirname "$self")/.."
root=$(pwd)

if [[ "${POLAR_CELL_NETNS:-}" != "1" ]]; then
  # Tools and the Python peers first (network needed), then everything else offline.
  cargo build --release --workspace --locked
  if [[ ! -x .venv/bin/python ]]; then
    python3 -m venv .venv
  fi
  .venv/bin/pip install --quiet --disable-pip-version-check -r tests/interop/requirements.txt
  cargo test --workspace --release --locked --no-run --quiet
  # The patched RustDDS's own tests (patches/rustdds/PATCH.md), built with its dev-dependencies.
  CARGO_TARGET_DIR=target/rustdds-patch cargo test --manifest-path patches/rustdds/Cargo.toml \
    --locked --lib --no-run --quiet
  (cd firmware && cargo fetch --locked --quiet)
  tests/firmware/run.sh --build-only
  if cargo fuzz --version >/dev/null 2>&1; then
    RUSTC_BOOTSTRAP=1 cargo fuzz build --fuzz-dir tests/fuzz -O
  fi
  if [[ $(id -u) == 0 ]] && unshare -n true 2>/dev/null; then
    exec env POLAR_CELL_NETNS=1 unshare -n "$self" "$@"
  fi
  echo "WARNING: cannot create a network namespace (needs root); DDS tests use the host's loopback" >&2
  export POLAR_CELL_NETNS=host
fi

if [[ "${POLAR_CELL_NETNS}" == "1" ]]; then
  ip link set lo up
  ip link set lo multicast on
fi

echo "== cargo fmt"
cargo fmt --all -- --check
echo "== cargo clippy"
cargo clippy --workspace --all-targets --locked --quiet -- -D warnings
echo "== the MCU crates for the RP2040 (thumbv6m-none-eabi: no_std, no alloc, no FPU)"
cargo build --release --locked --quiet -p step_core -p cell_protocol -p cell_firmware_core \
  --target thumbv6m-none-eabi
echo "== the RP2040 firmware (firmware/: its own workspace, thumbv6m-none-eabi), both profiles"
# Both built before the namespace (tests/firmware/run.sh --build-only: ELF and UF2 each).
(cd firmware && cargo fmt -- --check \
  && cargo clippy --release --locked --quiet -- -D warnings \
  && cargo clippy --release --locked --quiet --features bench-rig -- -D warnings)
ls -l firmware/target/polar_cell_firmware.uf2 firmware/target/polar_cell_firmware-bench-rig.uf2
echo "== cargo test"
cargo test --workspace --release --locked --no-fail-fast 2>&1 | tee /tmp/polar-cell-cargo-test.log | grep -E "^(test result|running|error|failures)|FAILED|panicked" || true
if grep -qE "FAILED|error(\[|:)" /tmp/polar-cell-cargo-test.log || ! grep -q "test result" /tmp/polar-cell-cargo-test.log; then
  cat /tmp/polar-cell-cargo-test.log
  # The reasons last, where a truncated CI log still shows them: each failing test's output.
  echo "== what the failing tests printed"
  awk '/^---- .* stdout ----$/ {show=1} /^failures:$/ && show {show=0} show' /tmp/polar-cell-cargo-test.log | tail -c 20000
  exit 1
fi
echo "== the patched RustDDS's tests of what patches/rustdds/PATCH.md changes"
CARGO_TARGET_DIR=target/rustdds-patch cargo test --manifest-path patches/rustdds/Cargo.toml \
  --locked --lib --quiet -- rtps::writer::tests::repair rtps::writer_send_buffer::tests \
  structure::dds_cache::tests network::util::tests
echo "== interop tests (Cyclone DDS, mcap-ros2-support, rosbags, Pinocchio, check_urdf)"
cd tests/interop
POLAR_CELL_BIN_DIR="$root/target/release" "$root/.venv/bin/python" -m pytest -q -p no:cacheprovider
cd "$root"
echo "== the RP2040 firmware in the loop (tests/firmware/run.sh: rp2040js against the node graph)"
tests/firmware/run.sh
echo "== fuzz smoke run (tests/fuzz/run.sh: 20,000 inputs per target, fixed seed)"
if cargo fuzz --version >/dev/null 2>&1; then
  tests/fuzz/run.sh 20000
else
  echo "WARNING: cargo-fuzz is not installed (cargo install cargo-fuzz); fuzz targets not run" >&2
fi
