#!/usr/bin/env bash
# The one command a lent GPU runs (the device tool's `run`; docs/training.md, "GPU bursts").
# It trains the inpainting net and the refiner from the training pack for MINUTES (set-up included), writing
# sharded weights into $OUT/burst every minute, then runs every CUDA test case.  Carry: .pack .whl (and the
# folder INIT lies in, when it is not a tracked file).  Uses the device's own python3 (torch, numpy 2, safetensors,
# matplotlib, pytest); trimesh, which only the tests import, comes as a wheel from .whl.
#   MINUTES=7 RECIPE=wide INIT=genre_backend/weights/default.safetensors bash scripts/gpu_burst.sh
set -uo pipefail
cd "$(dirname "$0")/.."
MINUTES=${MINUTES:-7}
RECIPE=${RECIPE:-wide}
INIT=${INIT:-genre_backend/weights/default.safetensors}
PACK=${PACK:-.pack}
OUT=${OUT:-$PWD/out/device}
PY=${PY:-python3}
BURST_ARGS=${BURST_ARGS:-}  # more options for genre train burst (a smoke run here: --device cpu --shapes 8 --max-steps 3)
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null || echo "no nvidia-smi"
"$PY" -c "import torch, numpy; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(), 'numpy', numpy.__version__)"
if [ -d .whl ] && ls .whl/*.whl >/dev/null 2>&1; then
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    && export PYTHONPATH=$PYTHONPATH:/tmp/site
fi
mkdir -p "$OUT/burst"
"$PY" -m training.learn.burst --pack "$PACK" --init "$INIT" --out "$OUT/burst" --recipe "$RECIPE" --minutes "$MINUTES" \
  --log-every 50 $BURST_ARGS
burst=$?
echo "burst exit $burst"
# the CUDA cases of the geometry tests (skipped on machines without a GPU, so CI never runs them)
timeout 240 "$PY" -m pytest -q -p no:cacheprovider -o addopts="" tests/backend/geometry/test_spherical.py tests/backend/geometry/test_voxels.py tests/training/learn/test_burst.py -k cuda
echo "cuda tests exit $?"
ls -la "$OUT/burst"
exit $burst
