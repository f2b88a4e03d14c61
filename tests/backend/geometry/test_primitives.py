"""Regular-shape snapping (genre_backend.geometry.primitives, .primitive_shapes): distances against a mesh-based
reference, fits that recover known shapes in random poses, the traced depth against the analytic sphere, and the snap
decision."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from genre_backend.config import GenreConfig
from genre_backend.geometry import primitive_shapes as S
from genre_backend.geometry import primitives as P
from genre_backend.geometry.analytic import sphere_depth
from support.scripts import load_script

SHAPES = {
    "box": (0.30, 0.20, 0.10),
    "cylinder": (0.20, 0.30),
    "cone": (0.25, 0.30),
    "torus": (0.30, 0.10),
    "ellipsoid": (0.30, 0.20, 0.15),
}
CAMERA = GenreConfig().camera


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _surface(family, params, count, rng):
    from genre_backend.geometry.metrics import sample_surface

    v, f = S.family_mesh(family, params)
    return sample_surface(v, f, count, seed=int(rng.integers(1 << 30))).double().numpy()


@pytest.mark.parametrize("family", S.FAMILIES)
def test_signed_distance_matches_the_distance_to_a_fine_mesh(family):
    rng = np.random.default_rng(1)
    params = SHAPES[family]
    far = rng.uniform(-0.5, 0.5, size=(300, 3))
    near = _surface(family, params, 300, rng) + rng.normal(scale=0.02, size=(300, 3))
    pts = np.concatenate([far, near])
    ours = S.signed_distance(family, torch.from_numpy(pts), torch.tensor(params, dtype=torch.float64)).numpy()
    ref = S.signed_distance_reference(family, pts, params)
    assert (np.sign(ours) == np.sign(ref))[np.abs(ref) > 2e-3].all()
    if family == "ellipsoid":  # a first-order estimate: exact on the surface, close near it
        close = np.abs(ref) < 0.03
        assert np.abs(ours - ref)[close].max() < 0.01
    else:  # exact, up to the faceting of the reference's 96 sections
        assert np.abs(ours - ref).max() < 2e-3


@pytest.mark.slow
@pytest.mark.parametrize("family", S.FAMILIES)
def test_a_posed_shape_seen_from_one_side_is_recovered(family):
    """Half the surface (the side toward the camera) and the whole surface as the mesh: the family, its size and its
    pose come back (the shape's own symmetries aside: compared through the distance of the true surface)."""
    rng = np.random.default_rng(7)
    params = SHAPES[family]
    rot, centre = _rotation(rng), np.array([0.03, -0.02, 0.05])
    pts = _surface(family, params, 4000, rng) @ rot.T + centre
    visible = pts[pts[:, 2] > np.median(pts[:, 2])]
    fit = P.fit_primitive(visible, pts)
    assert fit.family == family
    assert np.allclose(sorted(fit.params), sorted(params), atol=0.015) if family in ("box", "ellipsoid") \
        else np.allclose(fit.params, params, atol=0.015)
    err = fit.sdf(torch.from_numpy(pts)).abs()
    assert float(err.mean()) < 0.006 and float(err.max()) < 0.03  # (the diagonals are 0.6-0.8)


def test_trace_depth_is_the_analytic_sphere_and_the_outline_agrees_with_itself():
    fit = P.PrimitiveFit("ellipsoid", (0.3, 0.3, 0.3), np.eye(3), np.zeros(3), 0.0, 0.0, 0.0)
    traced = P.trace_depth(fit, CAMERA, 96).double()
    truth = sphere_depth(CAMERA, 96, 0.3)[0]
    both = (traced > 0) & (truth > 0)
    assert torch.equal(traced > 0, truth > 0)
    assert float((traced - truth)[both].abs().max()) < 2e-3
    assert P.outline_disagreement(fit, truth.float(), CAMERA) < 0.01
    box = P.PrimitiveFit("box", (0.3, 0.3, 0.3), np.eye(3), np.zeros(3), 0.0, 0.0, 0.0)
    assert P.outline_disagreement(box, truth.float(), CAMERA) > 0.15  # a square is no disc


def _traced(family, params, rot, centre):
    return P.trace_depth(P.PrimitiveFit(family, params, rot, centre, 0.0, 0.0, 0.0), CAMERA, 128)


@pytest.mark.slow
def test_snap_replaces_a_cylinder_and_keeps_an_l_shaped_block():
    import trimesh

    from genre_backend.geometry.cleanup import is_watertight

    rng = np.random.default_rng(3)
    rot, centre = _rotation(rng), np.zeros(3)
    depth = _traced("cylinder", SHAPES["cylinder"], rot, centre)
    v, f = S.family_mesh("cylinder", SHAPES["cylinder"])
    lumpy = (v @ rot.T + centre) * (1 + 0.02 * np.sin(7 * v[:, :1]))  # the refiner's blur, roughly
    # (the lumps leave a disagreement of 0.030-0.035 depending on the machine's floating-point paths: measured 0.035
    # on this project's 2-core Xeon with the same pinned torch; the L below is above 0.05 everywhere)
    sv, sf, fit = P.snap(lumpy, f, depth, CAMERA, 0.045)
    assert fit is not None and fit.family == "cylinder" and fit.residual < 0.045
    assert sv.shape != lumpy.shape and is_watertight(sf)
    assert np.allclose(fit.params, SHAPES["cylinder"], atol=0.02)
    # off: nothing is fitted
    same_v, same_f, none = P.snap(lumpy, f, depth, CAMERA, 0.0)
    assert none is None and same_v is lumpy and same_f is f
    # two boxes in an L: no single family covers its outline, so the mesh stays
    a, b = (0.3, 0.08, 0.1), (0.08, 0.25, 0.1)
    ca, cb = np.array([0.0, -0.17, 0.0]), np.array([-0.22, 0.0, 0.0])
    da, db = _traced("box", a, np.eye(3), ca), _traced("box", b, np.eye(3), cb)
    ell = torch.where((da > 0) & (db > 0), torch.minimum(da, db), torch.maximum(da, db))
    mesh = trimesh.util.concatenate([trimesh.creation.box(extents=[2 * x for x in a]).apply_translation(ca),
                                     trimesh.creation.box(extents=[2 * x for x in b]).apply_translation(cb)])
    lv, lf = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    kv, kf, fit = P.snap(lv, lf, ell, CAMERA, 0.03)
    assert fit is not None and fit.residual > 0.05 and kv is lv and kf is lf


def test_bad_input_is_refused():
    pts = np.random.default_rng(0).normal(size=(100, 3))
    with pytest.raises(ValueError, match="16"):
        P.fit_primitive(pts[:5], pts)
    with pytest.raises(ValueError, match="finite"):
        P.fit_primitive(np.vstack([pts, [np.nan, 0, 0]]), pts)
    with pytest.raises(ValueError, match="families"):
        P.fit_primitive(pts, pts, families=("pyramid",))
    with pytest.raises(ValueError, match="tolerance"):
        P.snap(pts, np.zeros((1, 3), dtype=np.int64), torch.zeros(8, 8), CAMERA, 1.5)
    with pytest.raises(ValueError, match="primitive_snap"):
        GenreConfig().geometry.__class__(primitive_snap=-0.1)


def test_the_tolerance_is_the_grid_value_with_the_lowest_mean_cd():
    """scripts/primitive_snap.py's rule: a view is snapped when its fit's disagreement (1 − IoU, or twice the mesh's
    distance to it) is at most tau; the lowest mean CD wins, ties go to the smaller tau."""
    script = load_script("primitive_snap")
    rec = lambda mesh, fit, res, mres=0.0: {"cd_mesh": mesh, "cd_fit": fit, "residual": res, "mesh_residual": mres}  # noqa: E731
    # the last view fits the outline (1 − IoU 0.01) but leaves the mesh (0.03, doubled: 0.06)
    views = [rec(0.10, 0.05, 0.015), rec(0.12, 0.06, 0.025), rec(0.08, 0.20, 0.045), rec(0.09, 0.30, 0.2), rec(0.10, 0.04, 0.01, 0.03)]
    best, means = script.choose(views, [0.0, 0.01, 0.02, 0.03, 0.05, 0.06])
    assert means[0.0] == pytest.approx(np.mean([0.10, 0.12, 0.08, 0.09, 0.10]))
    assert means[0.02] == pytest.approx(np.mean([0.05, 0.12, 0.08, 0.09, 0.10]))
    assert means[0.05] == pytest.approx(np.mean([0.05, 0.06, 0.20, 0.09, 0.10]))
    assert means[0.06] == pytest.approx(np.mean([0.05, 0.06, 0.20, 0.09, 0.04]))
    assert best == 0.03 and means[0.03] == pytest.approx(np.mean([0.05, 0.06, 0.08, 0.09, 0.10]))
    assert script.choose([rec(0.1, 0.2, 0.001)], [0.0, 0.01])[0] == 0.0  # snapping that only hurts stays off


@pytest.mark.slow
def test_the_fit_is_the_same_inside_inference_mode():
    """genre reconstruct runs its stages under torch.inference_mode, where autograd is off and tensors made there
    cannot take part in it: the fit must still run, and give the same shape."""
    rot = _rotation(np.random.default_rng(5))
    depth = _traced("torus", SHAPES["torus"], rot, np.zeros(3))
    v, f = S.family_mesh("torus", SHAPES["torus"])
    v = v @ rot.T
    plain = P.snap(v, f, depth, CAMERA, 0.05)[2]
    with torch.inference_mode():
        inside = P.snap(v, f, depth.clone(), CAMERA, 0.05)[2]
    assert plain.family == inside.family == "torus" and plain.params == inside.params and plain.residual == inside.residual
