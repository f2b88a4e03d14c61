"""``genre bench``: speed figures, printed (benchmarks are scripts, not timed tests).

``genre bench geometry`` times each geometry op at the ``default`` and
``paper`` resolutions on an analytic sphere (radius 0.45, seen from the
default camera), reports the median of several runs and the ratio to the
op's plain reference implementation.  References that would take minutes at
full size are timed on a slice of the work and scaled up; the table says so.

``genre bench inference`` times the reconstruction pipeline
(:class:`genre_backend.inference.reconstruct.Reconstructor`) stage by stage, end to end
from an image file (a 640×480 RGBA photo whose alpha holds the object), for
each preset with randomly initialised weights built in memory (speed does not
depend on training).  Each preset runs in a fresh subprocess so that its peak
memory (``getrusage`` max RSS) is its own; per-stage peaks come from sampling
the process's resident set every 2 ms.  On CUDA, per-stage peaks are
``torch.cuda.max_memory_allocated``.

``genre bench reconstruct`` times what a user runs: ``genre reconstruct`` of a
photo (``examples/sofa.png``) with the shipped weights (``default``) and their
own options (the salient net's mask, mirror averaging, cleanup …).  Warm: one process,
the weights loaded, each stage timed from the ``progress`` call that starts it.
Cold: fresh ``genre reconstruct`` processes, wall clock, and instrumented ones
that split that time into the interpreter's start, the imports, the weights'
loading, each stage and the exit (:mod:`.bench_probe`).  ``--against
LABEL=DIR`` times another checkout (an older commit) in the same run, the
checkouts taken in turn, and prints the two side by side with the meshes'
sha256.
"""

from __future__ import annotations

import argparse
import copy
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

from genre_backend.geometry.analytic import sphere_depth
from genre_backend.config import PRESETS, get_preset
from genre_backend.validation import check_threshold
from genre_backend.arguments import add_device, add_threads, add_weights

__all__ = ["main", "geometry_benchmark", "inference_benchmark"]


def _median_time(fn: Callable[[], object], repeats: int) -> float:
    fn()  # warm-up (caches, allocator)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def geometry_benchmark(preset: str, repeats: int = 5) -> list[dict]:
    """Time the geometry ops of one preset; returns one row per op."""
    cfg = get_preset(preset)
    g, cam = cfg.geometry, cfg.camera
    r = 0.45
    depth = sphere_depth(cam, g.image_size, r, dtype=torch.float32)
    rows = []

    def add(op, fast, ref=None, ref_scale=1.0, note=""):
        t = _median_time(fast, repeats)
        row = {"preset": preset, "op": op, "ms": 1e3 * t, "ref_ms": None, "note": note}
        if ref is not None:
            row["ref_ms"] = 1e3 * _median_time(ref, 1) * ref_scale
        rows.append(row)

    _time_map_ops(add, g, cam, depth, r)
    _time_visible_face_ops(add, g, cam, depth, r)
    _time_ground_truth_ops(add, g, r)
    return rows


def _time_map_ops(add: Callable, g, cam, depth: torch.Tensor, r: float) -> None:
    """Depth (1, N, N) → spherical map → voxels → mesh, and the voxels' first hits: one ``add`` per op."""
    from genre_backend.geometry.mesh_voxels import voxels_to_mesh
    from genre_backend.geometry.spherical import depth_to_sph, depth_to_triangles, raycast_triangles_reference, sph_to_points, sph_to_voxels
    from genre_backend.geometry.voxels import points_to_voxels_reference, ray_first_hit, ray_first_hit_reference

    # depth → partial spherical map; the reference ray-casts a few map rows against all triangles
    tris, _ = depth_to_triangles(depth, cam, g.depth_edge_max_ratio)
    ref_rows = 2
    tri_np = tris.double().numpy()
    add(
        f"depth {g.image_size}² → partial sph {g.sph_size}²",
        lambda: depth_to_sph(depth, cam, g.sph_size, g.depth_edge_max_ratio),
        lambda: raycast_triangles_reference(tri_np, ref_rows, g.sph_size),
        g.sph_size / ref_rows,
        f"reference timed on {ref_rows} of {g.sph_size} rows, scaled",
    )
    # spherical map → voxels
    full = torch.full((1, g.sph_size, g.sph_size), 1.0 - r)
    pts, mask = sph_to_points(full, g.sph_nohit_min, g.sph_supersample)
    sub = max(1, pts.shape[1] // 4096)
    add(
        f"sph {g.sph_size}² → voxels {g.voxel_size}³",
        lambda: sph_to_voxels(full, g.voxel_size, g.sph_nohit_min, g.sph_supersample),
        lambda: points_to_voxels_reference(pts[:, ::sub], g.voxel_size, mask[:, ::sub]),
        sub,
        f"reference timed on 1/{sub} of the points, scaled" if sub > 1 else "",
    )
    # marching cubes of a voxelised sphere
    vox = sph_to_voxels(full, g.voxel_size, g.sph_nohit_min, g.sph_supersample)[0, 0]
    add(f"marching cubes {g.voxel_size}³ → mesh", lambda: voxels_to_mesh(vox, g.default_threshold), note="scikit-image (no reference)")
    # the holes in the visible face (geometry.visible_fusion): which pixels see the grid
    rows_ref = 2
    add(f"first hits {g.voxel_size}³ → {g.image_size}²", lambda: ray_first_hit(vox, g.default_threshold, cam, g.image_size),
        lambda: ray_first_hit_reference(vox, g.default_threshold, cam, g.image_size, rows=rows_ref),
        g.image_size / rows_ref, f"reference timed on {rows_ref} of {g.image_size} rows, scaled")


def _time_visible_face_ops(add: Callable, g, cam, depth: torch.Tensor, r: float) -> None:
    """The visible face's holes and pits filled in a sphere's (V, V, V) distance grid: one ``add`` per op."""
    import dataclasses

    from genre_backend.geometry.visible_front import depth_to_distance, fuse_visible_surface, seal_back, seal_pits

    # the holes in the visible face (geometry.visible_fusion): the depth map's own distance grid; the whole
    # fusion into a grid with a tunnel through the sphere's front
    dg = dataclasses.replace(g, target="distance")
    add(f"depth {g.image_size}² → distance {g.voxel_size}³", lambda: depth_to_distance(depth[0], cam, dg),
        note="visible_fusion: libigl's AABB tree (its distances: mesh → distance's reference)")
    c = (torch.arange(g.voxel_size) + 0.5) / g.voxel_size - 0.5
    radius = torch.sqrt(c[:, None, None] ** 2 + c[None, :, None] ** 2 + c[None, None, :] ** 2)
    tube = (1.0 - (radius - r).abs() * g.voxel_size / dg.distance_band).clamp(0.0, 1.0)  # the sphere's distance target
    tunnel = (c.abs() < 0.05)[:, None, None] & (c.abs() < 0.05)[None, :, None]
    holed = torch.where(tunnel, torch.zeros_like(tube), tube)
    add(f"fuse the visible surface {g.voxel_size}³ (a hole)", lambda: fuse_visible_surface(holed, depth[0], cam, dg, g.default_threshold),
        note="ray coverage + the depth's distance grid of the hole's pixels")
    add(f"fuse the visible surface {g.voxel_size}³ (no hole)", lambda: fuse_visible_surface(tube, depth[0], cam, dg, g.default_threshold),
        note="ray coverage only")
    # the pits in the visible face (Seal Pits): the front cap missing over a narrow disc
    well = (c[:, None, None] ** 2 + c[None, :, None] ** 2 < 0.025 ** 2) & (c[None, None, :] > 0)
    pitted, obj = torch.where(well, torch.zeros_like(tube), tube), depth[0] > 0
    add(f"seal pits {g.voxel_size}³ (a pit)", lambda: seal_pits(pitted, obj, cam, dg, g.default_threshold, 2),
        note="first hits + basin filling (scikit-image) + the lid's distance grid")
    add(f"seal pits {g.voxel_size}³ (no pit)", lambda: seal_pits(tube, obj, cam, dg, g.default_threshold, 2),
        note="first hits + basin filling")
    # the dents in the back (Seal Back): the back cap missing over a wide disc
    dent = (c[:, None, None] ** 2 + c[None, :, None] ** 2 < (r / 2) ** 2) & (c[None, None, :] < 0)
    dented = torch.where(dent, torch.zeros_like(tube), tube)
    add(f"seal back {g.voxel_size}³ (a dent)", lambda: seal_back(dented, obj, cam, dg, g.default_threshold),
        note="last hits + basin filling (scikit-image) + the lid's distance grid")
    add(f"seal back {g.voxel_size}³ (no dent)", lambda: seal_back(tube, obj, cam, dg, g.default_threshold),
        note="last hits + basin filling")


def _time_ground_truth_ops(add: Callable, g, r: float) -> None:
    """Ground truth from a sphere mesh (offline data preparation) and the Chamfer distance: one ``add`` per op."""
    import trimesh

    from genre_backend.geometry.mesh_voxels import mesh_to_distance, mesh_to_shell
    from genre_backend.geometry.triangle_distance import point_mesh_distance_reference
    from genre_backend.geometry.metrics import chamfer_distance, chamfer_distance_reference, sample_surface
    from genre_backend.geometry.spherical import mesh_to_sph

    # ground truth from a mesh (offline data preparation)
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=r)
    v, f = torch.tensor(sphere.vertices, dtype=torch.float32), torch.tensor(sphere.faces)
    add(f"mesh (20k faces) → full sph {g.sph_size}²", lambda: mesh_to_sph(v, f, g.sph_size), note="ground truth, offline")
    add(f"mesh (20k faces) → shell {g.voxel_size}³", lambda: mesh_to_shell(v, f, g.voxel_size, g.shell_dilation), note="ground truth, offline")
    band = mesh_to_distance(v, f, g.voxel_size, g.distance_band) > 0
    probe = ((torch.nonzero(band)[:2].double() + 0.5) / g.voxel_size - 0.5).numpy()
    add(f"mesh (20k faces) → distance {g.voxel_size}³", lambda: mesh_to_distance(v, f, g.voxel_size, g.distance_band),
        lambda: point_mesh_distance_reference(probe, sphere.vertices, sphere.faces), int(band.sum()) / len(probe),
        f"ground truth, offline; reference timed on {len(probe)} of the {int(band.sum())} band voxels, scaled")
    # Chamfer distance
    for n in (g.chamfer_points, 10_000):
        a = sample_surface(v, f, n, seed=0)
        b = sample_surface(v, f, n, seed=1)
        sub = max(1, n // 1000)
        ref_note = f"reference: loop over points, timed on 1/{sub}² of the pairs, scaled" if sub > 1 else "reference: loop over points"
        # (add times its callables at once, so binding the loop's values as defaults changes nothing)
        add(f"chamfer {n} pts (k-d tree)", lambda a=a, b=b: chamfer_distance(a, b),
            lambda a=a, b=b, sub=sub: chamfer_distance_reference(a[::sub].numpy(), b[::sub].numpy()), sub * sub, ref_note)
        add(f"chamfer {n} pts (brute, differentiable)", lambda a=a, b=b: chamfer_distance(a, b, method="brute"),
            lambda a=a, b=b, sub=sub: chamfer_distance_reference(a[::sub].numpy(), b[::sub].numpy()), sub * sub, ref_note)


def _print_rows(rows: list[dict]) -> None:
    print(f"{'preset':<8} {'op':<42} {'median ms':>10} {'ref ms':>10} {'ref/fast':>9}  note")
    for row in rows:
        ref = f"{row['ref_ms']:.1f}" if row["ref_ms"] is not None else "—"
        ratio = f"{row['ref_ms'] / row['ms']:.1f}×" if row["ref_ms"] is not None else "—"
        print(f"{row['preset']:<8} {row['op']:<42} {row['ms']:>10.1f} {ref:>10} {ratio:>9}  {row['note']}")


def _rss_bytes() -> int:
    """Current resident set size of this process in bytes (Linux /proc; 0 elsewhere)."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


def _max_rss_bytes() -> int:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # kB on Linux


def _bench_image(folder: Path) -> Path:
    """A 640×480 RGBA photo: a shaded ellipse (the object, opaque) on transparent noise."""
    import numpy as np
    from PIL import Image

    rng = np.random.default_rng(0)
    h, w = 480, 640
    yy, xx = np.mgrid[0:h, 0:w]
    inside = ((xx - 330) / 170.0) ** 2 + ((yy - 250) / 120.0) ** 2 <= 1.0
    shade = np.clip(1.0 - (((xx - 280) / 260.0) ** 2 + ((yy - 200) / 200.0) ** 2), 0.1, 1.0)
    rgb = (rng.random((h, w, 3)) * 60 + 100).astype(np.uint8)
    rgb[inside] = (np.array([200, 120, 60])[None] * shade[inside][:, None]).astype(np.uint8)
    alpha = np.where(inside, 255, 0).astype(np.uint8)
    path = folder / "bench_photo.png"
    Image.fromarray(np.dstack([rgb, alpha]), "RGBA").save(path)
    return path


def _inference_worker(preset: str, device: str, repeats: int, threshold: float | None, mirror: bool = False) -> dict:
    """Run in a fresh process: time the pipeline of one preset; returns a JSON-able summary."""
    import tempfile
    import threading

    from genre_backend.nets.model import GenRe
    from genre_backend.inference.reconstruct import STAGES, Hooks, Reconstructor

    base_rss = _rss_bytes()
    torch.manual_seed(0)
    rec = Reconstructor.from_model(GenRe(get_preset(preset)), device)
    model_rss = _rss_bytes()
    params = sum(p.numel() for p in rec.model.parameters())
    cuda = rec.device.type == "cuda"
    current = {"stage": None}
    peaks: dict[str, int] = {}
    stop = threading.Event()

    def sampler():
        while not stop.is_set():
            st = current["stage"]
            if st is not None:
                peaks[st] = max(peaks.get(st, 0), _rss_bytes())
            time.sleep(0.002)

    def progress(stage: str, fraction: float) -> None:
        if cuda:
            prev = current["stage"]
            if prev is not None:
                peaks[prev] = max(peaks.get(prev, 0), torch.cuda.max_memory_allocated(rec.device))
            torch.cuda.reset_peak_memory_stats(rec.device)
        current["stage"] = stage

    thread = None if cuda else threading.Thread(target=sampler, daemon=True)
    if thread:
        thread.start()
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        image = _bench_image(Path(tmp))
        out_path = Path(tmp) / "mesh.obj"
        for i in range(repeats + 1):  # the first run warms up caches and the allocator
            t0 = time.perf_counter()
            result = rec.run(image, hooks=Hooks(progress), threshold=threshold, test_time_mirror=mirror)
            progress("write", 1.0)
            result.save_mesh(out_path)
            if cuda:
                progress("done", 1.0)
            current["stage"] = None
            total = time.perf_counter() - t0
            if i:
                runs.append({**result.timings, "total": total})
        # the extra depth-net pass that photos without mask or alpha need (in "preprocess")
        sil_times = _time_silhouette_pass(rec, result.intermediates["rgb"], repeats, cuda)
    stop.set()
    if thread:
        thread.join()
    med = {k: statistics.median(r[k] for r in runs) for k in [*STAGES, "total"] if all(k in r for r in runs)}
    return {
        "preset": preset,
        "test_time_mirror": mirror,
        "device": str(rec.device),
        "threads": torch.get_num_threads(),
        "params_m": params / 1e6,
        "repeats": repeats,
        "median_s": med,
        "silhouette_pass_s": statistics.median(sil_times),
        "peak_by_stage_mb": {k: v / 2**20 for k, v in peaks.items()},
        "peak_kind": "cuda max_memory_allocated" if cuda else "sampled RSS",
        "rss_start_mb": base_rss / 2**20,
        "rss_model_mb": model_rss / 2**20,
        "max_rss_mb": _max_rss_bytes() / 2**20,
        "vertices": int(len(result.vertices)),
        "faces": int(len(result.faces)),
        "mask_source": result.mask_source,
    }


def _time_silhouette_pass(rec, rgb: torch.Tensor, repeats: int, cuda: bool) -> list[float]:
    """Seconds of each of ``repeats`` runs of the depth net's silhouette pass on the (3, S, S) ``rgb``."""
    sil_times = []
    with torch.inference_mode():
        for _ in range(repeats):
            rec._first_pass = None  # no reuse of the previous pass: time the net
            t0 = time.perf_counter()
            rec._silhouette(rgb)
            if cuda:
                torch.cuda.synchronize(rec.device)
            sil_times.append(time.perf_counter() - t0)
    return sil_times


def inference_benchmark(preset: str, device: str = "cpu", repeats: int = 5, threshold: float | None = None, threads: int | None = None,
                        mirror: bool = False) -> dict:
    """Time the pipeline of ``preset`` in a fresh subprocess (so its peak memory is its own).

    ``threshold`` None: the preset's ``geometry.default_threshold``.  ``mirror``: with test-time
    mirroring (``geometry.test_time_mirror``: the nets run twice).
    """
    import json
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "genre_backend.cli", "bench", "_inference-worker", "--preset", preset, "--device", device,
           "--repeats", str(repeats)]
    if threshold is not None:
        cmd += ["--threshold", str(threshold)]
    if threads:
        cmd += ["--threads", str(threads)]
    if mirror:
        cmd.append("--test-time-mirror")
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        tail = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise RuntimeError(f"inference benchmark of {preset} on {device} failed: {tail}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


_TARGETS_S = {"default": 1.0, "paper": 8.0}  # CPU targets of the issue (2-core CPU)


def _print_inference(summary: dict) -> None:
    from genre_backend.inference.reconstruct import STAGES

    s = summary
    mirrored = ", averaged with the mirror image" if s.get("test_time_mirror") else ""
    print(f"\n{s['preset']}{mirrored} on {s['device']} ({s['threads']} threads, {s['params_m']:.1f} M parameters, median of {s['repeats']} runs; "
          f"mesh {s['vertices']} vertices / {s['faces']} faces, mask from {s['mask_source']})")
    print(f"  {'stage':<12} {'median ms':>10} {'peak MB':>9}")
    for st in STAGES:
        if st in s["median_s"]:
            peak = s["peak_by_stage_mb"].get(st)
            print(f"  {st:<12} {1e3 * s['median_s'][st]:>10.1f} {peak if peak is not None else float('nan'):>9.0f}")
    total = s["median_s"]["total"]
    target = _TARGETS_S.get(s["preset"]) if s["device"] == "cpu" else None
    verdict = f"  (target ≤ {target:.1f} s: {'met' if total <= target else 'MISSED'})" if target else ""
    print(f"  {'total':<12} {1e3 * total:>10.1f}{verdict}")
    print(f"  photos without mask or alpha add one depth-net pass: {1e3 * s['silhouette_pass_s']:.1f} ms")
    print(f"  memory ({s['peak_kind']} per stage): RSS at start {s['rss_start_mb']:.0f} MB, with model {s['rss_model_mb']:.0f} MB, "
          f"process peak (getrusage max RSS) {s['max_rss_mb']:.0f} MB")


# ----------------------------------------------------------------------------- what a user runs

_REPO = Path(__file__).resolve().parents[2]
_PROBE = Path(__file__).with_name("bench_probe.py")
_COLD_ROWS = ("interpreter", "python + cli", "import reconstruct", "weights", "load", "preprocess", "depth", "partial_sph",
              "inpaint", "voxels", "refine", "mesh", "write", "cli", "exit")


def _checkout_env(root: Path) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(root), *filter(None, [env.get("PYTHONPATH")])])
    return env


def _probe(root: Path, *args: str) -> dict:
    """Run bench_probe.py (this checkout's) against the code of checkout ``root`` in a fresh process."""
    import json
    import subprocess

    code = f"import runpy, sys; sys.argv = ['bench_probe', *{list(args)!r}]; runpy.run_path({str(_PROBE)!r}, run_name='__main__')"
    launched = time.time()
    proc = subprocess.run([sys.executable, "-c", code], cwd=root, env=_checkout_env(root), capture_output=True, text=True)
    ended = time.time()
    if proc.returncode != 0:
        tail = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise RuntimeError(f"bench probe {args[0]} in {root} failed: {tail}")
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    out["launched"], out["ended"] = launched, ended
    return out


class _WarmProbe:
    """A warm bench_probe process in checkout ``root``: weights loaded and one warm-up run done on start;
    :meth:`run` times one more run."""

    def __init__(self, root: Path, image: Path, weights: str):
        import subprocess

        code = ("import runpy, sys; sys.argv = ['bench_probe', 'warm', "
                f"{str(image)!r}, {weights!r}]; runpy.run_path({str(_PROBE)!r}, run_name='__main__')")
        self.root = root
        self.proc = subprocess.Popen([sys.executable, "-c", code], cwd=root, env=_checkout_env(root), stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.summary = self._read()

    def _read(self) -> dict:
        import json

        for line in self.proc.stdout:
            if line.startswith("{"):
                return json.loads(line)
        tail = (self.proc.stderr.read().strip().splitlines() or ["(no output)"])[-1]
        raise RuntimeError(f"bench probe warm in {self.root} failed: {tail}")

    def run(self) -> dict:
        self.proc.stdin.write("run\n")
        self.proc.stdin.flush()
        return self._read()

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                self.proc.stdin.write("quit\n")
                self.proc.stdin.close()
                self.proc.wait(timeout=60)
            except (OSError, ValueError):
                pass
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()


def _cold_wall(root: Path, image: Path, out: Path, weights: str) -> tuple[float, float, str]:
    """Wall-clock seconds of a plain ``genre reconstruct IMAGE -o OUT --weights W`` process in checkout ``root``,
    its processor seconds (user + system, every thread), and the sha256 of the mesh it wrote."""
    import hashlib
    import subprocess

    import resource

    cmd = [sys.executable, "-m", "genre_backend.cli", "reconstruct", str(image), "-o", str(out), "--weights", weights]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=root, env=_checkout_env(root), capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        tail = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise RuntimeError(f"genre reconstruct in {root} failed: {tail}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, hashlib.sha256(out.read_bytes()).hexdigest()


def _cold_parts(probe: dict) -> dict[str, float]:
    """A cold probe's stamps → seconds per part (``cli``: the command's own work between the timed parts)."""
    stamps = [("interpreter", probe["launched"]), *probe["stamps"], ("exit", probe["stamps"][-1][1])]
    stamps = [(name, at) for name, at in stamps if name != "end"] + [("", probe["ended"])]
    parts: dict[str, float] = {}
    for (name, at), (_, nxt) in zip(stamps[:-1], stamps[1:]):
        parts[name] = parts.get(name, 0.0) + (nxt - at)
    return parts


def reconstruct_benchmark(checkouts: dict[str, Path], image: Path, weights: str = "default", repeats: int = 5,
                          cold_repeats: int = 3) -> dict[str, dict]:
    """Time ``genre reconstruct IMAGE --weights WEIGHTS`` as a user runs it, in each checkout (label → root).

    Warm: one process per checkout, all started together, then ``repeats`` rounds of one run each, median per
    stage.  Cold: ``cold_repeats`` rounds of one plain ``genre reconstruct`` process (wall clock, median) and
    one instrumented one (median per part) per checkout.  Within each round the checkouts take turns (the order
    reversed every other round), so that they share the machine's load alike.
    """
    import statistics
    import tempfile

    cold: dict[str, list] = {k: [] for k in checkouts}
    walls: dict[str, list] = {k: [] for k in checkouts}
    cpus: dict[str, list] = {k: [] for k in checkouts}
    shas: dict[str, set] = {k: set() for k in checkouts}
    warm: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(cold_repeats):
            order = list(checkouts.items()) if r % 2 == 0 else list(checkouts.items())[::-1]
            for label, root in order:
                wall, cpu, sha = _cold_wall(root, image, Path(tmp) / f"{label}-{r}.obj", weights)
                walls[label].append(wall)
                cpus[label].append(cpu)
                shas[label].add(sha)
                probe = _probe(root, "cold", str(image), str(Path(tmp) / f"{label}-{r}-probe.obj"), weights)
                if probe["rc"] != 0:
                    raise RuntimeError(f"genre reconstruct in {root} exited {probe['rc']}")
                cold[label].append(probe)
        probes: dict[str, _WarmProbe] = {}
        try:
            for label, root in checkouts.items():
                probes[label] = _WarmProbe(root, image, weights)
            runs: dict[str, list] = {k: [] for k in checkouts}
            for r in range(repeats):
                for label in (list(checkouts) if r % 2 == 0 else list(checkouts)[::-1]):
                    runs[label].append(probes[label].run())
        finally:
            for probe in probes.values():
                probe.close()
        for label in checkouts:
            names = list(runs[label][0])
            warm[label] = {**probes[label].summary, "repeats": repeats,
                           "median_s": {k: statistics.median(x[k] for x in runs[label]) for k in names},
                           "totals_s": [x["total"] for x in runs[label]]}
    out = {}
    for label, root in checkouts.items():
        parts = [_cold_parts(p) for p in cold[label]]
        names = [n for n in _COLD_ROWS if any(n in p for p in parts)]
        out[label] = {
            "root": str(root),
            "warm": warm[label],
            "cold_wall_s": statistics.median(walls[label]),
            "cold_walls_s": walls[label],
            "cold_cpu_s": statistics.median(cpus[label]),
            "cold_cpus_s": cpus[label],
            "cold_parts_s": {n: statistics.median(p.get(n, 0.0) for p in parts) for n in names},
            "cold_modules": cold[label][-1]["modules"],
            "cold_module_count": cold[label][-1]["module_count"],
            "mesh_sha256": sorted(shas[label]),
        }
    return out


_USER_TARGETS_S = {"warm": 1.0, "cold": 3.0}  # issue 41's goals for the shipped weights on the 2-core CPU


def _print_reconstruct(summaries: dict[str, dict], image: Path, weights: str) -> None:
    labels = list(summaries)
    first = summaries[labels[0]]["warm"]
    mirror = "mirror averaging on" if first["test_time_mirror"] else "no mirror averaging"
    print(f"genre reconstruct {image} --weights {weights}: the weights' own options (threshold {first['threshold']:g}, {mirror}), "
          f"mask from {first['mask_source']}, mesh {first['vertices']} vertices / {first['faces']} faces, "
          f"{first['threads']} torch threads")
    for label in labels:
        print(f"  {label}: {summaries[label]['root']}")
    width = max(12, *(len(x) for x in labels))
    head = "".join(f"{x:>{width + 2}}" for x in labels)

    def row(name: str, values: list[float | None], note: str = "") -> None:
        cells = "".join(f"{'—' if v is None else f'{1e3 * v:.0f}':>{width + 2}}" for v in values)
        print(f"  {name:<22}{cells}{'  ' + note if note else ''}")

    reps = first["repeats"]
    print(f"\nwarm: one process, weights loaded, median of {reps} runs after a warm-up (ms)")
    print(f"  {'stage':<22}{head}")
    stages = [k for k in first["median_s"] if k != "total"]
    for st in stages:
        note = "(with the mirror image through every net)" if st == "refine" and first["test_time_mirror"] else ""
        row(st, [summaries[x]["warm"]["median_s"].get(st) for x in labels], note)
    target = _USER_TARGETS_S["warm"]
    totals = [summaries[x]["warm"]["median_s"]["total"] for x in labels]
    row("total", totals, f"(goal ≤ {1e3 * target:.0f}: " + ", ".join(f"{x} {'met' if t <= target else 'missed'}" for x, t in zip(labels, totals)) + ")")
    row("weights load (once)", [summaries[x]["warm"]["weights_s"] for x in labels])

    n = len(summaries[labels[0]]["cold_walls_s"])
    print(f"\ncold: a fresh `genre reconstruct` process per run, median of {n} (ms)")
    print(f"  {'part':<22}{head}")
    names = [k for k in _COLD_ROWS if any(k in summaries[x]["cold_parts_s"] for x in labels)]
    notes = {"interpreter": "(Python's start-up, to the first line of the command)",
             "python + cli": "(the cli module, argument parsing, finding the commands)",
             "import reconstruct": "(torch and the pipeline's modules, from the first import of torch)",
             "cli": "(the command's own work between these parts)",
             "exit": "(interpreter shut-down)"}
    for name in names:
        row(name, [summaries[x]["cold_parts_s"].get(name) for x in labels], notes.get(name, ""))
    row("sum of the parts", [sum(summaries[x]["cold_parts_s"].values()) for x in labels], "(an instrumented run)")
    target = _USER_TARGETS_S["cold"]
    walls = [summaries[x]["cold_wall_s"] for x in labels]
    row("wall, plain process", walls, f"(goal ≤ {1e3 * target:.0f}: " + ", ".join(f"{x} {'met' if t <= target else 'missed'}" for x, t in zip(labels, walls)) + ")")
    row("processor, plain", [summaries[x]["cold_cpu_s"] for x in labels],
        "(user + system time of that process, all threads: less swayed by other jobs than the wall clock)")
    print("\n  heavy modules a cold run imported:")
    for x in labels:
        print(f"  {x:<{width}}  {', '.join(summaries[x]['cold_modules'])} ({summaries[x]['cold_module_count']} modules in all)")
    shas = {x: summaries[x]["mesh_sha256"] for x in labels}
    same = len({tuple(v) for v in shas.values()}) == 1 and len(shas[labels[0]]) == 1
    print(f"  mesh sha256: {shas[labels[0]][0][:16]}… " + ("(the same from every checkout and run)" if same else f"DIFFERS: {shas}"))


_LAYOUTS = {"contiguous": torch.contiguous_format, "channels-last": torch.channels_last_3d}


def layers_benchmark(preset: str, batch: int = 8, repeats: int = 5) -> list[dict]:
    """Forward and backward of each of the preset refiner's stride-2 transposed convolutions, torch's and by phases.

    Each layer at its own input resolution and widths, random input and weights, in both
    layouts; the phase form (:class:`genre_backend.nets.phase_conv.PhaseConvTranspose3d`)
    keeps torch's backward, so its rows differ from torch's in the forward.  Then the whole
    refiner with its last layer each way (sparse random input grids, training mode).
    """
    from genre_backend.nets.phase_conv import PhaseConvTranspose3d
    from genre_backend.nets.refiner import VoxelRefiner

    cfg = get_preset(preset)
    g, n = cfg.geometry, cfg.network
    refiner = VoxelRefiner(g.voxel_size, n.refiner_nf, n.refiner_fc, n.refiner_full_nf, n.refiner_max_width)
    convs = [m for m in refiner.modules() if isinstance(m, torch.nn.ConvTranspose3d)]
    sizes = {}
    hooks = [m.register_forward_pre_hook(lambda mod, inp: sizes.update({mod: inp[0].shape[2]})) for m in convs]
    with torch.no_grad():
        refiner.eval()(torch.zeros(1, 2, g.voxel_size, g.voxel_size, g.voxel_size))
    for h in hooks:
        h.remove()
    rows = []
    for conv in convs:
        cin, cout, n = conv.in_channels, conv.out_channels, sizes[conv]
        pair = (torch.nn.ConvTranspose3d(cin, cout, 4, 2, 1, bias=conv.bias is not None),
                PhaseConvTranspose3d(cin, cout, bias=conv.bias is not None))
        for layout_name, layout in _LAYOUTS.items():
            x = torch.randn(batch, cin, n, n, n).contiguous(memory_format=layout).requires_grad_()
            rows.append(_time_pair(f"{cin}→{cout} at {n}³→{2 * n}³", layout_name, pair, x, repeats))
    # the whole refiner (training mode), its last layer torch's against by phases, on sparse input grids
    plain = copy.deepcopy(refiner)
    plain.out = torch.nn.ConvTranspose3d(refiner.out.in_channels, 1, 4, 2, 1)
    plain.out.load_state_dict(refiner.out.state_dict())
    x = (torch.rand(batch, 2, g.voxel_size, g.voxel_size, g.voxel_size) > 0.9).float()
    for layout_name, layout in _LAYOUTS.items():
        rows.append(_time_pair("whole refiner", layout_name, (plain.train(), refiner.train()),
                               x.contiguous(memory_format=layout), repeats))
    return rows


def _time_pair(layer: str, layout: str, pair: tuple[torch.nn.Module, torch.nn.Module], x: torch.Tensor, repeats: int) -> dict:
    """Median seconds of the forward, and of forward + backward, of torch's module and the one by phases."""
    row = {"layer": layer, "layout": layout}
    for name, module in zip(("torch", "phases"), pair):
        module.to(memory_format=_LAYOUTS[layout])
        grad = torch.randn_like(module(x).detach())
        row[name + " fwd"] = _median_time(lambda m=module: m(x), repeats)
        row[name + " fwd+bwd"] = _median_time(lambda m=module, g=grad: m(x).backward(g), repeats)
    return row


def _print_layers(rows: list[dict], preset: str, batch: int) -> None:
    print(f"refiner transposed convolutions, preset {preset}, batch {batch}: median ms (torch | by phases)")
    print(f"{'layer':<22} {'layout':<14} {'fwd':>17} {'fwd+bwd':>17} {'fwd+bwd ratio':>14}")
    for r in rows:
        fwd = f"{r['torch fwd'] * 1e3:7.1f} | {r['phases fwd'] * 1e3:7.1f}"
        both = f"{r['torch fwd+bwd'] * 1e3:7.1f} | {r['phases fwd+bwd'] * 1e3:7.1f}"
        print(f"{r['layer']:<22} {r['layout']:<14} {fwd:>17} {both:>17} {r['torch fwd+bwd'] / r['phases fwd+bwd']:13.2f}×")


def _parser(prog: str) -> argparse.ArgumentParser:
    """The command line of ``genre bench``: its ``geometry``, ``layers``, ``inference``, ``reconstruct`` and internal worker commands."""
    parser = argparse.ArgumentParser(prog=prog, description="Print speed figures of the project's operations.")
    sub = parser.add_subparsers(dest="what", required=True)
    geo = sub.add_parser("geometry", help="time the geometry core at the default and paper resolutions")
    geo.add_argument("--preset", choices=[*PRESETS, "all"], default="all")
    geo.add_argument("--repeats", type=int, default=5, help="timed runs per op (median reported)")
    add_threads(geo)
    inf = sub.add_parser("inference", help="time the reconstruction pipeline per stage (random weights of each preset)")
    inf.add_argument("--preset", choices=[*PRESETS, "all"], default="all")
    add_device(inf, choices=["cpu", "cuda", "all"], default="all", help="all: the CPU, and CUDA when present")
    inf.add_argument("--repeats", type=int, default=5, help="timed runs per preset after one warm-up (median reported)")
    inf.add_argument("--threshold", type=float, default=None, help="isosurface level (default: the preset's default_threshold)")
    add_threads(inf)
    inf.add_argument("--test-time-mirror", action="store_true",
                     help="also time each preset with test-time mirroring (the nets run on the mirror image too)")
    inf.add_argument("--json", action="store_true", help="also print the raw figures as JSON")
    lay = sub.add_parser("layers", help="time the refiner's transposed convolutions, torch's and by phases")
    lay.add_argument("--preset", choices=list(PRESETS), default="default")
    lay.add_argument("--batch", type=int, default=8, help="batch size (default 8, one training rank's)")
    lay.add_argument("--repeats", type=int, default=5, help="timed runs per layer (median reported)")
    add_threads(lay)
    user = sub.add_parser("reconstruct", help="time `genre reconstruct` of a photo with the shipped weights and their own options, warm and cold")
    user.add_argument("--image", default=str(_REPO / "examples" / "sofa.png"), help="the photo (default: examples/sofa.png)")
    add_weights(user, default="default", help="shipped weights' name or a file (default: default)")
    user.add_argument("--repeats", type=int, default=5, help="warm runs after one warm-up (median reported)")
    user.add_argument("--cold-repeats", type=int, default=3, help="fresh processes (median reported)")
    user.add_argument("--against", action="append", default=[], metavar="LABEL=DIR",
                      help="also time another checkout of this project (e.g. a `git worktree` of an older commit) in the "
                           "same run, beside this one; repeatable")
    user.add_argument("--json", action="store_true", help="also print the raw figures as JSON")
    worker = sub.add_parser("_inference-worker")  # internal: one preset in a fresh process
    worker.add_argument("--preset", required=True)
    add_device(worker, required=True)
    worker.add_argument("--repeats", type=int, required=True)
    worker.add_argument("--threshold", type=float, default=None)
    add_threads(worker)
    worker.add_argument("--test-time-mirror", action="store_true")
    return parser


def _main_reconstruct(parser: argparse.ArgumentParser, args: argparse.Namespace, prog: str) -> int:
    """``genre bench reconstruct``: time ``genre reconstruct`` in this checkout and the ``--against`` ones."""
    import json

    checkouts = {"this checkout": _REPO}
    for item in args.against:
        label, sep, folder = item.partition("=")
        if not sep or not label or not (Path(folder) / "genre_backend" / "cli.py").is_file():
            parser.error(f"--against {item!r}: expected LABEL=DIR, DIR a checkout of this project")
        checkouts[label] = Path(folder).resolve()
    image = Path(args.image).resolve()
    if not image.is_file():
        parser.error(f"--image {args.image}: no such file")
    try:
        summaries = reconstruct_benchmark(checkouts, image, args.weights, args.repeats, args.cold_repeats)
    except RuntimeError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 1
    _print_reconstruct(summaries, Path(args.image), args.weights)
    if args.json:
        print(json.dumps(summaries, indent=2))
    return 0


def _main_inference(parser: argparse.ArgumentParser, args: argparse.Namespace, prog: str) -> int:
    """``genre bench inference``: time the pipeline of each preset on each device, one subprocess each."""
    import json

    if args.threshold is not None:
        try:
            check_threshold("--threshold", args.threshold)
        except ValueError as exc:
            parser.error(str(exc))
    devices = ["cpu", "cuda"] if args.device == "all" else [args.device]
    if "cuda" in devices and not torch.cuda.is_available():
        if args.device == "cuda":
            print(f"{prog}: error: no CUDA device is available", file=sys.stderr)
            return 1
        devices.remove("cuda")
    print(f"torch {torch.__version__}, {args.threads or torch.get_num_threads()} threads, devices: {', '.join(devices)}")
    presets = list(PRESETS) if args.preset == "all" else [args.preset]
    summaries = []
    for device in devices:
        for preset in presets:
            for mirror in ((False, True) if args.test_time_mirror else (False,)):
                try:
                    summary = inference_benchmark(preset, device, args.repeats, args.threshold, args.threads, mirror)
                except RuntimeError as exc:
                    print(f"{prog}: error: {exc}", file=sys.stderr)
                    return 1
                summaries.append(summary)
                _print_inference(summary)
    if args.json:
        print(json.dumps(summaries, indent=2))
    return 0


def _main_geometry(args: argparse.Namespace) -> int:
    """``genre bench geometry``: time the geometry ops of each preset."""
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, device cpu")
    presets = list(PRESETS) if args.preset == "all" else [args.preset]
    rows = []
    for preset in presets:
        rows += geometry_benchmark(preset, args.repeats)
    _print_rows(rows)
    return 0


def main(argv: list[str], prog: str = "genre bench") -> int:
    """``genre bench``: parse ``argv`` and run the command it names; the exit status."""
    parser = _parser(prog)
    args = parser.parse_args(argv)
    if getattr(args, "threads", None):
        torch.set_num_threads(args.threads)
    if args.repeats < 1 or getattr(args, "cold_repeats", 1) < 1:
        parser.error("--repeats and --cold-repeats must be at least 1")
    if args.what == "reconstruct":
        return _main_reconstruct(parser, args, prog)
    if args.what == "_inference-worker":
        import json

        print(json.dumps(_inference_worker(args.preset, args.device, args.repeats, args.threshold, args.test_time_mirror)))
        return 0
    if args.what == "inference":
        return _main_inference(parser, args, prog)
    if args.what == "layers":
        if args.batch < 1:
            parser.error("--batch must be at least 1")
        print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, device cpu")
        _print_layers(layers_benchmark(args.preset, args.batch, args.repeats), args.preset, args.batch)
        return 0
    return _main_geometry(args)
