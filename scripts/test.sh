#!/usr/bin/env bash
# The test suite in two phases (the README's test command; CI runs exactly this):
#   1. every test that keeps no real-time schedule, on all cores (pytest-xdist): analysis,
#      importers, drivers against recorded peers, the window offscreen, faults and HIL runs that
#      assert what happened, not how punctually;
#   2. the tests marked `schedule` (they assert the 16 Hz schedule, or skip a recording that
#      missed samples), one at a time, at normal priority, while phase 1 runs in the idle class.
# Extra arguments go to both phases (e.g. -x, -k NAME). FOAMLAB_TEST_WORKERS overrides the
# worker count of phase 1 (default: one per core); worksteal: an idle worker takes queued tests
# from a busy one, so two long tests do not end up queued behind each other on one worker.
set -uo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
# One BLAS thread per test process, whatever the caller's environment asks: phase 1 runs one
# worker per core, and a BLAS pool per worker oversubscribes the cores (fresh clone, 2 cores:
# ci10 default threads 16:04 against ci9's 15:38 at one thread; ci24 with OMP_NUM_THREADS=2
# exported 18:01, phase 1 1 052 s, against ci20's 12:04 at 1). What the product does under
# other thread counts is a test's own business (test_apart fits the real file at 1 and 2 threads
# in subprocesses and gets the same answer).
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
WORKERS=${FOAMLAB_TEST_WORKERS:-auto}

# Phase 2 waits on the machine's clock most of the time (one run is 15 min of machine time at
# x15): it runs beside phase 1, which gets only the CPU time phase 2 leaves (SCHED_IDLE: any
# runnable normal task preempts it at once; `nice -n 19` where the idle class is refused). Its
# engines take no real-time priority there (acquisition.schedule.in_background); a simulated
# device still answers at its own (a device has its own processor).
idle() { if chrt --idle 0 true 2>/dev/null; then chrt --idle 0 "$@"; else nice -n 19 "$@"; fi; }
log=$(mktemp "${TMPDIR:-/tmp}/foamlab-phase2.XXXXXX")
start=$(date +%s)
"$PY" -m pytest -q -p no:xdist -m "schedule" "$@" >"$log" 2>&1 &
phase2=$!
trap 'kill "$phase2" 2>/dev/null; rm -f "$log"' EXIT
idle "$PY" -m pytest -q -n "$WORKERS" --dist worksteal -m "not schedule" "$@"
first=$?
phase1_end=$(date +%s)
wait "$phase2"
second=$?
echo "---- phase 2 (schedule tests, run beside phase 1) ----"
cat "$log"
echo "scripts/test.sh: phase 1 (parallel, idle class) $((phase1_end - start)) s, exit $first; phase 2 (schedule, beside it; its time above) exit $second; all $(( $(date +%s) - start )) s"
# exit 5 = no test collected (a -k that selects only one phase's tests) is not a failure
[ "$first" -eq 5 ] && first=0
[ "$second" -eq 5 ] && second=0
exit $(( first != 0 ? first : second ))
