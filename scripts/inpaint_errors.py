"""The inpainting net's stage table: its full spherical map against the truth, beside trivial fills and retrieval.

Views are made from meshes with no rendering (:class:`training.learn.burst.ViewMaker`): the product test
split's shapes (decimated as a pack is, never trained on), each seen from ``--views`` seeded poses with
elevation uniform in −10°…88° and azimuth uniform; the depth carries the recipe's smooth error (σ 0.01, the
depth net's kind of error), so the partial map is what the inpainting net sees in use.  For each view and
method the table gives, on the **hidden side** (the pixels the partial map does not see):

* ``hit IoU``: the predicted hits against the true hits;
* ``RMSE``: the map value's error (s = 1 − r, no hit = 1) over the pixels where either says "hit";
* ``RMSE hits``: the same over the true hits only (a miss there costs its radius);
* ``radius bias``: the mean of the predicted radius less the true one over those true hits (a miss counts radius
  0): above 0 the map is inflated, below 0 it cuts into the object;

and on the **visible side** (the seen pixels) the map's RMSE against the true map.

Methods:

* ``net``: the weights' inpainting net, as inference runs it;
* ``net+keep``: the same with the seen pixels replaced by the partial map's own values (visible side kept);
* ``sphere``: every hidden pixel a hit at the seen pixels' mean radius (a sphere);
* ``mirror``: the seen points reflected through the object's symmetry plane, the plane (object x = 0 or
  y = 0) chosen from the mesh itself and placed by the true pose (an oracle's advantage); hidden pixels the
  reflection misses take the sphere's value;
* ``retrieval``: the full map of the training view (``--bank`` views of the training pack, same sampler)
  whose partial map is nearest (L2 over the map at 32 × 32), after Tatarchenko et al., CVPR 2019.

Usage::

    python scripts/inpaint_errors.py --manifest $GENRE_HOME/corpus/manifest.json --pack $GENRE_HOME/pack \\
        --weights default --views 4 --bank 8000 --out results/stage_errors/inpaint.md
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from genre_backend.arguments import add_out, add_seed, add_weights  # noqa: E402
from genre_backend.frame import camera_rotation  # noqa: E402
from genre_backend.geometry.spherical import NO_HIT, directions_to_pixels, sph_to_points  # noqa: E402
from genre_backend.weights_file import resolve_weights  # noqa: E402
from genre_backend.nets.model import load_model  # noqa: E402
from training.data.pack import Pack, _decimate, quantise, read_pack  # noqa: E402
from training.learn.burst import ViewMaker  # noqa: E402
from training.learn.recipe import get_burst_recipe  # noqa: E402

METHODS = ("net", "net+keep", "sphere", "mirror", "retrieval")


def test_pack(manifest_path: Path, split: str = "product-test", max_faces: int = 2000) -> Pack:
    """The test split's shapes as an in-memory pack (decimated and quantised as a training pack is)."""
    import trimesh

    manifest = json.loads(manifest_path.read_text())
    entries = [e for e in manifest["shapes"] if e.get("split") == split or split in (e.get("groups") or ())]
    verts, faces, vo, fo, shapes = [], [], [0], [0], []
    for e in entries:
        rel = e.get("mesh")
        path = (manifest_path.parent / rel) if rel else manifest_path.parent / "shapes" / f"{e['id']}.glb"
        mesh = trimesh.load(path, force="mesh", process=False)
        v, f = _decimate(np.asarray(mesh.vertices), np.asarray(mesh.faces), max_faces)
        verts.append(quantise(v))
        faces.append(f.astype(np.uint16))
        vo.append(vo[-1] + len(v))
        fo.append(fo[-1] + len(f))
        shapes.append({"id": e["id"], "class": e.get("class")})
    return Pack(manifest_path.parent, {"shapes": shapes, "split": split}, np.concatenate(verts), np.concatenate(faces),
                np.asarray(vo, np.int64), np.asarray(fo, np.int64))


def symmetry_normal(pack: Pack, i: int) -> np.ndarray:
    """The object-frame normal (x or y axis) of the plane through the origin the shape is most symmetric about."""
    from scipy.spatial import cKDTree

    v, f = pack.mesh(i)
    tri = v[f]
    rng = np.random.default_rng(i)
    a, b = rng.random((2, len(tri) * 4 if len(tri) < 500 else 4000))
    k = rng.integers(0, len(tri), a.shape[0])
    flip = a + b > 1
    a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
    pts = tri[k, 0] + a[:, None] * (tri[k, 1] - tri[k, 0]) + b[:, None] * (tri[k, 2] - tri[k, 0])
    tree = cKDTree(pts)
    best, normal = np.inf, None
    for axis in (0, 1):
        n = np.eye(3)[axis]
        refl = pts - 2 * (pts @ n)[:, None] * n
        err = tree.query(refl)[0].mean()
        if err < best:
            best, normal = err, n
    return normal


def sphere_fill(partial: torch.Tensor) -> torch.Tensor:
    seen = partial < NO_HIT
    r = (1 - partial)[seen].mean() if seen.any() else torch.tensor(0.3)
    return torch.where(seen, partial, 1 - r)


def mirror_fill(partial: torch.Tensor, normal_view: torch.Tensor) -> torch.Tensor:
    """The partial map with its seen points reflected through the plane of normal ``normal_view`` (view frame)."""
    h, w = partial.shape
    pts, ok = sph_to_points(partial[None])
    pts = pts[0][ok[0]]
    refl = pts - 2 * (pts @ normal_view)[:, None] * normal_view
    r = refl.norm(dim=1)
    pix = directions_to_pixels(refl / r.clamp(min=1e-9)[:, None], h, w)
    i = pix[:, 0].round().long().clamp(0, h - 1)
    j = torch.remainder(pix[:, 1].round().long(), w)
    out_r = torch.zeros(h * w)
    out_r.scatter_reduce_(0, i * w + j, r, reduce="amax")
    got = (out_r > 0).view(h, w)
    base = sphere_fill(partial)
    seen = partial < NO_HIT
    return torch.where(seen, partial, torch.where(got, 1 - out_r.view(h, w), base))


def scores(pred: torch.Tensor, true: torch.Tensor, seen: torch.Tensor, nohit_min: float) -> dict[str, float]:
    hid = ~seen
    ph, th = pred < nohit_min, true < nohit_min
    inter, union = (ph & th & hid).sum().item(), ((ph | th) & hid).sum().item()
    either = (ph | th) & hid
    err = (pred - true) ** 2
    radius_bias = (true - pred)[th & hid]  # radius predicted − true radius (s = 1 − r)
    return {"hit_iou": inter / union if union else 1.0,
            "radius_bias": float(radius_bias.mean()) if radius_bias.numel() else 0.0,
            "rmse": float(err[either].mean().sqrt()) if either.any() else 0.0,
            "rmse_hits": float(err[th & hid].mean().sqrt()) if (th & hid).any() else 0.0,
            "visible": float(err[seen].mean().sqrt()) if seen.any() else 0.0}


def small(m: torch.Tensor) -> torch.Tensor:
    return torch.nn.functional.avg_pool2d(m[:, None], 2)[:, 0].flatten(1)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--manifest", required=True)
    ap.add_argument("--pack", required=True, help="the training pack (for the retrieval bank)")
    add_weights(ap, action="append", default=None, help="weights (repeat to compare several); default: default")
    ap.add_argument("--views", type=int, default=4, help="views per test shape")
    ap.add_argument("--bank", type=int, default=8000, help="training views in the retrieval bank")
    ap.add_argument("--elevation", type=float, nargs=2, default=None, help="elevation range (default the recipe's)")
    add_out(ap, default=None, help="write the table (markdown) here")
    add_seed(ap, default=1234)
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    t0 = time.time()
    recipe = get_burst_recipe("session")
    el_lo, el_hi = args.elevation or (recipe.elevation_min_deg, recipe.elevation_max_deg)
    weights = args.weights or ["default"]
    models = {w: load_model(resolve_weights(w)).eval() for w in weights}
    first = next(iter(models.values()))
    g = first.config.geometry
    tpack = test_pack(Path(args.manifest))
    tmaker = ViewMaker(tpack, first.config, torch.device("cpu"), voxels=False)
    normals = [torch.from_numpy(symmetry_normal(tpack, i)).float() for i in range(len(tpack))]
    # the retrieval bank: training views from the same sampler
    bmaker = ViewMaker(read_pack(args.pack), first.config, torch.device("cpu"), voxels=False)
    gen = torch.Generator().manual_seed(args.seed + 1)
    bank_keys, bank_full = [], []
    for start in range(0, args.bank, 64):
        b = min(64, args.bank - start)
        shape, az, el = bmaker.draw(gen, b, recipe)
        el = el_lo + (el - recipe.elevation_min_deg) / (recipe.elevation_max_deg - recipe.elevation_min_deg) * (el_hi - el_lo)
        s = bmaker.make(shape, az, el, recipe.depth_noise, gen)
        bank_keys.append(small(first.partial_sph(s["depth"])))
        bank_full.append(s["full_sph"].half())
    bank_keys, bank_full = torch.cat(bank_keys), torch.cat(bank_full)
    print(f"bank: {len(bank_keys)} training views ({time.time() - t0:.0f} s)", flush=True)
    gen = torch.Generator().manual_seed(args.seed)
    rows = []
    for i in range(len(tpack)):
        shape = torch.full((args.views,), i, dtype=torch.long)
        az = torch.rand(args.views, generator=gen) * 360
        el = el_lo + torch.rand(args.views, generator=gen) * (el_hi - el_lo)
        s = tmaker.make(shape, az, el, recipe.depth_noise, gen)
        rot = camera_rotation(az, el)
        with torch.no_grad():
            partial = first.partial_sph(s["depth"])
            nets = {w: m.inpaint_net(partial) for w, m in models.items()}
            keys = small(partial)
            nearest = torch.cdist(keys, bank_keys).argmin(dim=1)
        for k in range(args.views):
            p, t = partial[k], s["full_sph"][k]
            seen = p < NO_HIT
            preds = {}
            for w, full in nets.items():
                tag = "" if len(models) == 1 else f" [{w}]"
                preds["net" + tag] = full[k]
                preds["net+keep" + tag] = torch.where(seen, p, full[k])
            preds["sphere"] = sphere_fill(p)
            preds["mirror"] = mirror_fill(p, normals[i] @ rot[k])
            preds["retrieval"] = torch.where(seen, p, bank_full[nearest[k]].float())
            for name, pred in preds.items():
                rows.append({"shape": tpack.ids[i], "class": tpack.meta["shapes"][i]["class"], "view": k,
                             "elevation": float(el[k]), "method": name, **scores(pred, t, seen, g.sph_nohit_min)})
        if (i + 1) % 20 == 0:
            print(f"{i + 1}/{len(tpack)} shapes ({time.time() - t0:.0f} s)", flush=True)
    methods = list(dict.fromkeys(r["method"] for r in rows))
    base = {(r["shape"], r["view"]): r["rmse"] for r in rows if r["method"] == "sphere"}
    lines = [f"Inpainting stage on the product test split: {len(tpack)} shapes × {args.views} views, elevation "
             f"{el_lo:g}°…{el_hi:g}°, depth error σ {recipe.depth_noise}; retrieval bank {len(bank_keys)} training views. "
             f"Hidden side = pixels the partial map does not see. Weights: {', '.join(weights)}.", "",
             "| method | hidden hit IoU | hidden RMSE | hidden RMSE (true hits) | hidden radius bias (true hits) "
             "| visible RMSE | beats sphere (views) |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for m in methods:
        rs = [r for r in rows if r["method"] == m]
        wins = sum(r["rmse"] < base[(r["shape"], r["view"])] for r in rs)
        lines.append(f"| {m} | {np.mean([r['hit_iou'] for r in rs]):.3f} | {np.mean([r['rmse'] for r in rs]):.4f} | "
                     f"{np.mean([r['rmse_hits'] for r in rs]):.4f} | {np.mean([r['radius_bias'] for r in rs]):+.4f} | "
                     f"{np.mean([r['visible'] for r in rs]):.4f} | "
                     f"{wins} / {len(rs)} |")
    lines += ["", f"Made by `python scripts/inpaint_errors.py {' '.join(argv if argv is not None else sys.argv[1:])}` "
              f"in {time.time() - t0:.0f} s."]
    text = "\n".join(lines)
    print(text)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
