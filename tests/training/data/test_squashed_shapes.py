"""training/data/sources/squashed.py and ``genre data squashed``: one footprint, every depth, lying flat."""

import json

import numpy as np
import pytest

from training.data.cli import main as data_main
from training.data.sources.squashed import KINDS, THICKNESS, squashed_shape


@pytest.mark.parametrize("kind", KINDS)
def test_shapes_lie_flat_normalised_and_span_the_thickness_range(kind):
    ratios = []
    for k in range(40):
        sid, cls, mesh = squashed_shape(kind, k)
        assert sid == f"squashed-{kind}-{k:03d}" and cls == f"squashed-{kind}"
        lo, hi = mesh.bounds
        np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-9)  # centred on its bounding box
        assert np.isclose(np.linalg.norm(hi - lo), 1.0)  # diagonal 1
        x, y, z = mesh.extents
        assert np.isclose(x, max(x, y, z)) and 0.5 - 1e-9 <= y / x <= 1.0 + 1e-9  # the footprint's long side is x
        assert mesh.is_watertight
        ratios.append(z / x)
    ratios = np.array(ratios)
    assert THICKNESS[0] - 1e-9 <= ratios.min() and ratios.max() <= THICKNESS[1] + 1e-9
    assert ratios.min() < 0.1 and ratios.max() > 0.5  # flat ones and deep ones: every depth for the outline
    # the same shape on every call; another seed another shape
    np.testing.assert_array_equal(squashed_shape(kind, 3)[2].vertices, squashed_shape(kind, 3)[2].vertices)
    assert not np.allclose(squashed_shape(kind, 3, seed=1)[2].extents, squashed_shape(kind, 3)[2].extents)


def test_the_command_writes_meshes_and_a_manifest_the_renderer_reads(tmp_path, capsys):
    assert data_main(["squashed", "--out", str(tmp_path), "--per-kind", "2"]) == 0
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    rows = manifest["shapes"]
    assert [r["id"] for r in rows] == [f"squashed-{kind}-{k:03d}" for kind in KINDS for k in range(2)]
    for row in rows:
        assert (tmp_path / row["mesh"]).is_file() and row["split"] == "product-train"
        assert row["source"] == "procedural-squashed" and row["licence"] == "CC0"
    assert data_main(["squashed", "--out", str(tmp_path), "--per-kind", "0"]) == 2
    assert "--per-kind" in capsys.readouterr().err
