"""Geometry demo: a real Blender render pushed through GenRe's projections.

Until the networks are trained, ``make demo`` shows what exists end to end:

1. Blender's Suzanne, normalised into the object frame, is rendered headless
   with Cycles (RGB, Z-pass depth, alpha mask) by :mod:`training.render.scene`.
2. The rendered depth becomes the partial spherical map; the mesh's own full
   spherical map (ground truth) stands in for the inpainting network
   (the paper's *GenRe-SphOracle* path).
3. Both are back-projected to voxels, combined, and meshed by marching cubes
   in the viewer-centred frame; the Chamfer distance to the true shape is
   printed, and a preview PNG shows every intermediate.

Run: ``python -m training.demo_geometry --out out/demo``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from genre_backend import frame
from genre_backend.config import PRESETS, get_preset
from genre_backend.geometry.mesh_voxels import voxels_to_mesh
from genre_backend.geometry.metrics import mesh_chamfer
from genre_backend.geometry.spherical import depth_to_sph, mesh_to_sph, sph_to_voxels
from genre_backend.geometry.voxels import points_to_voxels
from genre_backend.arguments import add_out


def suzanne_mesh() -> tuple[np.ndarray, np.ndarray]:
    """Blender's monkey head in the object frame: (V, 3) float, (F, 3) int; centred, diagonal 1.

    Suzanne faces −Y in Blender, which is the object frame's front already.
    """
    from genre_backend.output.blender import import_bpy

    bpy = import_bpy()
    mesh = bpy.data.meshes.new("suzanne")
    import bmesh

    bm = bmesh.new()
    bmesh.ops.create_monkey(bm)
    bmesh.ops.triangulate(bm, faces=bm.faces[:])
    verts = np.array([v.co[:] for v in bm.verts], dtype=np.float64)
    faces = np.array([[v.index for v in f.verts] for f in bm.faces], dtype=np.int64)
    bm.free()
    bpy.data.meshes.remove(mesh)
    lo, hi = verts.min(0), verts.max(0)
    verts = (verts - 0.5 * (lo + hi)) / np.linalg.norm(hi - lo)
    return verts, faces


def run(out: Path, preset: str, azimuth: float, elevation: float) -> dict:
    import trimesh

    from training.data.views import ShapeEntry, load_view
    from training.render.scene import BlenderRenderer, render_shape

    cfg = get_preset(preset)
    g, cam = cfg.geometry, cfg.camera
    out.mkdir(parents=True, exist_ok=True)
    timings = {}
    t0 = time.perf_counter()
    verts, faces = suzanne_mesh()
    with tempfile.TemporaryDirectory(prefix="genre-demo-") as tmp:
        mesh_path = Path(tmp) / "suzanne.ply"
        trimesh.Trimesh(verts, faces, process=False).export(mesh_path)
        renderer = BlenderRenderer(cfg, scratch_dir=Path(tmp) / "scratch")
        render_shape(renderer, ShapeEntry("suzanne", mesh_path), [(azimuth, elevation)], Path(tmp) / "views", seed=0)
        view = load_view(Path(tmp) / "views" / "suzanne", 0)
    timings["render (Cycles)"] = time.perf_counter() - t0

    t = time.perf_counter()
    rot = torch.tensor(view["camera"]["rotation_cam_to_obj"], dtype=torch.float32)[None]
    depth = torch.from_numpy(view["depth"])[None]
    partial = depth_to_sph(depth, cam, g.sph_size, g.depth_edge_max_ratio)
    timings["depth → partial spherical map"] = time.perf_counter() - t
    t = time.perf_counter()
    view_verts = frame.object_to_view(torch.tensor(verts, dtype=torch.float32)[None], rot)[0]
    full = mesh_to_sph(view_verts, torch.from_numpy(faces), g.sph_size)[None]
    timings["true full spherical map (stands in for inpainting)"] = time.perf_counter() - t
    t = time.perf_counter()
    vox_sph = sph_to_voxels(full, g.voxel_size, g.sph_nohit_min, g.sph_supersample)
    pts = frame.depth_to_points(depth, cam).reshape(1, -1, 3)
    vox_depth = points_to_voxels(pts, g.voxel_size, frame.depth_valid_mask(depth).reshape(1, -1))
    timings["back-projections to voxels"] = time.perf_counter() - t
    t = time.perf_counter()
    combined = torch.maximum(vox_sph, vox_depth)[0, 0]
    mesh_v, mesh_f = voxels_to_mesh(combined, g.default_threshold)
    timings["marching cubes"] = time.perf_counter() - t

    gt = (view_verts.numpy(), faces)
    result = {
        "preset": preset,
        "view": {"azimuth_deg": azimuth, "elevation_deg": elevation},
        "vertices": int(mesh_v.shape[0]),
        "faces": int(mesh_f.shape[0]),
        "chamfer_normalised_1024": mesh_chamfer((mesh_v, mesh_f), gt, g.chamfer_points),
        "chamfer_view_frame_10000": mesh_chamfer((mesh_v, mesh_f), gt, 10_000, normalize=False),
        "timings_s": timings,
    }
    trimesh.Trimesh(mesh_v, mesh_f, process=False).export(out / "suzanne_sph_oracle.obj")
    trimesh.Trimesh(gt[0], gt[1], process=False).export(out / "suzanne_truth_view_frame.obj")
    (out / "result.json").write_text(json.dumps(result, indent=2))
    _preview(out / "preview.png", view, partial[0], full[0], (mesh_v, mesh_f), gt, result)
    return result


def _preview(path: Path, view, partial, full, pred, gt, result) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(15, 7.5))
    panels = [
        ("rendered photo (Cycles)", view["rgb"], None),
        ("Z-pass depth (planar)", np.where(view["depth"] > 0, view["depth"], np.nan), "viridis"),
        ("partial spherical map\n(from depth)", partial.numpy(), "magma"),
        ("full spherical map\n(truth, stands in for inpainting)", full.numpy(), "magma"),
    ]
    for i, (title, img, cmap) in enumerate(panels):
        ax = fig.add_subplot(2, 4, i + 1)
        ax.imshow(img, cmap=cmap)
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    for j, (title, (v, f), azim) in enumerate(
        [
            ("reconstruction, photo viewpoint", pred, -90),
            ("reconstruction, from the side", pred, 0),
            ("truth, photo viewpoint", gt, -90),
            ("truth, from the side", gt, 0),
        ]
    ):
        ax = fig.add_subplot(2, 4, 5 + j, projection="3d")
        # view frame: x right, y up, z toward the camera; show it as matplotlib's x, z-up, -y
        ax.plot_trisurf(v[:, 0], -v[:, 2], v[:, 1], triangles=f, color="lightsteelblue", linewidth=0, antialiased=False, shade=True)
        ax.view_init(elev=0, azim=azim)
        ax.set_box_aspect((1, 1, 1))
        for setter in (ax.set_xlim, ax.set_ylim, ax.set_zlim):
            setter(-0.3, 0.3)
        ax.set_axis_off()
        ax.set_title(title, fontsize=9)
    fig.suptitle(
        f"GenRe geometry demo ({result['preset']} preset): Chamfer {result['chamfer_normalised_1024']:.3f} "
        "(1,024 pts, normalised; sum of both directions)",
        fontsize=11,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m training.demo_geometry", description=__doc__.split("\n\n")[0])
    add_out(parser, type=Path, default=Path("out/demo"))
    parser.add_argument("--preset", choices=sorted(PRESETS), default="default")
    parser.add_argument("--azimuth", type=float, default=30.0)
    parser.add_argument("--elevation", type=float, default=20.0)
    args = parser.parse_args(argv)
    result = run(args.out, args.preset, args.azimuth, args.elevation)
    print(json.dumps(result, indent=2))
    print(f"wrote {args.out / 'suzanne_sph_oracle.obj'} and {args.out / 'preview.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
