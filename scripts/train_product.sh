#!/usr/bin/env bash
# The product model, the `default` weights users get: trained on every class of the corpus (less
# the product test split, which holds out shapes of every class) and the procedural shapes, on
# photo-composited renders.  Training accumulates: data and runs live under $GENRE_HOME (default
# ~/.cache/genre), a run with no checkpoint starts from the shipped `default` weights, and every
# invocation adds ROUNDS rounds of ROUND_STEPS joint steps to what is there, scoring the product
# test split after each round (the learning curve: results/product/learning_curve.csv).
# Every step resumes where it stopped: run the script again after an interruption.
#   ROUNDS=2 ROUND_STEPS=600 bash scripts/train_product.sh     # two more rounds
#   SKIP_TO=NAME starts at the step whose log name is NAME; DRY_RUN=1 prints the steps.
# A fresh machine continuing the shipped product model (no run here yet):
#   FIRST_CHAIN=0 BASE_HOURS=2.44 CURVE_PREFIX=s2_ ROUNDS=3 ROUND_STEPS=1000 bash scripts/train_product.sh
# (joint rounds straight from the shipped weights; the curve's hours continue from the 2.44 h behind them,
# and its labels get a prefix so they do not replace the earlier run's points).
# The refiner grown by a full-resolution branch (recipe product_full), its refine stage from the shipped weights,
# then joint rounds:
#   RECIPE=product_full FIRST_CHAIN=refine RUN=$GENRE_HOME/runs/product_full ROUNDS=0 bash scripts/train_product.sh
# Installing the weights is a separate, deliberate step (the rule is fixed in
# results/decisions.md): see the end of this script.
set -euo pipefail
cd "$(dirname "$0")/.."
G=.venv/bin/genre
PY=.venv/bin/python
GENRE_HOME=${GENRE_HOME:-${GENRE_DATA_DIR:-$($PY -c 'from training.data.corpus import data_dir; print(data_dir())')}}
export GENRE_HOME
M=$GENRE_HOME/corpus/manifest.json
VIEWS=${VIEWS:-$GENRE_HOME/views/product}
EVAL_VIEWS=${EVAL_VIEWS:-$GENRE_HOME/views/product_eval}
# More views of the training primitives (regular shapes are what a new user tries first, and the
# product test split holds only 14 of them), and 8 views of each test primitive for a steadier figure.
PRIM_VIEWS=${PRIM_VIEWS:-$GENRE_HOME/views/product_primitives}
PRIM_EVAL_VIEWS=${PRIM_EVAL_VIEWS:-$GENRE_HOME/views/primitives_eval}
PRIMITIVE_VIEWS=${PRIMITIVE_VIEWS:-12}
RUN=${RUN:-$GENRE_HOME/runs/product}
SCORES=${SCORES:-$GENRE_HOME/results/product}      # genre eval folders of each round (large; not committed)
RESULTS=${RESULTS:-results/product}                # the committed tables and the learning curve
BACKGROUNDS=${BACKGROUNDS:-$GENRE_HOME/backgrounds}
VIEWS_PER_SHAPE=${VIEWS_PER_SHAPE:-4}
ROUNDS=${ROUNDS:-1}
ROUND_STEPS=${ROUND_STEPS:-600}
EVAL_JOBS=${EVAL_JOBS:-2}
# Where a run with no checkpoint starts: the shipped product weights, so that training on a fresh
# machine adds to what was shipped instead of starting over.
INIT=${INIT:-genre_backend/weights/default.safetensors}
# Processor hours behind INIT (earlier runs: the learning curve's last installed point), so that the curve's
# hours stay cumulative when a fresh machine starts over from the shipped weights.
BASE_HOURS=${BASE_HOURS:-0}
# FIRST_CHAIN=0: start with the joint stage from INIT (weights that are already a joint-trained product
# model) instead of re-running depth, inpaint and refine from it; FIRST_CHAIN=refine: the refine stage only.
FIRST_CHAIN=${FIRST_CHAIN:-1}
RECIPE=${RECIPE:-product}  # training/learn/recipe.py: product, or product_full (the refiner grown)
CURVE_PREFIX=${CURVE_PREFIX:-}
# The level every score is read at (results/decisions.md): the one the starting weights install.
LEVEL=${LEVEL:-$($PY -c "import sys; from genre_backend.nets.model import load_model; print(load_model(sys.argv[1]).config.geometry.default_threshold)" "$INIT")}
SKIP_TO=${SKIP_TO:-}
DRY_RUN=${DRY_RUN:-}
LOGS=$GENRE_HOME/logs
[ -n "$DRY_RUN" ] || mkdir -p "$LOGS" "$RESULTS"
log() { if [ -n "$DRY_RUN" ]; then echo "$*"; else echo "$(date -u +%FT%TZ) $*" | tee -a "$LOGS/product_chain.log"; fi; }
step() {
  local name=$1; shift
  if [ -n "$SKIP_TO" ] && [ "$SKIP_TO" != "$name" ]; then log "skip: $name"; return; fi
  SKIP_TO=""
  if [ -n "$DRY_RUN" ]; then log "step $name: $*"; return; fi
  local t0=$SECONDS; log "start: $name: $*"; "$@"; log "done in $((SECONDS - t0)) s: $name"
}
ck_step() {  # the step count of a stage's checkpoint (0 when none)
  local f=$RUN/$1/checkpoint/state.json
  if [ -f "$f" ]; then $PY -c "import json,sys; print(json.load(open(sys.argv[1]))['step'])" "$f"; else echo 0; fi
}
first() { [ -f "$RUN/$1/checkpoint/state.json" ] && echo "" || echo "--init $2"; }

step fetch   $G data fetch
step build   $G data build
step backgrounds $G data backgrounds
step render  $G data render --shapes "$M" --split product-train --out "$VIEWS" --views "$VIEWS_PER_SHAPE" --preset default --no-progress
step targets $G data targets --views "$VIEWS" --no-progress
step render_eval $G data render --shapes "$M" --split product-test --out "$EVAL_VIEWS" --views 1 --preset default --seed 1 --no-progress
step targets_eval $G data targets --views "$EVAL_VIEWS" --no-progress
step render_primitives $G data render --shapes "$M" --split product-train --classes primitive --out "$PRIM_VIEWS" \
  --views "$PRIMITIVE_VIEWS" --preset default --seed 2 --no-progress
step targets_primitives $G data targets --views "$PRIM_VIEWS" --no-progress
step render_primitives_eval $G data render --shapes "$M" --split product-test --classes primitive --out "$PRIM_EVAL_VIEWS" \
  --views 8 --preset default --seed 3 --no-progress
step targets_primitives_eval $G data targets --views "$PRIM_EVAL_VIEWS" --no-progress

T=($G train --recipe "$RECIPE" --data "$VIEWS" "$PRIM_VIEWS" --out "$RUN" --backgrounds "$BACKGROUNDS" --no-progress)
# The first chain: each stage once, from the shipped weights (the recipe's budgets).
JOINT_INIT=$INIT
if [ "$FIRST_CHAIN" = 1 ]; then
  step depth   "${T[@]}" depth   $(first depth "$INIT")
  step inpaint "${T[@]}" inpaint $(first inpaint "$RUN/depth/best.safetensors")
  step refine  "${T[@]}" refine  $(first refine "$RUN/inpaint/best.safetensors")
  JOINT_INIT=$RUN/refine/best.safetensors
elif [ "$FIRST_CHAIN" = refine ]; then
  step refine  "${T[@]}" refine  $(first refine "$INIT")
  JOINT_INIT=$RUN/refine/best.safetensors
fi

evaluate() {  # score weights on the product test split (and 8 views of its primitives): genre eval into $SCORES/LABEL
  # (each once: a folder with its per-view scores is kept)
  [ -f "$SCORES/$1/per_view.csv" ] || step "eval_$1" $G eval --data "$EVAL_VIEWS" --weights "$2" --groups product-test \
    --rows "GenRe,Truth through the representation" --out "$SCORES/$1" --jobs "$EVAL_JOBS" --no-figures --no-progress
  [ -f "$SCORES/primitives/$1/per_view.csv" ] || step "eval_primitives_$1" $G eval --data "$PRIM_EVAL_VIEWS" --weights "$2" --groups product-test \
    --rows "GenRe,Truth through the representation" --out "$SCORES/primitives/$1" --jobs "$EVAL_JOBS" --no-figures --no-progress
}
curve() {  # add the point LABEL to the learning curve (the hours of RUN; none: the starting point, 0 h); a third
  # argument marks it installed (the shipped default weights the run starts from; a round is marked by hand once installed)
  step "curve_$1" $PY -m training.eval.product curve ${2:+--run "$2"} --eval "$SCORES/$1" --label "$CURVE_PREFIX$1" --csv "$RESULTS/learning_curve.csv" \
    --threshold "$LEVEL" --base-hours "$BASE_HOURS" ${3:+--installed}
}
# Once: the protocol model (the side-by-side table) and the weights the run started from (the curve's first point;
# while the shipped default weights are a copy of the protocol's, the same scores).
evaluate protocol protocol
if $PY -c "import sys, torch; from safetensors.torch import load_file as f; a, b = f(sys.argv[1]), f(sys.argv[2]); \
sys.exit(0 if a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a) else 1)" "$INIT" genre_backend/weights/protocol.safetensors; then
  [ -n "$DRY_RUN" ] || [ -e "$SCORES/start" ] || ln -s protocol "$SCORES/start"
  [ -n "$DRY_RUN" ] || [ -e "$SCORES/primitives/start" ] || { mkdir -p "$SCORES/primitives"; ln -s protocol "$SCORES/primitives/start"; }
else
  evaluate start "$INIT"  # (each part once: see evaluate)
fi
# the curve's first point, once per prefix
if [ "$INIT" -ef genre_backend/weights/default.safetensors ]; then START_INSTALLED=yes; else START_INSTALLED=; fi
grep -q "^${CURVE_PREFIX}start," "$RESULTS/learning_curve.csv" 2>/dev/null || curve start "" $START_INSTALLED
LAST=start  # the label of the last weights scored (the tables below are theirs)
if [ "$FIRST_CHAIN" = refine ]; then  # the refine stage's weights are a point of the curve of their own
  evaluate refine "$JOINT_INIT"
  curve refine "$RUN"
  LAST=refine
fi
# Then rounds of joint training, every net end to end (the recipe's joint stage), scored after each.
for _ in $(seq 1 "$ROUNDS"); do
  done_steps=$( [ -n "$DRY_RUN" ] && echo 0 || ck_step joint )
  target=$(( done_steps + ROUND_STEPS ))
  step "joint_$target" "${T[@]}" joint $(first joint "$JOINT_INIT") --steps "$target"
  # each round's weights are kept (the next round overwrites joint/final): the one to install may be an earlier round's
  step "keep_$target" cp "$RUN/joint/final.safetensors" "$RUN/joint/round_$target.safetensors"
  evaluate "joint_$target" "$RUN/joint/final.safetensors"
  curve "joint_$target" "$RUN"
  LAST=joint_$target
done
step compare $PY -m training.eval.product compare --product "$SCORES/$LAST" --protocol "$SCORES/protocol" \
  --manifest "$M" --out "$RESULTS/table.md" --threshold "$LEVEL"
step compare_primitives $PY -m training.eval.product compare --product "$SCORES/primitives/$LAST" \
  --protocol "$SCORES/primitives/protocol" --manifest "$M" --out "$RESULTS/primitives.md" --threshold "$LEVEL" \
  --title "Regular primitives of the product test split, 8 views each"
# Installing (deliberately not automatic): when the rule in results/decisions.md says so,
#   $PY -m training.eval.install --name default --weights $RUN/joint/round_N.safetensors --threshold $LEVEL --hole-closing K \
#     --fp16 --test-time-mirror --pit-sealing 4
# (K from scripts/hole_closing.py on the seen-test views of those weights; the mesh settings the installed file carries,
# genre_backend/weights/default.json, each chosen by its rule in results/decisions.md)
log "done; learning curve: $RESULTS/learning_curve.csv"
