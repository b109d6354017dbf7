#!/bin/bash
# The GPU checks, prepared for the device tool (docs/NUMERICS.md "On a GPU").
#
#   bash benchmarks/gpu_check.sh prepare     # here: wheels into .whl/, scenes into .gpu/
#   bash benchmarks/gpu_check.sh run         # there, carrying [".whl", ".gpu"]
#
# `run` installs the wheels, JIT-compiles gsplat (about a minute on 16 cores), runs every
# CUDA test, and trains the demo, lego-tiny and two MuJoCo scenes at full resolution
# side by side for TRAIN_MINUTES each (default 1.5), leaving pytest logs, train logs and
# summary.json (each run's metrics.json) in $OUT. Budget: ~1 min start, ~1 min compile,
# ~15 s of tests, TRAIN_MINUTES + ~40 s of training and evaluation.
set -u
here=$(cd "$(dirname "$0")/.." && pwd)
cd "$here"

if [ "${1:-}" = prepare ]; then
    mkdir -p .whl .gpu/shared/data
    python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
        --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
        --platform manylinux2014_x86_64 -d .whl gsplat==1.5.3 tyro==1.0.17 kornia==0.9.0 \
        kornia_rs==0.2.0 docstring_parser==0.18.0 typeguard==4.6.1
    cp -r ../shared/weights .gpu/shared/
    for s in lego-tiny mujoco-thin_structure mujoco-texture; do
        cp -r "../shared/data/$s" .gpu/shared/data/
    done
    du -sh .whl .gpu
    exit 0
fi
[ "${1:-}" = run ] || { echo "usage: $0 prepare|run" >&2; exit 2; }

T0=$(date +%s)
OUT=${OUT:-/tmp/gpu-check}
mkdir -p "$OUT" /tmp/runs
log() { echo "[$(( $(date +%s) - T0 ))s] $*" | tee -a "$OUT/steps.log"; }
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl || { log "pip install failed"; exit 1; }
export PYTHONPATH=$here:/tmp/site PYTHONUNBUFFERED=1 MAX_JOBS=16 TORCH_CUDA_ARCH_LIST=9.0
export TORCH_HOME=$here/.gpu/shared/weights/torch-home
[ -e ../shared ] || ln -s "$here/.gpu/shared" ../shared
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
  python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)"
  git rev-parse --short HEAD 2>/dev/null; } > "$OUT/machine.txt" 2>&1
timeout 300 python3 -c "from gsplat.cuda._backend import _C" > "$OUT/compile.log" 2>&1
log "gsplat compile rc=$?"

minutes=${TRAIN_MINUTES:-1.5}
train() {  # name, args...
    local name=$1; shift
    OMP_NUM_THREADS=3 timeout $(( ${minutes%.*} * 60 + 150 )) python3 -m dyngs.cli hexplane-4dgs \
        "$@" --seed 0 --time-budget "$minutes" --output-dir /tmp/runs --run-name "$name" \
        > "/tmp/runs/$name.log" 2>&1
    log "$name rc=$?"
}
train demo --data demo &
train lego-tiny @configs/lego-tiny.args &
train thin_structure-800 --data ../shared/data/mujoco-thin_structure --background 1 1 1 &
train texture-800 --data ../shared/data/mujoco-texture --background 1 1 1 &

# Two pytest runs, so that a crash in gsplat's kernels leaves the other's report.
timeout 120 python3 -m pytest -q -rs -p no:cacheprovider --tb=short -k cuda \
    tests/renderers/test_cuda_tile.py tests/datamanagers tests/fields tests/test_cli.py \
    > "$OUT/pytest-parity.log" 2>&1
log "pytest parity rc=$? $(tail -1 "$OUT/pytest-parity.log")"
timeout 120 python3 -m pytest -q -rs -p no:cacheprovider --tb=short -k cuda \
    tests/renderers/test_hard_cases.py > "$OUT/pytest-hard-cases.log" 2>&1
log "pytest hard cases rc=$? $(tail -1 "$OUT/pytest-hard-cases.log")"
wait
python3 - > "$OUT/summary.json" <<'PY'
import json, pathlib
runs = sorted(pathlib.Path("/tmp/runs").glob("*/metrics.json"))
print(json.dumps({m.parent.name: json.loads(m.read_text()) for m in runs}, indent=1))
PY
for f in /tmp/runs/*.log; do echo "=== $f"; grep -v "it/s *$" "$f" | tail -30; done \
    > "$OUT/train-logs.txt"
log end
