#!/usr/bin/env bash
# Peak memory (VmHWM) of the parser alone (`polar-cell check`) and of the whole print pipeline
# (`polar-cell print`, DDS + recorder) for generated G-code files of the given sizes in MB.
#   tests/bench/rss.sh 10 500
# Run as root to get a private network namespace for the DDS part.
set -euo pipefail
cd "$(dirname "$0")/../.."
cargo build --release --quiet
bin=target/release/polar-cell
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
peak_kb() { # run a command; print its peak RSS in kB (getrusage of the child: exact)
  python3 - "$@" 2>"$work/err" <<'PY'
import resource, subprocess, sys
rc = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL).returncode
if rc:
    sys.exit(rc)
print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
PY
}
for mb in "$@"; do
  python3 - "$work/in.gcode" "$mb" <<'PY'
import math, sys
path, mb = sys.argv[1], float(sys.argv[2])
target = int(mb * 1e6)
with open(path, "w") as f:
    f.write("G21\nG90\nM82\nG92 E0\n")
    i, size, e = 0, 0, 0.0
    while size < target:
        a = i * 0.01
        r = 20 + 10 * math.sin(i * 0.001)
        e += 0.01
        line = "G1 X%.3f Y%.3f E%.5f F3000\n" % (r * math.cos(a), r * math.sin(a), e)
        f.write(line)
        size += len(line)
        i += 1
PY
  size=$(stat -c %s "$work/in.gcode")
  check=$(peak_kb "$bin" check --parse-only "$work/in.gcode")
  if [[ $(id -u) == 0 ]] && unshare -n true 2>/dev/null; then
    print=$(unshare -n bash -c "ip link set lo up; ip link set lo multicast on; $(declare -f peak_kb); work=$work; peak_kb $bin print $work/in.gcode --bag $work/out.mcap --no-progress --dry-run")
  else
    print=$(peak_kb "$bin" print "$work/in.gcode" --bag "$work/out.mcap" --no-progress --dry-run)
  fi
  rate=$(grep -o '[0-9]* moves/s' "$work/err" || true)
  echo "file ${size} bytes: check peak RSS ${check} kB; print peak RSS ${print} kB (${rate})"
  rm -f "$work/out.mcap"
done
