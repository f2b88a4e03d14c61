#!/usr/bin/env bash
# The whole chain that produces the default weights, on the 2-core CPU.
# Every step resumes where it stopped: run this script again after an
# interruption. Step counts can be raised to continue training (the
# checkpoint's step count carries on). Timings go to data/logs/chain.log.
set -euo pipefail
cd "$(dirname "$0")/.."
G=.venv/bin/genre
VIEWS=${VIEWS:-data/views/default}
RUN=${RUN:-runs/default}
DEPTH_STEPS=${DEPTH_STEPS:-2000}
INPAINT_STEPS=${INPAINT_STEPS:-1500}
REFINE_STEPS=${REFINE_STEPS:-1500}
JOINT_STEPS=${JOINT_STEPS:-500}
mkdir -p data/logs
log() { echo "$(date -u +%FT%TZ) $*" | tee -a data/logs/chain.log; }
step() { local t0=$SECONDS; log "start: $*"; "$@"; log "done in $((SECONDS - t0)) s: $*"; }

step $G data fetch
step $G data build
step $G data render --shapes data/corpus/manifest.json --split train --out "$VIEWS" --views 20 --preset default --no-progress
step $G data targets --views "$VIEWS" --preset default --no-progress
step $G train depth   --data "$VIEWS" --out "$RUN" --steps "$DEPTH_STEPS" --no-progress
step $G train inpaint --data "$VIEWS" --out "$RUN" --steps "$INPAINT_STEPS" --init "$RUN/depth/best.safetensors" --no-progress
step $G train refine  --data "$VIEWS" --out "$RUN" --steps "$REFINE_STEPS" --init "$RUN/inpaint/best.safetensors" --no-progress
step $G train joint   --data "$VIEWS" --out "$RUN" --steps "$JOINT_STEPS" --init "$RUN/refine/best.safetensors" --no-progress
log "weights: $RUN/joint/best.safetensors"
