#!/usr/bin/env bash
# The research chain: produces, evaluates and installs the `protocol` weights
# (genre_backend/weights/protocol.*: trained on the seen classes only; every
# Table-1 number comes from them) on the 2-core CPU: corpus, renders, targets,
# the four GenRe stages, the two trained baselines, the evaluation views and
# `genre eval`. (The product model, `default`, is another chain.)
# Every step resumes where it stopped: run this script again after an
# interruption. Step counts can be raised to continue training (the
# checkpoint's step count carries on).
# Corpus, views, runs and logs live in the GenRe home, outside the checkout:
# $GENRE_HOME, else $GENRE_DATA_DIR (the old name), else $XDG_CACHE_HOME/genre,
# else ~/.cache/genre -- resolved by training.data.corpus.data_dir(), as in
# Python. Timings go to $GENRE_HOME/logs/chain.log; the results (RESULTS) are
# committed, so they stay in the repository's results/.
# SKIP_TO=NAME starts at the step whose log name is NAME (e.g. SKIP_TO=eval);
# DRY_RUN=1 prints the steps (and the training settings) without running them.
set -euo pipefail
cd "$(dirname "$0")/.."
G=.venv/bin/genre
GENRE_HOME=$(.venv/bin/python -c 'from training.data.corpus import data_dir; print(data_dir())')
export GENRE_HOME  # the genre commands below resolve the same home
VIEWS=${VIEWS:-$GENRE_HOME/views/default}
EVAL_VIEWS=${EVAL_VIEWS:-$GENRE_HOME/views/eval}
RUN=${RUN:-$GENRE_HOME/runs/default}
RESULTS=${RESULTS:-results/default}
TRAIN_VIEWS_PER_SHAPE=${TRAIN_VIEWS_PER_SHAPE:-20}
EVAL_TEST_VIEWS=${EVAL_TEST_VIEWS:-3}      # per seen-test shape (they also choose the honest threshold)
EVAL_UNSEEN_VIEWS=${EVAL_UNSEEN_VIEWS:-1}  # per unseen shape: every unseen shape, one random view
# The training recipe (learning rates, loss weights, step budgets of every stage) is the named
# recipe in training/learn/recipe.py; the voxel stages depart from the paper's optimiser numbers
# (why: ARCHITECTURE.md, "Where we depart from the paper").  Step budgets can be raised per
# stage to continue training: DEPTH_STEPS, INPAINT_STEPS, REFINE_STEPS, JOINT_STEPS,
# COMPLETION_STEPS, ONESTEP_STEPS (unset: the recipe's).
RECIPE=${RECIPE:-shipped}
# RECIPE=photo continues the depth net from the shipped weights on renders composited over real
# photographs ($GENRE_HOME/backgrounds, 'genre data backgrounds'); DEPTH_INIT overrides where it starts.
BACKGROUNDS=${BACKGROUNDS:-$GENRE_HOME/backgrounds}
DEPTH_INIT=${DEPTH_INIT:-}
PHOTO_ARGS=()
# RECIPE=sharp moves the shipped weights to the truncated-distance voxel target: the depth net is
# kept as shipped, every other stage (and the 3D Completion net, which starts from the same refiner)
# continues from SHARP_INIT; the 1-step baseline is trained afresh as in the shipped chain.
# Both continue the research weights, `protocol` (seen classes only), never the product model.
SHARP_INIT=${SHARP_INIT:-genre_backend/weights/protocol.safetensors}
if [ "$RECIPE" = photo ]; then
  DEPTH_INIT=${DEPTH_INIT:-genre_backend/weights/protocol.safetensors}
  PHOTO_ARGS=(--backgrounds "$BACKGROUNDS")
fi
init() { local v="${1:-}"; [ -n "$v" ] && echo "--init $v" || true; }
steps() { local v="${1:-}"; [ -n "$v" ] && echo "--steps $v" || true; }
SKIP_TO=${SKIP_TO:-}
# DRY_RUN=1: run nothing, write nothing; print each step's command, and for the training
# steps the settings they resolve to (genre train --dry-run: one JSON line each).
DRY_RUN=${DRY_RUN:-}
LOGS=$GENRE_HOME/logs
[ -n "$DRY_RUN" ] || mkdir -p "$LOGS"
log() { if [ -n "$DRY_RUN" ]; then echo "$*"; else echo "$(date -u +%FT%TZ) $*" | tee -a "$LOGS/chain.log"; fi; }
step() {
  local name=$1; shift
  if [ -n "$SKIP_TO" ] && [ "$SKIP_TO" != "$name" ]; then log "skip: $name"; return; fi
  SKIP_TO=""
  if [ -n "$DRY_RUN" ]; then
    log "step $name: $*"
    if [ "$1 $2" = "$G train" ]; then "$@" --dry-run; fi
    return
  fi
  local t0=$SECONDS; log "start: $name: $*"; "$@"; log "done in $((SECONDS - t0)) s: $name"
}
M=$GENRE_HOME/corpus/manifest.json

step fetch   $G data fetch
step build   $G data build
step render  $G data render --shapes "$M" --split train --out "$VIEWS" --views "$TRAIN_VIEWS_PER_SHAPE" --preset default --no-progress
step targets $G data targets --views "$VIEWS" --preset default --no-progress
[ "$RECIPE" = photo ] && step backgrounds $G data backgrounds
T=($G train --recipe "$RECIPE")
if [ "$RECIPE" = sharp ]; then
  DEPTH_WEIGHTS=$SHARP_INIT; COMPLETION_INIT=$SHARP_INIT; log "skip: depth (RECIPE=sharp keeps the depth net of $SHARP_INIT)"
else
  DEPTH_WEIGHTS=$RUN/depth/best.safetensors; COMPLETION_INIT=$RUN/depth/best.safetensors
  step depth   "${T[@]}" depth   --data "$VIEWS" --out "$RUN" $(steps "${DEPTH_STEPS:-}") $(init "$DEPTH_INIT") "${PHOTO_ARGS[@]}" --no-progress
fi
step inpaint "${T[@]}" inpaint --data "$VIEWS" --out "$RUN" $(steps "${INPAINT_STEPS:-}") --init "$DEPTH_WEIGHTS" --no-progress
step refine  "${T[@]}" refine  --data "$VIEWS" --out "$RUN" $(steps "${REFINE_STEPS:-}") --init "$RUN/inpaint/best.safetensors" --no-progress
step joint   "${T[@]}" joint   --data "$VIEWS" --out "$RUN" $(steps "${JOINT_STEPS:-}") --init "$RUN/refine/best.safetensors" --no-progress
# Evaluation views: seen-test and both unseen groups.
step render_eval bash -c "$G data render --shapes $M --split test --out $EVAL_VIEWS --views $EVAL_TEST_VIEWS --preset default --seed 1 --no-progress &&
  for s in unseen unseen-pix3d; do $G data render --shapes $M --split \$s --out $EVAL_VIEWS --views $EVAL_UNSEEN_VIEWS --preset default --seed 1 --no-progress; done"
step targets_eval $G data targets --views "$EVAL_VIEWS" --preset default --no-progress
# Baselines, same data and the recipe's budgets: the completion net gets the refiner's steps;
# 1-step gets half the depth net's, to fit the CPU budget.
step completion "${T[@]}" completion --data "$VIEWS" --out "$RUN" $(steps "${COMPLETION_STEPS:-${REFINE_STEPS:-}}") --init "$COMPLETION_INIT" --no-progress
step onestep    "${T[@]}" onestep    --data "$VIEWS" --out "$RUN" $(steps "${ONESTEP_STEPS:-}") --no-progress
# The full evaluation views: every seen-test shape (EVAL_TEST_VIEWS views) and every unseen shape
# (EVAL_UNSEEN_VIEWS), scored by EVAL_JOBS worker processes side by side.
EVAL_JOBS=${EVAL_JOBS:-2}
step eval $G eval --data "$EVAL_VIEWS" --out "$RESULTS" --run "$RUN" --train-views "$VIEWS" --manifest "$M" --jobs "$EVAL_JOBS" \
  --heatmap-shapes 2 --gallery 2 --no-progress
# Installed as the research weights, `protocol`. The product weights, `default`, are rewritten only while
# they are still the interim copy of `protocol` (their sidecar says "copy_of": "protocol").
step install .venv/bin/python -m training.eval.install --weights "$RUN/joint/best.safetensors" --thresholds "$RESULTS/thresholds.json" \
                     --name protocol
log "weights: genre_backend/weights/protocol.safetensors; results: $RESULTS; home: $GENRE_HOME"
