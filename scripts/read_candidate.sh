#!/usr/bin/env bash
# A read of a training snapshot by the install rule (results/decisions.md; `python -m training.eval.product verdict`):
#
#   scripts/read_candidate.sh SNAPSHOT NAME [INSTALLED]
#
# 1. waits until SNAPSHOT exists (a read is named before its snapshot is written), then 30 s more for the file to
#    be complete; pauses every process whose command line matches $PAUSE (default "train joint") while it scores;
# 2. stores SNAPSHOT int8 as $GENRE_HOME/cand/NAME.safetensors (as the installed file is stored);
# 3. scores it at level 0.45 on the rule's five sets ($GENRE_HOME/views/{product_eval_photo, product_up_photo,
#    product_eval, product_up, primitives_eval}: `genre chain eval-views`, then scripts/photo_views.py --seed 81 / 82)
#    and the flat group ($GENRE_HOME/views/flat_eval, $GENRE_HOME/flat_test/manifest.json), into
#    $GENRE_HOME/scores/NAME/SET (a set already scored is kept, so a stopped read resumes);
# 4. the real flat photos (examples/flat) into $GENRE_HOME/scores/NAME/photos_flat/table.md;
# 5. with INSTALLED (a name under $GENRE_HOME/scores scored the same way), the verdict (ProductRule and the second
#    path, ParetoRule: `verdict --pareto`) into
#    $GENRE_HOME/scores/NAME/verdict.md and verdict.json.
# Run from the repository root with its .venv active. About 18 minutes on two cores. JOBS (default 2) sets genre
# eval's worker processes. FRAMING=_pf reads the same sets framed as photos are ($GENRE_HOME/views/SET_pf, made by
# `genre data photo-frame` and `genre data targets`; the photo-like ones by scripts/photo_views.py from those) into
# $GENRE_HOME/scores/NAME_pf: docs/training.md.
set -euo pipefail
H=${GENRE_HOME:?set GENRE_HOME}
SNAP=${1:?snapshot}; NAME=${2:?name}; INSTALLED=${3:-}
PAUSE=${PAUSE:-train joint}
FR=${FRAMING:-}
OUT=$H/scores/$NAME$FR; W=$H/cand/$NAME.safetensors
while [ ! -f "$SNAP" ]; do sleep 20; done
sleep 30
resume() { { pgrep -f "$PAUSE" || true; } | xargs -r kill -CONT; }
trap resume EXIT
{ pgrep -f "$PAUSE" || true; } | xargs -r kill -STOP  # nothing to pause is no error (pipefail)
mkdir -p "$H/cand" "$OUT"
[ -f "$W" ] || python -c "import sys; from genre_backend.nets.model import load_model, save_model; \
save_model(load_model(sys.argv[1]), sys.argv[2], storage='int8')" "$SNAP" "$W"
export OMP_NUM_THREADS=1
for set in product_eval_photo product_up_photo product_eval product_up primitives_eval; do
  [ -f "$OUT/$set.done" ] && continue
  data=${set%_photo}$FR; [ "$data" = "$set$FR" ] || data=${data}_photo  # product_eval_photo → product_eval_pf_photo
  genre eval --data "$H/views/$data" --groups product-test --weights "$W" --rows GenRe --levels 0.45 --gallery 0 \
    --no-figures --jobs "${JOBS:-2}" --no-progress --out "$OUT/$set" > "$OUT/$set.log" 2>&1
  echo ok > "$OUT/$set.done"
done
if [ ! -f "$OUT/flat.done" ]; then
  genre eval --data "$H/views/flat_eval$FR" --groups flat-from-above --manifest "$H/flat_test/manifest.json" \
    --weights "$W" --rows GenRe --levels 0.45 --jobs "${JOBS:-2}" --no-progress --out "$OUT/flat" > "$OUT/flat.log" 2>&1
  echo ok > "$OUT/flat.done"
fi
python scripts/eval_photos.py --photos examples/flat --no-gallery --weights "$W" --out "$OUT/photos_flat" \
  > "$OUT/photos_flat.log" 2>&1
if [ -n "$INSTALLED" ]; then
  python -m training.eval.product verdict --installed "$H/scores/$INSTALLED$FR" --candidate "$OUT" \
    --pareto --json "$OUT/verdict.json" | tee "$OUT/verdict.md"
fi
echo done > "$OUT/read.done"
