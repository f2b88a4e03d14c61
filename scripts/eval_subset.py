#!/usr/bin/env python3
"""Pick the evaluation views that fit the 2-core CPU budget and split them in two halves.

    python scripts/eval_subset.py [--views data/views/eval] [--cap 8]

Every seen-test shape, and at most ``--cap`` shapes of each unseen class (the
first by SHA-256 of the shape id: deterministic, independent of quality).
Writes folders of symbolic links: ``<views>_sub`` (all chosen shapes) and
``<views>_part_a`` / ``<views>_part_b`` (alternate halves, each with seen-test
shapes) so that two ``genre eval`` processes can share the two cores; their
``per_view.csv`` files are then concatenated into the final run's folder,
which ``genre eval`` resumes from (see ``scripts/train_default.sh``).
"""

import argparse
import hashlib
import json
import os
from collections import defaultdict
from pathlib import Path


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--views", default="data/views/eval")
    p.add_argument("--manifest", default="data/corpus/manifest.json")
    p.add_argument("--cap", type=int, default=8)
    args = p.parse_args()
    shapes = {s["id"]: s for s in json.loads(Path(args.manifest).read_text())["shapes"]}
    root = Path(args.views)
    present = sorted(d.name for d in root.iterdir() if d.is_dir() and d.name in shapes)

    def order(ids):
        return sorted(ids, key=lambda i: hashlib.sha256(i.encode()).hexdigest())

    seen = order(i for i in present if shapes[i]["split"] == "test")
    unseen = defaultdict(list)
    for i in present:
        if shapes[i]["split"] == "unseen":
            unseen[shapes[i]["class"]].append(i)
    capped = order(i for ids in unseen.values() for i in order(ids)[: args.cap])
    halves = {"a": seen[0::2] + capped[0::2], "b": seen[1::2] + capped[1::2]}
    for name, ids in (("sub", seen + capped), ("part_a", halves["a"]), ("part_b", halves["b"])):
        out = Path(f"{root}_{name}")
        out.mkdir(parents=True, exist_ok=True)
        for i in ids:
            link = out / i
            if not link.exists():
                os.symlink((root / i).resolve(), link)
        print(f"{out}: {len(ids)} shapes")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
