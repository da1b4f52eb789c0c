#!/usr/bin/env bash
# The device half of a CPU benchmark staged by deploy/device_bench_prepare.sh: run on the lent
# host from the repository root, with $OUT the folder whose files come back.
#   bash deploy/device_bench_run.sh SECONDS [bench accuracy options...]
# runs `bench accuracy` with its seeds checkpointed in /tmp/ck, stops it as Ctrl-C does after
# SECONDS (a seed in flight is lost; every finished one is kept), and returns the checkpoints as
# one tarball, $OUT/ck.tgz: $OUT gives back only a handful of files, so a folder of seed files
# would come back cut short. Give the call a timeout_s about 60 s above SECONDS (installing,
# packing). Back here, into the checkpoint folder of the same benchmark:
#   tar xzf <files_at>/ck.tgz -C CHECKPOINT_DIR
# then the same `cropcraft bench accuracy ... --checkpoint-dir CHECKPOINT_DIR` reads the seeds
# (and the answers of the scenes combined there) instead of fitting them. The seeds are the
# device's numbers (its numpy and numba), not this machine's: say so where they are reported.
set -uo pipefail
seconds="${1:?usage: device_bench_run.sh SECONDS [bench accuracy options]}"
shift
out="${OUT:?OUT must name the folder whose files come back}"
whl=build/device-whl
[ -d "$whl/first" ] || { echo "$whl: missing; run deploy/device_bench_prepare.sh here first" >&2; exit 2; }
t0=$(date +%s)
for part in first last; do
  pip install -q --no-index --no-deps --target "/tmp/device-$part" "$whl/$part"/*.whl \
    >> "$out/pip.log" 2>&1 || { echo "pip install of $whl/$part failed: $out/pip.log" >&2; exit 3; }
done
{ nproc; python3 -c "import numpy, numba, scipy; print(numpy.__version__, numba.__version__, scipy.__version__)"; } \
  > "$out/host.txt" 2>&1
mkdir -p /tmp/ck
# its own process group, so that the deadline reaches the spawned workers too (they get this
# sys.path from multiprocessing; benchmarks/workers.py spawns): Ctrl-C, then a kill 15 s later
# (a pool waits for its running seeds on Ctrl-C, a minute each)
setsid python3 -c "
import sys
sys.path[:0] = ['/tmp/device-first', '$PWD']
sys.path.append('/tmp/device-last')
from benchmarks.bench_accuracy import main
sys.exit(main(sys.argv[1:]))
" "$@" --checkpoint-dir /tmp/ck > "$out/bench.log" 2>&1 &
pid=$!
( sleep "$seconds"; kill -INT -- "-$pid" 2>/dev/null; sleep 15; kill -KILL -- "-$pid" 2>/dev/null ) &
watcher=$!
wait "$pid"
rc=$?
kill "$watcher" 2>/dev/null
echo "rc=$rc after $(( $(date +%s) - t0 )) s, $(find /tmp/ck -name '*.json' | wc -l) files" >> "$out/host.txt"
tar czf "$out/ck.tgz" -C /tmp/ck .
cat "$out/host.txt"
