#!/usr/bin/env bash
# A diagnosis, not a product run (results/decisions.md, 2026-12-01 23:20 UTC): can the refiner fit a few shapes when
# every input it reads is true?  GenRe-SphOracle (true depth and full map) is 2.2x the Chamfer noise floor on the
# product test and about as far on the training views, so either the refiner cannot fit even its own shapes (its
# form or its inputs are the limit) or it can and 1,300 shapes are too many for it (capacity, samples).
#
#   scripts/fit_oracle.sh [COUNT] [INIT] [NAME] [RECIPE]      (defaults: 48 default X0 fit-oracle)
#
# 1. COUNT product-train shapes drawn (seed 53) from $GENRE_HOME/views/fresh88, their meshes packed
#    ($GENRE_HOME/fit/packCOUNT) and their renders linked ($GENRE_HOME/views/fitCOUNT);
# 2. genre train session --nets both --recipe RECIPE (training/learn/recipe.py: the refiner always reads the true
#    depth and the true full map) from INIT, into $GENRE_HOME/fit/run_NAME (resumes);
# 3. GenRe-SphOracle at level 0.45 on one render of each of those shapes, for INIT and for the trained file
#    ($GENRE_HOME/fit/eval_init_NAME, $GENRE_HOME/fit/eval_NAME; `genre eval` prints the means).
set -euo pipefail
H=${GENRE_HOME:?set GENRE_HOME}
N=${1:-48}; INIT=${2:-default}; NAME=${3:-X0}; RECIPE=${4:-fit-oracle}
mkdir -p "$H/fit"
python - "$H" "$N" <<'EOF'
import json, os, random, sys
home, count = sys.argv[1], int(sys.argv[2])
manifest = json.load(open(f"{home}/corpus/manifest.json"))
rendered = set(os.listdir(f"{home}/views/fresh88"))
shapes = sorted((s for s in manifest["shapes"] if "product-train" in s["groups"] and s["id"] in rendered),
                key=lambda s: s["id"])
random.Random(53).shuffle(shapes)
manifest["shapes"] = [dict(s, mesh=os.path.join(home, "corpus", s["mesh"])) for s in shapes[:count]]
json.dump(manifest, open(f"{home}/fit/manifest{count}.json", "w"))
os.makedirs(f"{home}/views/fit{count}", exist_ok=True)
for s in manifest["shapes"]:
    link = f"{home}/views/fit{count}/{s['id']}"
    if not os.path.lexists(link):
        os.symlink(f"{home}/views/fresh88/{s['id']}", link)
EOF
[ -f "$H/fit/pack$N/pack.json" ] || genre data pack --shapes "$H/fit/manifest$N.json" --out "$H/fit/pack$N" --thin 0 --no-progress
STEPS=$(python -c "from training.learn.recipe import get_burst_recipe; print(get_burst_recipe('$RECIPE').total_steps)")
genre train session --pack "$H/fit/pack$N" --nets both --recipe "$RECIPE" --init "$INIT" --out "$H/fit/run_$NAME" \
    --threads 2 --max-steps "$STEPS" --log-every 50
score() {
    genre eval --data "$H/views/fit$N" --weights "$1" --groups product-train --max-views 1 --rows GenRe-SphOracle \
        --levels 0.45 --jobs 2 --no-figures --no-progress --out "$2"
}
[ -f "$H/fit/eval_init_$NAME/per_view.csv" ] || score "$INIT" "$H/fit/eval_init_$NAME"
score "$H/fit/run_$NAME/both/weights.safetensors" "$H/fit/eval_$NAME"
