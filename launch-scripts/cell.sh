#!/usr/bin/env bash
# Start each node of the cell as its own process, parameters from params/cell.yaml.
#   launch-scripts/cell.sh FILE.gcode [BAG.mcap]
# The executor plays the plan at machine pace ($POLAR_CELL_SPEED times faster, default 1) and
# the script ends once it has executed all of it.
# With POLAR_CELL_DEVICE set the machine is a microcontroller behind mcu_bridge instead of the
# virtual executor: a serial line (/dev/ttyACM0, unix:/path), or `emulator` to start
# mcu_emulator on a Unix socket at the same speed. A real MCU is asked first where it stands
# (`polar-cell mcu-position`; a cancelled print leaves it mid-part), and the plan starts there.
# Ctrl-C (or SIGINT/SIGTERM to this script) stops the machine on the path, then every node;
# the exit status is non-zero when any node failed (the recorder's included).
# Binaries come from target/release (build with `cargo build --release --workspace`) or from
# $POLAR_CELL_BIN_DIR. Extra ROS arguments for every node can go in $POLAR_CELL_ROS_ARGS.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
bin=${POLAR_CELL_BIN_DIR:-$here/../target/release}
params=$here/params/cell.yaml
if [[ $# -lt 1 ]]; then
  echo "usage: $0 FILE.gcode [BAG.mcap]" >&2
  exit 2
fi
gcode=$1
bag=${2:-cell.mcap}
speed=${POLAR_CELL_SPEED:-1.0}
device=${POLAR_CELL_DEVICE:-}
machine=cell_executor
[[ -n $device ]] && machine=mcu_bridge
# A real MCU (not one started here) stands where the last print left it: it is asked.
real_mcu=
[[ -n $device && $device != emulator ]] && real_mcu=1
tools=(bag_recorder polar_planner screw_driver $machine gcode_streamer)
[[ -n $real_mcu ]] && tools+=(polar-cell)
[[ $device == emulator ]] && tools+=(mcu_emulator)
for b in "${tools[@]}"; do
  [[ -x $bin/$b ]] || { echo "$bin/$b missing: cargo build --release --workspace" >&2; exit 1; }
done
# Where the plan starts: home, or where a real MCU stands (the planner and the machine take
# `initial_joints`, the streamer `start_position_mm`; POLAR_CELL_ROS_ARGS still wins).
start_joints=()
start_position=()
if [[ -n $real_mcu ]]; then
  # shellcheck disable=SC2086
  start_text=$("$bin/polar-cell" mcu-position --device "$device" --ros-args --params-file "$params" ${POLAR_CELL_ROS_ARGS:-})
  mapfile -t start <<<"$start_text"
  start_joints=(-p "${start[0]}")
  start_position=(-p "${start[1]}")
fi
# Every node started goes when the script ends, however it ends (set before the first one
# starts). SIGTERM, not SIGINT: a background job of a script starts with SIGINT ignored, so a
# node stopped while it starts up would never see one. Every node takes SIGTERM as its
# shutdown: the machine stops on the path first, the recorder finishes its bag.
recorder= planner= screw= emulator= executor= streamer=
recorder_status=0
stop_nodes() {
  # Stopping goes to its end: a second Ctrl-C reaches the nodes themselves (the machine's
  # emergency stop), not this.
  trap '' INT TERM
  local running="$executor $screw $planner $streamer"
  if [[ -n ${running// /} ]]; then
    # shellcheck disable=SC2086
    kill -TERM $running 2>/dev/null || true
    # shellcheck disable=SC2086
    wait $running 2>/dev/null || true
  fi
  executor= screw= planner= streamer=
  if [[ -n $recorder ]]; then
    kill -TERM "$recorder" 2>/dev/null || true
    wait "$recorder" || recorder_status=$?
    recorder=
  fi
  if [[ -n $emulator ]]; then
    kill "$emulator" 2>/dev/null || true
    wait "$emulator" 2>/dev/null || true
  fi
}
trap stop_nodes EXIT
trap 'exit 130' INT
trap 'exit 143' TERM
# shellcheck disable=SC2086
"$bin/bag_recorder" --ros-args --params-file "$params" -p "output:=$bag" ${POLAR_CELL_ROS_ARGS:-} &
recorder=$!
# shellcheck disable=SC2086
"$bin/polar_planner" --ros-args --params-file "$params" -p "credit_producer:=$machine" "${start_joints[@]}" ${POLAR_CELL_ROS_ARGS:-} &
planner=$!
# shellcheck disable=SC2086
"$bin/screw_driver" --ros-args --params-file "$params" ${POLAR_CELL_ROS_ARGS:-} &
screw=$!
if [[ $device == emulator ]]; then
  socket=$(mktemp -u "${TMPDIR:-/tmp}/polar-cell-mcu.XXXXXX.sock")
  "$bin/mcu_emulator" --socket "$socket" --speed "$speed" >/dev/null &
  emulator=$!
  device=unix:$socket
fi
machine_args=(-p "speed:=$speed" -p exit_when_done:=true "${start_joints[@]}")
[[ -n $device ]] && machine_args+=(-p "device:=$device")
# shellcheck disable=SC2086
"$bin/$machine" --ros-args --params-file "$params" "${machine_args[@]}" ${POLAR_CELL_ROS_ARGS:-} &
executor=$!
# shellcheck disable=SC2086
"$bin/gcode_streamer" "$gcode" --ros-args --params-file "$params" "${start_position[@]}" ${POLAR_CELL_ROS_ARGS:-} &
streamer=$!
# The print ends with the machine: at the end of the plan, or with an error at a fault (a
# node of the graph restarted mid-print, the MCU lost) while the streamer may still wait.
# Any other node that fails ends it too, with its status: a streamer that cannot read the
# file, a planner refusing a move out of reach (the machine would wait for its plan for
# ever), a recorder that cannot write. A planner or screw driver killed by a signal may be
# restarted by hand: the machine knows how long to wait for it.
failed() {
  echo "$0: $1 ended with exit status $2" >&2
  exit "$2"
}
while true; do
  ended=
  status=0
  # shellcheck disable=SC2086
  wait -n -p ended $executor $streamer $planner $screw $recorder || status=$?
  case $ended in
    "$executor")
      executor=
      [[ $status == 0 ]] || failed "$machine" "$status"
      break ;;
    "$streamer")
      streamer=
      [[ $status == 0 ]] || failed gcode_streamer "$status" ;;
    "$planner")
      planner=
      [[ $status == 0 || $status -gt 128 ]] || failed polar_planner "$status" ;;
    "$screw")
      screw=
      [[ $status == 0 || $status -gt 128 ]] || failed screw_driver "$status" ;;
    "$recorder")
      recorder=
      [[ $status != 0 ]] || status=1 # it records until told to stop
      failed bag_recorder "$status" ;;
  esac
done
if [[ -n $streamer ]]; then
  wait "$streamer" # every move was acknowledged
  streamer=
fi
sleep 0.3 # the last samples, progress and diagnostics reach the recorder
stop_nodes
trap - EXIT
[[ $recorder_status == 0 ]] || failed bag_recorder "$recorder_status"
