#!/usr/bin/env bash
# Re-resolve the locks in lock/ from pyproject.toml's ranges, as of today's registry.
#
#   tools/refresh_locks.sh            # needs uv on PATH (pip install uv); writes lock/*.txt
#   .ci/run                           # then the suite on the new lock; commit lock/ when it is green
#
# lock/ci.txt is what the README's test command installs (the core and the extras CI tests); every
# other lock is resolved with ci.txt as constraints, so a package they share has the version CI
# tested. One universal resolution ("fewest" versions across platforms and Pythons >= 3.11), so
# the same file serves Linux, macOS and Windows; CI tests it on Linux with Python 3.11.
set -euo pipefail
cd "$(dirname "$0")/.."
uv="${UV:-uv}"
compile() {   # compile OUTPUT [uv pip compile arguments...]
  local out="$1"; shift
  "$uv" pip compile pyproject.toml --universal --fork-strategy fewest --python-version 3.11 --quiet \
    --no-header --annotation-style line -o "$out" "$@"
  # the command that made it, without this machine's paths: the next refresh reads the same
  sed -i.bak "1i # $out: made by tools/refresh_locks.sh (uv pip compile $*); do not edit by hand" "$out" && rm -f "$out.bak"
}
compile lock/ci.txt --extra test --extra distributed --extra tune --extra slurm --extra stonesoup --extra mlflow
compile lock/core.txt -c lock/ci.txt
compile lock/bench.txt --extra bench -c lock/ci.txt
compile lock/adsb.txt --extra adsb -c lock/ci.txt
for f in lock/*.txt; do echo "$f: $(grep -c "==" "$f") pinned" >&2; done; echo "now run .ci/run, and commit lock/ when it is green" >&2
