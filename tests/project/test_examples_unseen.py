"""The example photos are honest: no example's stated source shape is a training shape of a shipped model.

``examples/README.md`` names each example's source shape on a line ``shape id: ID``; the training
shapes of the shipped weights are the first column of the tables in
``genre_backend/weights/TRAINING_SHAPES_DEFAULT.md`` (``default``) and ``TRAINING_SHAPES.md``
(``protocol``).  Fast, no model, no corpus.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
WEIGHTS = REPO / "genre_backend" / "weights"
TRAINING_LISTS = {"default": WEIGHTS / "TRAINING_SHAPES_DEFAULT.md", "protocol": WEIGHTS / "TRAINING_SHAPES.md"}
SHAPE_ID_LINE = re.compile(r"^\s*shape id:\s*`?([A-Za-z0-9_.\-]+)`?\s*$", re.MULTILINE | re.IGNORECASE)


def training_shape_ids(path: Path) -> set[str]:
    """The shape ids of a ``genre data credits`` table: the first cell of each row, header and rule skipped.

    The heading says how many shapes the split has (``# Shapes of the 'train' split (220)``); the parse
    must find exactly that many, so a change of format cannot make the list silently empty.
    """
    text = path.read_text(encoding="utf-8")
    ids = []
    for line in text.splitlines():
        if not line.startswith("|"):
            continue
        first = line.strip("|").split("|")[0].strip()
        if first in ("shape", "") or set(first) <= set("-: "):
            continue
        ids.append(first)
    heading = re.search(r"^# Shapes of the '[^']+' split \((\d+)\)", text, re.MULTILINE)
    assert heading, f"{path.name}: no '# Shapes of the ... split (N)' heading"
    assert len(ids) == int(heading.group(1)) == len(set(ids)), (path.name, len(ids), heading.group(1))
    return set(ids)


def example_shape_ids(readme: Path = REPO / "examples" / "README.md") -> list[str]:
    return SHAPE_ID_LINE.findall(readme.read_text(encoding="utf-8"))


def test_the_training_lists_parse():
    default, protocol = (training_shape_ids(p) for p in TRAINING_LISTS.values())
    assert len(default) == 1327 and len(protocol) == 220
    assert "sh3d-blendswap-cc-0-sofa2-132" in default  # the old demo's shape: the parse finds real rows
    assert "crrcsim-allegro" in protocol


def test_every_example_names_its_source_shape():
    ids = example_shape_ids()
    assert ids, "examples/README.md states no 'shape id:' line"
    assert "sh3d-blendswap-cc-by-sofa3-119" in ids  # examples/sofa.png


@pytest.mark.parametrize("model", sorted(TRAINING_LISTS))
def test_no_example_is_a_training_shape(model):
    trained = training_shape_ids(TRAINING_LISTS[model])
    seen = [i for i in example_shape_ids() if i in trained]
    assert not seen, f"examples/README.md calls these unseen, but the {model!r} weights trained on them: {seen}"


def test_the_check_catches_a_training_shape(tmp_path):
    """The parse of README lines works on the old, wrong demo: it would have failed."""
    readme = tmp_path / "README.md"
    readme.write_text("A sofa.\n\nshape id: sh3d-blendswap-cc-0-sofa2-132\nlicence: CC0\n", encoding="utf-8")
    ids = example_shape_ids(readme)
    assert ids == ["sh3d-blendswap-cc-0-sofa2-132"]
    assert set(ids) & training_shape_ids(TRAINING_LISTS["default"])
