#!/usr/bin/env bash
# Regenerate the golden bags of tests/golden/ (planner, screw driver and mechanism replays).
# Run after an intended change of the planner's output; review the diff of the test first.
set -euo pipefail
cd "$(dirname "$0")/../.."
cargo build --release --workspace
[[ -x .venv/bin/python ]] || { python3 -m venv .venv && .venv/bin/pip install -q -r tests/interop/requirements.txt; }
if [[ $(id -u) == 0 ]] && unshare -n true 2>/dev/null; then
  exec unshare -n bash -c 'ip link set lo up; ip link set lo multicast on; .venv/bin/python tests/interop/golden.py'
fi
.venv/bin/python tests/interop/golden.py
