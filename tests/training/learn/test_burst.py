"""The GPU burst's path, run on the CPU: the training pack, the samples the device makes (against Blender's
renders and the exact targets), the burst trainer for a few steps, and its shards read back bit for bit."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from genre_backend.config import CameraConfig
from genre_backend.frame import camera_rotation
from genre_backend.geometry.mesh_voxels import mesh_to_distance
from genre_backend.geometry.triangle_distance import point_mesh_distance_reference, point_triangles_distance
from genre_backend.geometry.raster import mesh_depth, mesh_depth_reference
from genre_backend.geometry.spherical import mesh_to_sph
from genre_backend.nets.model import GenRe, load_model, save_model
from support.tiny_data import TINY, write_manifest

ROOT = Path(__file__).resolve().parents[3]
# the device tests run on a lent GPU too (scripts/gpu_burst.sh runs every "cuda" case)
DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device"))]


def _posed(mesh: trimesh.Trimesh, az: float, el: float) -> torch.Tensor:
    """The mesh's triangles (T, 3, 3) in the view frame of a camera at (az, el)."""
    rot = camera_rotation(az, el, dtype=torch.float64)[0]
    return torch.from_numpy(mesh.vertices[mesh.faces]) @ rot


@pytest.mark.parametrize("device", DEVICES)
def test_mesh_depth_matches_its_reference(device):
    torus = trimesh.creation.torus(0.3, 0.08, major_sections=12, minor_sections=6)
    box = trimesh.creation.box(extents=(0.5, 0.2, 0.3))
    cam = CameraConfig()
    tris = [_posed(torus, 30.0, 50.0), _posed(box, 200.0, -5.0)]
    got = mesh_depth(torch.cat(tris).to(device),
                     torch.cat([torch.full((len(t),), i, dtype=torch.int64) for i, t in enumerate(tris)]).to(device),
                     2, cam, 24).cpu()
    for i, t in enumerate(tris):
        ref = mesh_depth_reference(t.numpy(), cam, 24)
        assert ((got[i].numpy() > 0) == (ref > 0)).all()
        assert np.abs(got[i].numpy() - ref).max() < 1e-12
        assert (ref > 0).sum() > 40  # the shapes cover pixels
    with pytest.raises(ValueError, match="in front of the camera"):
        mesh_depth(torch.tensor([[[0.0, 0.0, 3.0], [0.1, 0.0, 3.0], [0.0, 0.1, 3.0]]]), torch.zeros(1, dtype=torch.int64), 1, cam, 8)


@pytest.mark.parametrize("device", DEVICES)
def test_point_triangles_distance_matches_its_reference(device):
    mesh = trimesh.creation.icosphere(subdivisions=1, radius=0.3)
    # a degenerate triangle (a segment) and one far away
    tris = np.concatenate([mesh.vertices[mesh.faces], [[[0.4, 0.0, 0.0], [0.5, 0.0, 0.0], [0.45, 0.0, 0.0]]]])
    points = np.random.default_rng(0).uniform(-0.6, 0.6, (300, 3))
    got = point_triangles_distance(torch.from_numpy(points).to(device), torch.from_numpy(tris).to(device),
                                   chunk_pairs=500).cpu().numpy()
    v = tris.reshape(-1, 3)
    ref = point_mesh_distance_reference(points, v, np.arange(len(v)).reshape(-1, 3))
    assert np.abs(got - ref).max() < 1e-12


@pytest.mark.parametrize("device", DEVICES)
def test_near_surface_distance_is_exact_within_its_reach(device):
    from genre_backend.geometry.triangle_distance import near_surface_distance

    torus = trimesh.creation.torus(0.3, 0.06, major_sections=24, minor_sections=8)
    tris = torch.from_numpy(torus.vertices[torus.faces]).to(device)
    points = torch.from_numpy(np.random.default_rng(1).uniform(-0.45, 0.45, (4000, 3))).to(device)
    full = point_triangles_distance(points, tris)
    near = near_surface_distance(points, tris, reach=0.05, block=0.07, chunk_pairs=20_000)
    inside = full <= 0.05
    assert int(inside.sum()) > 200
    assert torch.equal(near[inside], full[inside])
    assert bool((near[~inside] >= full[~inside]).all())


def test_pack_holds_the_training_split_only_and_reads_back(tmp_path):
    from training.data.pack import build_pack, read_pack

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)  # 1,280 faces
    box = trimesh.creation.box(extents=(0.6, 0.3, 0.4))
    held_out = trimesh.creation.cylinder(0.3, 0.5)
    manifest = write_manifest(tmp_path, {"sphere": (sphere, "product-train"), "box": (box, "product-train"),
                                    "cyl": (held_out, "product-test")})
    meta = build_pack(manifest, tmp_path / "pack", max_faces=200)
    pack = read_pack(tmp_path / "pack")
    assert pack.ids == ["sphere", "box"] and meta["classes"] == {"primitive": 2}
    v, f = pack.mesh(1)
    assert len(f) == 12 and np.abs(np.sort(v, axis=0) - np.sort(box.vertices, axis=0)).max() <= 0.5 / 65535 + 1e-7
    vs, fs = pack.mesh(0)
    assert len(fs) <= 200 and meta["shapes"][0]["faces_source"] == 1280
    # decimated, the sphere stays a sphere of radius 0.5 to within a few hundredths
    assert np.abs(np.linalg.norm(vs, axis=1) - 0.5).max() < 0.03
    with pytest.raises(ValueError, match="never a test split"):
        build_pack(manifest, tmp_path / "bad", split="product-test")
    with pytest.raises(ValueError, match="budget"):
        build_pack(manifest, tmp_path / "big", max_mib=1e-4)
    raw = bytearray((tmp_path / "pack" / "meshes.npz").read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    (tmp_path / "pack" / "meshes.npz").write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="damaged"):
        read_pack(tmp_path / "pack")
    js = json.loads((tmp_path / "pack" / "pack.json").read_text())
    js["shapes"][0]["groups"] = ["product-test"]
    (tmp_path / "pack" / "pack.json").write_text(json.dumps(js))
    with pytest.raises(ValueError, match="test split"):
        read_pack(tmp_path / "pack", verify=False)


@pytest.fixture(scope="module")
def tiny_pack(tiny_views, tmp_path_factory):
    """A pack of the tiny views' two meshes (box and table), undecimated, and the views' folder."""
    from training.data.pack import build_pack

    tmp = tmp_path_factory.mktemp("pack")
    meshes = tiny_views.parent / "meshes"
    manifest = write_manifest(tmp, {name: (trimesh.load(meshes / f"{name}.ply", process=False), "product-train")
                               for name in ("box", "table")})
    build_pack(manifest, tmp / "pack", max_faces=65535)
    return tmp / "pack", tiny_views


def test_samples_made_on_the_device_match_blender_and_the_exact_targets(tiny_pack):
    from training.data.pack import read_pack
    from training.data.targets import load_targets
    from training.learn.burst import ViewMaker

    pack_dir, views = tiny_pack
    pack = read_pack(pack_dir)
    maker = ViewMaker(pack, TINY, torch.device("cpu"), grid_factor=2)
    for i, sid in enumerate(pack.ids):
        cam = json.loads((views / sid / "view_000.json").read_text())
        s = maker.make(torch.tensor([i]), torch.tensor([cam["azimuth_deg"]]), torch.tensor([cam["elevation_deg"]]))
        with np.load(views / sid / "view_000.npz") as z:
            b_depth, b_mask = z["depth"], z["mask"] > 0.5
        depth = s["depth"][0].numpy()
        both = (depth > 0) & b_mask & (b_depth > 0)
        iou = ((depth > 0) & b_mask).sum() / ((depth > 0) | b_mask).sum()
        assert iou > 0.95, (sid, iou)  # Blender's film alpha is anti-aliased at the outline
        assert np.median(np.abs(depth - b_depth)[both]) < 1e-4
        t = load_targets(views / sid, 0, TINY.geometry)
        assert np.abs(s["full_sph"][0].numpy() - t["full_sph"]).mean() < 1e-3
        # the voxel target resampled from the object-frame grid, against the exact distance of the posed mesh
        v, f = pack.mesh(i)
        rot = camera_rotation(cam["azimuth_deg"], cam["elevation_deg"])[0]
        exact = mesh_to_distance(torch.from_numpy(v) @ rot, torch.from_numpy(f), TINY.geometry.voxel_size,
                                 TINY.geometry.distance_band).numpy()
        got = s["voxels"][0].numpy()
        band = (exact > 0) | (got > 0)
        assert np.abs(got - exact)[band].mean() < 0.05
        inside = (got > 0.45) & (exact > 0.45)
        assert inside.sum() / ((got > 0.45) | (exact > 0.45)).sum() > 0.9
        # and the spherical map is the exact one of the posed mesh
        sph = mesh_to_sph(torch.from_numpy(v) @ rot, torch.from_numpy(f), TINY.geometry.sph_size)
        assert torch.allclose(s["full_sph"][0], sph, atol=1e-5)


def test_shards_read_back_bit_for_bit(tmp_path):
    from training.learn.burst import read_shards, write_shards

    torch.manual_seed(0)
    model = GenRe(TINY)
    paths = write_shards(model, tmp_path, {"step": 3}, shard_bytes=64 * 1024)  # small shards: big tensors are cut
    assert len(paths) > 3 and all(p.stat().st_size <= 64 * 1024 + 16 * 1024 for p in paths)  # (+ the JSON header)
    index = json.loads((tmp_path / "weights.index.json").read_text())
    assert index["split"]  # at least one tensor was cut into parts
    back, meta = read_shards(tmp_path)
    assert meta == {"step": 3}
    a, b = model.state_dict(), back.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    paths[0].write_bytes(paths[0].read_bytes()[:-8])
    with pytest.raises(ValueError, match="damaged"):
        read_shards(tmp_path)


@pytest.mark.slow
def test_burst_trains_on_the_cpu_and_returns_weights(tiny_pack, tmp_path):
    """The CPU dry run: a few steps of each recipe from tiny weights; the shards come back and join into a weights file."""
    from training.learn.burst import BurstSpec, main, read_shards, run_burst

    pack_dir, _ = tiny_pack
    torch.manual_seed(0)
    init = tmp_path / "init.safetensors"
    save_model(GenRe(TINY), init)
    for recipe in ("keep", "wide"):
        out = tmp_path / recipe
        summary = run_burst(BurstSpec(pack=str(pack_dir), init=str(init), out=str(out), recipe=recipe, minutes=10,
                                      batch_size=2, device="cpu", max_steps=3, log_every=1), say=lambda m: None)
        assert summary["steps"] == 3 and summary["samples"] == 6 and math.isfinite(summary["last_loss"])
        for name in ("weights.index.json", "log.csv", "loss.png"):
            assert (out / name).is_file()
        model, meta = read_shards(out)
        assert meta["step"] == 3 and meta["final"] and meta["summary"]["samples"] == 6
        start = load_model(init).state_dict()
        trained = model.state_dict()
        assert all(torch.equal(trained[k], v) for k, v in start.items() if k.startswith("depth_net."))  # the depth net is kept
        if recipe == "keep":
            assert any(not torch.equal(trained[k], v) for k, v in start.items() if k.startswith("refiner."))
    assert model.config.network.refiner_nf == 16  # the wide recipe's refiner
    joined = tmp_path / "joined.safetensors"
    assert main(["--join", str(tmp_path / "wide"), "--save", str(joined)]) == 0
    again = load_model(joined).state_dict()
    assert all(torch.equal(again[k], v) for k, v in model.state_dict().items())


def test_training_code_is_numpy_2_clean():
    """The burst runs under numpy 2 on the device: ruff's NPY201 finds the names numpy 2 removed."""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "ruff", "check", "--select", "NPY201", "--no-cache",
                           "genre_backend", "training"], cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr


def test_the_repository_travels_with_its_pack():
    """A device call carries 64 MiB: the tracked tree, the pack and the wheels must fit with a margin."""
    import subprocess

    from training.data.pack import DEVICE_CARRY_MIB, PACK_BUDGET_MIB, TREE_BUDGET_MIB, WHEELS_BUDGET_MIB

    assert TREE_BUDGET_MIB + PACK_BUDGET_MIB + WHEELS_BUDGET_MIB <= DEVICE_CARRY_MIB - 3  # 3 MiB spare
    files = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout.split(b"\0")
    tracked = sum((ROOT / f.decode()).stat().st_size for f in files if f and (ROOT / f.decode()).is_file())
    assert tracked <= TREE_BUDGET_MIB * 2**20, f"the tracked tree is {tracked / 2**20:.1f} MiB"


def test_the_devices_bf16_channels_last_step_matches_float32(tiny_pack):
    """What only the GPU runs (bf16 autocast, channels-last tensors), run on the CPU: the same loss to bf16's precision."""
    from training.data.pack import read_pack
    from training.learn.burst import ViewMaker, _step_loss, widen
    from training.learn.recipe import get_burst_recipe

    torch.manual_seed(0)
    model, _ = widen(GenRe(TINY), "wide")
    model.eval()  # batch statistics would differ between the two passes' batches otherwise (the same batch here)
    maker = ViewMaker(read_pack(tiny_pack[0]), TINY, torch.device("cpu"))
    sample = maker.make(torch.tensor([0, 1]), torch.tensor([30.0, 200.0]), torch.tensor([20.0, 70.0]), 0.01,
                        torch.Generator().manual_seed(0))
    recipe = get_burst_recipe("wide")
    with torch.no_grad():
        ref, _ = _step_loss(model, sample, recipe, amp=False, channels_last=False)
        model.inpaint_net.to(memory_format=torch.channels_last)
        model.refiner.to(memory_format=torch.channels_last_3d)
        got, terms = _step_loss(model, sample, recipe, amp=True, channels_last=True)
    assert math.isfinite(float(got)) and all(math.isfinite(float(v)) for v in terms.values())
    assert abs(float(got) - float(ref)) <= 0.05 * abs(float(ref))
    # and its backward pass reaches both trained nets with finite gradients, in training mode
    model.train()
    loss, _ = _step_loss(model, sample, recipe, amp=True, channels_last=True)
    loss.backward()
    for net in (model.inpaint_net, model.refiner):
        grads = [p.grad for p in net.parameters() if p.grad is not None]
        assert grads and all(bool(torch.isfinite(g).all()) for g in grads)
