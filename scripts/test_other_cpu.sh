#!/usr/bin/env bash
# The README's tests with another CPU's floating-point rounding, on this machine: OpenBLAS picks
# its kernels by the CPU, and OPENBLAS_CORETYPE makes it use another's (default Sandybridge: AVX,
# no FMA, an older Intel Xeon's). A test that passes only with this machine's kernels fails here
# too, without another machine (docs/analysis.md, "Verdicts that turn on the last bits", session
# 32). The kernel must run on this CPU: Sandybridge, Haswell, Zen or Prescott on an AVX2 machine.
# Arguments go to scripts/test.sh (e.g. tests/test_diagnosis.py -k drift).
set -euo pipefail
cd "$(dirname "$0")/.."
export OPENBLAS_CORETYPE=${OPENBLAS_CORETYPE:-Sandybridge}
echo "scripts/test_other_cpu.sh: OpenBLAS kernels $OPENBLAS_CORETYPE"
exec bash scripts/test.sh "$@"
