"""Headless Blender renderer of the training views (``genre data render``).

One bpy process (Cycles on the CPU) renders many shapes and views without
restarting Blender.  For every view of a shape it writes, into
``OUT/<shape id>/``:

* ``view_KKK.png``  -- RGB, 8-bit, (H, W, 3): the object rendered over a
  transparent film, then composited over a random background (solid colour,
  gradient or smooth noise), so the true mask survives;
* ``view_KKK.npz``  -- ``depth`` float32 (H, W): planar Z-pass depth encoded
  with :func:`genre_backend.frame.encode_raw_depth` (background = 0), and
  ``mask`` float32 (H, W): the film alpha (object coverage) in [0, 1];
* ``view_KKK.json`` -- camera parameters (azimuth, elevation, distance, focal,
  the camera-to-object rotation (3, 3) of :func:`frame.camera_rotation`, the
  camera centre), the lighting and background used, and the shape's metadata.
  The JSON is written last: a view is complete iff its JSON exists.

Every file is written to a temporary name in the same folder and renamed, so
a process killed at any moment leaves no half-written file under a final
name; re-running skips complete views.

Frame and camera come from :mod:`genre_backend.frame` and
:class:`genre_backend.config.CameraConfig` only: the camera sits at
``frame.camera_location(az, el, d)`` with rotation ``frame.camera_rotation``
(its columns are the Blender camera's local x, y, z axes), looks at the origin
and has the config's lens and square sensor; resolution is the preset's
``geometry.image_size``.

Mesh files are read in the object frame *as stored*, i.e. the coordinates
trimesh reads from the same file (so ground truth computed with trimesh
agrees with the renders): OBJ and PLY are imported with no axis conversion,
and for glTF/GLB the importer's Y-up → Z-up conversion is undone.

Lighting is seeded per (seed, shape, view): one of Blender's bundled world
HDRIs (``datafiles/studiolights/world``) at a random rotation and strength,
plus zero to two random sun lights; without the HDRIs, a grey world and one
to three suns.  Backgrounds are seeded the same way, on their own stream.

``bpy`` is imported only inside functions, so importing this module is cheap.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from genre_backend.inference.blender import import_bpy, prepare_blender_environment, quiet_stdout

__all__ = [
    "MESH_SUFFIXES",
    "RenderSettings",
    "ShapeEntry",
    "BlenderRenderer",
    "prepare_blender_environment",
    "view_rng",
    "sample_views",
    "make_background",
    "composite_over",
    "render_shape",
    "view_is_complete",
    "load_view",
    "discover_shapes",
    "main",
]

MESH_SUFFIXES = (".glb", ".gltf", ".obj", ".ply")

# Streams of the per-(shape, view) random generator.
_STREAM_VIEW, _STREAM_LIGHT, _STREAM_BACKGROUND = 0, 1, 2
# glTF (x, y, z) is imported as Blender (x, -z, y); this rotation (-90° about X) undoes it.
_GLTF_UNDO = ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, -1.0, 0.0))
# Per shard, so that parallel workers (--shard I/N) into one folder never write the same file;
# failures are read back from all shards' files.
_FAILURES_GLOB = "render_failures*.json"
_SETTINGS_FILE = "render_settings.json"
# A shape whose render was interrupted this many times (e.g. Blender crashed) is given up.
MAX_ATTEMPTS = 2


# --------------------------------------------------------------------------- environment


# --------------------------------------------------------------------------- randomness


def _shape_key(shape_id: str) -> int:
    return zlib.crc32(shape_id.encode("utf-8"))


def view_rng(seed: int, shape_id: str, view_index: int, stream: int) -> np.random.Generator:
    """The random generator of one (seed, shape, view, stream); deterministic across runs and machines."""
    if view_index < 0:
        raise ValueError(f"view_index must be >= 0, got {view_index}")
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, _shape_key(shape_id), int(view_index), int(stream)])


def sample_views(shape_id: str, n_views: int, seed: int, camera) -> list[tuple[float, float]]:
    """``n_views`` random (azimuth, elevation) pairs in degrees for one shape.

    Azimuth is uniform in [0, 360); elevation uniform in the camera config's
    ``[elevation_min_deg, elevation_max_deg]``.  View k depends only on
    (seed, shape_id, k), so asking for more views later keeps the first ones.
    """
    if n_views < 0:
        raise ValueError(f"n_views must be >= 0, got {n_views}")
    lo, hi = float(camera.elevation_min_deg), float(camera.elevation_max_deg)
    if not (-90.0 < lo <= hi < 90.0):
        raise ValueError(f"camera elevation range must lie in (-90, 90), got [{lo}, {hi}]")
    views = []
    for k in range(n_views):
        rng = view_rng(seed, shape_id, k, _STREAM_VIEW)
        views.append((float(rng.uniform(0.0, 360.0)), float(rng.uniform(lo, hi))))
    return views


# --------------------------------------------------------------------------- backgrounds


def _smooth_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """Value noise (size, size, 3) in [0, 1]: a random (cells+1)² colour grid, bilinearly upsampled."""
    grid = rng.random((cells + 1, cells + 1, 3))
    t = (np.arange(size) + 0.5) / size * cells
    i0 = np.minimum(t.astype(int), cells - 1)
    f = (t - i0)[:, None]
    rows = grid[i0] * (1 - f)[:, :, None] + grid[i0 + 1] * f[:, :, None]  # (size, cells+1, 3)
    out = rows[:, i0] * (1 - f.T)[:, :, None] + rows[:, i0 + 1] * f.T[:, :, None]
    return out


def make_background(rng: np.random.Generator, size: int) -> tuple[np.ndarray, dict[str, Any]]:
    """A random background image (size, size, 3) float32 in [0, 1] and a description.

    Kinds: ``solid`` (one colour), ``gradient`` (two colours along a random
    direction) and ``noise`` (two to three octaves of smooth value noise).
    """
    if size <= 0:
        raise ValueError(f"background size must be positive, got {size}")
    kind = str(rng.choice(["solid", "gradient", "noise"]))
    if kind == "solid":
        colour = rng.random(3)
        img = np.broadcast_to(colour, (size, size, 3)).copy()
        info = {"kind": kind, "colour": [round(float(c), 4) for c in colour]}
    elif kind == "gradient":
        a, b = rng.random(3), rng.random(3)
        angle = float(rng.uniform(0.0, 2.0 * math.pi))
        coords = (np.arange(size) + 0.5) / size - 0.5
        proj = coords[None, :] * math.cos(angle) - coords[:, None] * math.sin(angle)  # (H, W)
        t = np.clip(proj / math.sqrt(0.5) + 0.5, 0.0, 1.0)[:, :, None]
        img = a * (1 - t) + b * t
        info = {"kind": kind, "angle_deg": round(math.degrees(angle), 2)}
    else:
        octaves = int(rng.integers(2, 4))
        img = np.zeros((size, size, 3))
        weight_sum = 0.0
        for o in range(octaves):
            w = 0.5**o
            img += w * _smooth_noise(rng, size, int(rng.integers(2, 5)) * 2**o)
            weight_sum += w
        img /= weight_sum
        # Stretch the contrast so noise backgrounds are not all mid-grey.
        lo, hi = img.min(), img.max()
        img = (img - lo) / max(hi - lo, 1e-6)
        info = {"kind": kind, "octaves": octaves}
    return img.astype(np.float32), info


def composite_over(rgba: np.ndarray, background: np.ndarray) -> np.ndarray:
    """Straight-alpha ``rgba`` (H, W, 4) uint8 over ``background`` (H, W, 3) float in [0, 1] → (H, W, 3) uint8."""
    if rgba.ndim != 3 or rgba.shape[2] != 4 or rgba.dtype != np.uint8:
        raise ValueError(f"rgba: expected (H, W, 4) uint8, got {rgba.shape} {rgba.dtype}")
    if background.shape != rgba.shape[:2] + (3,):
        raise ValueError(f"background: expected {rgba.shape[:2] + (3,)}, got {background.shape}")
    fg = rgba[..., :3].astype(np.float32) / 255.0
    a = rgba[..., 3:].astype(np.float32) / 255.0
    out = fg * a + background.astype(np.float32) * (1.0 - a)
    return np.clip(np.rint(out * 255.0), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- renderer


@dataclass(frozen=True)
class RenderSettings:
    """Cycles settings.

    ``denoise``: OpenImageDenoise with its fast prefilter and quality.  At 16
    samples the HDRI lighting leaves strong speckle noise on every surface;
    the fast denoiser removes it for ~0.05 s/view at 128², far cheaper than
    the samples that would do the same.
    """

    samples: int = 16
    threads: int = 2
    denoise: bool = True

    def __post_init__(self):
        if self.samples < 1:
            raise ValueError(f"samples must be >= 1, got {self.samples}")
        if self.threads < 1:
            raise ValueError(f"threads must be >= 1, got {self.threads}")


class BlenderRenderer:
    """A bpy scene set up once (camera, world, compositor) that renders shape after shape.

    ``config``: a :class:`genre_backend.config.GenreConfig` (camera + image
    size).  ``scratch_dir``: where the compositor's File Output node writes
    ``view_rgba.png`` and ``view_depth.exr`` for each view (a fresh temporary
    folder by default).  ``quiet``: silence Blender's own prints.

    Blender has one scene state per process, so only the newest renderer is
    usable (:attr:`is_active`); an older one raises RuntimeError.
    """

    def __init__(self, config, settings: RenderSettings | None = None, scratch_dir: str | os.PathLike | None = None,
                 quiet: bool = True):
        self.config = config
        self.settings = settings or RenderSettings()
        self.size = int(config.geometry.image_size)
        if self.size <= 0:
            raise ValueError(f"image_size must be positive, got {self.size}")
        self._own_scratch = scratch_dir is None
        self.scratch = Path(scratch_dir) if scratch_dir is not None else Path(tempfile.mkdtemp(prefix="genre-render-"))
        self.scratch.mkdir(parents=True, exist_ok=True)
        self.quiet = quiet
        self.bpy = import_bpy()
        global _ACTIVE_RENDERER
        _ACTIVE_RENDERER = None  # the factory reset below invalidates any earlier renderer's scene
        with quiet_stdout(self.quiet):
            self._setup_scene()
        self.shape_path: Path | None = None
        _ACTIVE_RENDERER = self

    @property
    def is_active(self) -> bool:
        """False once another :class:`BlenderRenderer` has reset Blender (one per process at a time)."""
        return _ACTIVE_RENDERER is self

    def _check_active(self) -> None:
        if not self.is_active:
            raise RuntimeError("this BlenderRenderer's scene was replaced by a newer BlenderRenderer; make a new one")

    # ---- scene set-up -------------------------------------------------------
    def _setup_scene(self) -> None:
        bpy = self.bpy
        bpy.ops.wm.read_factory_settings(use_empty=True)
        scene = bpy.context.scene
        self.scene = scene
        render = scene.render
        render.engine = "CYCLES"
        scene.cycles.device = "CPU"
        scene.cycles.samples = self.settings.samples
        scene.cycles.use_adaptive_sampling = False
        scene.cycles.use_denoising = self.settings.denoise
        if self.settings.denoise:
            scene.cycles.denoiser = "OPENIMAGEDENOISE"
            scene.cycles.denoising_prefilter = "FAST"
            scene.cycles.denoising_input_passes = "RGB"
            scene.cycles.denoising_quality = "FAST"
        # Clamping and glossy blur remove most fireflies at a small bias (irrelevant for training data).
        scene.cycles.sample_clamp_direct = 4.0
        scene.cycles.sample_clamp_indirect = 2.0
        scene.cycles.blur_glossy = 1.0
        scene.cycles.max_bounces = 4
        scene.cycles.diffuse_bounces = 2
        scene.cycles.glossy_bounces = 2
        scene.cycles.transmission_bounces = 4
        scene.cycles.volume_bounces = 0
        scene.cycles.caustics_reflective = False
        scene.cycles.caustics_refractive = False
        # The light tree pays off with many lights; with at most three suns it only adds set-up work.
        scene.cycles.use_light_tree = False
        scene.cycles.transparent_max_bounces = 8
        render.threads_mode = "FIXED"
        render.threads = self.settings.threads
        render.resolution_x = render.resolution_y = self.size
        render.resolution_percentage = 100
        render.pixel_aspect_x = render.pixel_aspect_y = 1.0
        render.film_transparent = True
        render.use_compositing = True
        render.use_sequencer = False
        render.use_persistent_data = True
        scene.view_settings.view_transform = "Standard"
        scene.view_settings.look = "None"
        scene.view_settings.exposure = 0.0
        scene.view_settings.gamma = 1.0
        view_layer = scene.view_layers[0]
        view_layer.use_pass_z = True

        cam = self.config.camera
        cam_data = bpy.data.cameras.new("genre_camera")
        cam_data.type = "PERSP"
        cam_data.lens_unit = "MILLIMETERS"
        cam_data.lens = float(cam.lens_mm)
        cam_data.sensor_fit = "HORIZONTAL"
        cam_data.sensor_width = float(cam.sensor_mm)
        cam_data.sensor_height = float(cam.sensor_mm)
        cam_data.shift_x = cam_data.shift_y = 0.0
        cam_data.clip_start = 0.01
        cam_data.clip_end = 100.0
        self.camera = bpy.data.objects.new("genre_camera", cam_data)
        scene.collection.objects.link(self.camera)
        scene.camera = self.camera

        self._setup_world()
        self._setup_compositor()
        # Meshes imported without any material get this one, with a random colour per view.
        self.default_material = bpy.data.materials.new("genre_default")
        self.default_bsdf = next(n for n in self.default_material.node_tree.nodes if n.type == "BSDF_PRINCIPLED")
        self.uses_default_material = False
        self.suns = []
        for i in range(3):
            light = bpy.data.lights.new(f"genre_sun_{i}", "SUN")
            obj = bpy.data.objects.new(f"genre_sun_{i}", light)
            scene.collection.objects.link(obj)
            obj.hide_render = True
            self.suns.append(obj)
        # Everything created so far survives clear_shape().
        self._baseline = {name: {id_.as_pointer() for id_ in getattr(bpy.data, name)} for name in _CLEARED_COLLECTIONS}

    def _setup_world(self) -> None:
        bpy = self.bpy
        world = bpy.data.worlds.new("genre_world")
        self.scene.world = world
        nt = world.node_tree  # Blender 5.0 gives new worlds a node tree (use_nodes is deprecated)
        nt.nodes.clear()
        out = nt.nodes.new("ShaderNodeOutputWorld")
        bg = nt.nodes.new("ShaderNodeBackground")
        nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
        self.world_background = bg
        self.hdris = []
        hdri_dir = bpy.utils.system_resource("DATAFILES", path=os.path.join("studiolights", "world"))
        if hdri_dir and os.path.isdir(hdri_dir):
            for name in sorted(os.listdir(hdri_dir)):
                if name.lower().endswith((".exr", ".hdr")):
                    img = bpy.data.images.load(os.path.join(hdri_dir, name), check_existing=True)
                    self.hdris.append(img)
        self.env_texture = None
        self.env_mapping = None
        if self.hdris:
            coords = nt.nodes.new("ShaderNodeTexCoord")
            mapping = nt.nodes.new("ShaderNodeMapping")
            env = nt.nodes.new("ShaderNodeTexEnvironment")
            nt.links.new(coords.outputs["Generated"], mapping.inputs["Vector"])
            nt.links.new(mapping.outputs["Vector"], env.inputs["Vector"])
            nt.links.new(env.outputs["Color"], bg.inputs["Color"])
            env.image = self.hdris[0]
            # The automatic importance map follows the HDRI's size and is rebuilt every
            # view (~3 s at 128²); a fixed 256 map costs ~0.05 s and lights the same.
            world.cycles.sampling_method = "MANUAL"
            world.cycles.sample_map_resolution = 256
            self.env_texture, self.env_mapping = env, mapping

    def _setup_compositor(self) -> None:
        bpy = self.bpy
        tree = bpy.data.node_groups.new("genre_compositor", "CompositorNodeTree")
        self.scene.compositing_node_group = tree
        layers = tree.nodes.new("CompositorNodeRLayers")
        layers.scene = self.scene
        fo = tree.nodes.new("CompositorNodeOutputFile")
        fo.directory = str(self.scratch)
        fo.file_name = "view_"
        fo.format.media_type = "IMAGE"
        fo.format.file_format = "PNG"
        fo.format.color_mode = "RGBA"
        fo.format.color_depth = "8"
        fo.file_output_items.clear()
        fo.file_output_items.new("RGBA", "rgba")
        fo.file_output_items.new("FLOAT", "depth")
        # Item handles go stale when the collection grows: look them up again.
        depth = fo.file_output_items["depth"]
        depth.override_node_format = True
        depth.format.media_type = "IMAGE"
        depth.format.file_format = "OPEN_EXR"
        depth.format.color_mode = "BW"
        depth.format.color_depth = "32"
        depth.format.exr_codec = "NONE"
        inputs = {sock.name: sock for sock in fo.inputs if sock.identifier != "__extend__"}
        tree.links.new(layers.outputs["Image"], inputs["rgba"])
        tree.links.new(layers.outputs["Depth"], inputs["depth"])
        if not (inputs["rgba"].is_linked and inputs["depth"].is_linked):
            raise RuntimeError("could not link the render passes to the File Output node")
        self.file_output = fo

    # ---- shapes -------------------------------------------------------------
    def clear_shape(self) -> None:
        """Remove the current shape and every datablock it brought (meshes, materials, images...)."""
        self._check_active()
        bpy = self.bpy
        for name in _CLEARED_COLLECTIONS:
            keep = self._baseline[name]
            doomed = [id_ for id_ in getattr(bpy.data, name) if id_.as_pointer() not in keep]
            if doomed:
                bpy.data.batch_remove(doomed)
        self.shape_path = None

    def load_shape(self, path: str | os.PathLike) -> int:
        """Clear the scene and import one mesh file (.glb/.gltf/.obj/.ply) in the object frame.

        Returns the number of mesh objects imported.  Raises ValueError for an
        unsupported suffix, a missing file or a file with no mesh.
        """
        self._check_active()
        bpy = self.bpy
        path = Path(path)
        suffix = path.suffix.lower()
        if suffix not in MESH_SUFFIXES:
            raise ValueError(f"{path}: unsupported mesh format {suffix!r}; expected one of {MESH_SUFFIXES}")
        if not path.is_file():
            raise ValueError(f"{path}: no such mesh file")
        self.clear_shape()
        before = {o.as_pointer() for o in bpy.data.objects}
        with quiet_stdout(self.quiet):
            if suffix in (".glb", ".gltf"):
                bpy.ops.import_scene.gltf(filepath=str(path), loglevel=50)
            elif suffix == ".obj":
                bpy.ops.wm.obj_import(filepath=str(path), forward_axis="Y", up_axis="Z", use_split_objects=False,
                                      use_split_groups=False)
            else:
                bpy.ops.wm.ply_import(filepath=str(path), forward_axis="Y", up_axis="Z")
        new = [o for o in bpy.data.objects if o.as_pointer() not in before]
        for obj in new:
            if obj.name not in self.scene.collection.all_objects:
                self.scene.collection.objects.link(obj)
        if suffix in (".glb", ".gltf"):
            import mathutils  # noqa: PLC0415

            undo = mathutils.Matrix(_GLTF_UNDO).to_4x4()
            for obj in new:
                if obj.parent is None:
                    obj.matrix_world = undo @ obj.matrix_world
        meshes = [o for o in new if o.type == "MESH"]
        self.uses_default_material = False
        for obj in meshes:
            slots = obj.data.materials
            if len(slots) == 0:
                slots.append(self.default_material)
                self.uses_default_material = True
            for i, mat in enumerate(slots):
                if mat is None:
                    slots[i] = self.default_material
                    self.uses_default_material = True
        # Importers may add cameras/lights of their own: only ours may render.
        for obj in new:
            if obj.type in ("CAMERA", "LIGHT"):
                obj.hide_render = True
        if not meshes:
            self.clear_shape()
            raise ValueError(f"{path}: the file holds no mesh")
        self.scene.camera = self.camera
        self.shape_path = path
        return len(meshes)

    def shape_bounds(self) -> np.ndarray:
        """World-space bounds (2, 3) float64 [min, max] of the loaded shape's vertices."""
        bpy = self.bpy
        pts = []
        depsgraph = bpy.context.evaluated_depsgraph_get()
        for obj in self.scene.objects:
            if obj.type != "MESH":
                continue
            ev = obj.evaluated_get(depsgraph)
            mesh = ev.to_mesh()
            co = np.empty(len(mesh.vertices) * 3, dtype=np.float64)
            mesh.vertices.foreach_get("co", co)
            co = co.reshape(-1, 3)
            m = np.array(ev.matrix_world, dtype=np.float64)
            pts.append(co @ m[:3, :3].T + m[:3, 3])
            ev.to_mesh_clear()
        if not pts:
            raise ValueError("no shape loaded")
        allp = np.concatenate(pts)
        return np.stack([allp.min(0), allp.max(0)])

    # ---- views --------------------------------------------------------------
    def place_camera(self, azimuth_deg: float, elevation_deg: float) -> np.ndarray:
        """Put the camera at (azimuth, elevation); returns its camera-to-object rotation (3, 3) float64."""
        import mathutils  # noqa: PLC0415
        import torch  # noqa: PLC0415

        from genre_backend import frame  # noqa: PLC0415

        rot = frame.camera_rotation(float(azimuth_deg), float(elevation_deg), dtype=torch.float64)[0].numpy()
        loc = frame.camera_location(float(azimuth_deg), float(elevation_deg), self.config.camera.distance,
                                    dtype=torch.float64)[0].numpy()
        m = np.eye(4)
        m[:3, :3] = rot
        m[:3, 3] = loc
        self.camera.matrix_world = mathutils.Matrix(m.tolist())
        return rot

    def randomise_lighting(self, rng: np.random.Generator) -> dict[str, Any]:
        """Pick the world HDRI, its rotation and strength, and 0–2 suns (1–3 without HDRIs); returns a description.

        Also gives the default material (used by meshes imported without one) a random colour.
        """
        info: dict[str, Any] = {}
        if self.hdris:
            img = self.hdris[int(rng.integers(len(self.hdris)))]
            self.env_texture.image = img
            rot_z = float(rng.uniform(0.0, 2.0 * math.pi))
            self.env_mapping.inputs["Rotation"].default_value = (0.0, 0.0, rot_z)
            strength = float(rng.uniform(0.6, 1.6))
            self.world_background.inputs["Strength"].default_value = strength
            info.update(hdri=img.name, hdri_rotation_deg=round(math.degrees(rot_z), 2), hdri_strength=round(strength, 3))
            n_suns = int(rng.integers(0, 3))
        else:
            grey = float(rng.uniform(0.2, 0.6))
            self.world_background.inputs["Color"].default_value = (grey, grey, grey, 1.0)
            self.world_background.inputs["Strength"].default_value = 1.0
            info.update(world_grey=round(grey, 3))
            n_suns = int(rng.integers(1, 4))
        suns = []
        for i, obj in enumerate(self.suns):
            obj.hide_render = i >= n_suns
            if i >= n_suns:
                continue
            az = float(rng.uniform(0.0, 2.0 * math.pi))
            el = float(rng.uniform(math.radians(10.0), math.radians(80.0)))
            strength = float(rng.uniform(1.0, 4.0))
            tint = 1.0 - 0.15 * rng.random(3)
            obj.data.energy = strength
            obj.data.color = tuple(float(t) for t in tint)
            obj.data.angle = float(rng.uniform(0.02, 0.3))
            # A sun shines along its local −Z: point local +Z at the direction it comes from.
            import mathutils  # noqa: PLC0415

            direction = mathutils.Vector((math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)))
            obj.rotation_euler = direction.to_track_quat("Z", "Y").to_euler()
            suns.append({"azimuth_deg": round(math.degrees(az), 2), "elevation_deg": round(math.degrees(el), 2),
                         "strength": round(strength, 3)})
        info["suns"] = suns
        if self.uses_default_material:
            # Draw the colour last so the lighting above does not depend on whether it is used.
            colour = 0.1 + 0.8 * rng.random(3)
            self.default_bsdf.inputs["Base Color"].default_value = (*(float(c) for c in colour), 1.0)
            roughness = float(rng.uniform(0.3, 0.9))
            self.default_bsdf.inputs["Roughness"].default_value = roughness
            info["default_material"] = {"colour": [round(float(c), 4) for c in colour], "roughness": round(roughness, 3)}
        return info

    def render_view(self, azimuth_deg: float, elevation_deg: float, light_rng: np.random.Generator) -> dict[str, Any]:
        """Render one view of the loaded shape.

        Returns ``rgba`` (H, W, 4) uint8 (straight alpha, transparent film),
        ``raw_depth`` (H, W) float32 (Cycles Z pass, background 1e10), row 0
        at the top of the image, ``rotation`` (3, 3) float64 camera-to-object,
        and ``lighting`` (a JSON-able description).
        """
        self._check_active()
        bpy = self.bpy
        if self.shape_path is None:
            raise ValueError("render_view: no shape loaded (call load_shape first)")
        rot = self.place_camera(azimuth_deg, elevation_deg)
        lighting = self.randomise_lighting(light_rng)
        rgba_path = self.scratch / "view_rgba.png"
        depth_path = self.scratch / "view_depth.exr"
        for f in (rgba_path, depth_path):
            f.unlink(missing_ok=True)
        with quiet_stdout(self.quiet):
            bpy.ops.render.render(write_still=False)
        if not rgba_path.is_file() or not depth_path.is_file():
            found = sorted(p.name for p in self.scratch.iterdir())
            raise RuntimeError(f"the compositor wrote {found}, expected view_rgba.png and view_depth.exr")
        from PIL import Image  # noqa: PLC0415

        with Image.open(rgba_path) as im:
            rgba = np.asarray(im.convert("RGBA"), dtype=np.uint8).copy()
        img = bpy.data.images.load(str(depth_path))
        try:
            img.colorspace_settings.name = "Non-Color"
            w, h = img.size
            buf = np.empty(w * h * img.channels, dtype=np.float32)
            img.pixels.foreach_get(buf)
        finally:
            bpy.data.images.remove(img)
        raw_depth = buf.reshape(h, w, -1)[::-1, :, 0].copy()  # Blender rows are bottom-up
        if rgba.shape[:2] != (self.size, self.size) or raw_depth.shape != (self.size, self.size):
            raise RuntimeError(f"unexpected render size {rgba.shape} / {raw_depth.shape}, expected {self.size}²")
        return {"rgba": rgba, "raw_depth": raw_depth, "rotation": rot, "lighting": lighting}

    def close(self) -> None:
        """Drop the shape and remove the scratch folder if this renderer made it."""
        if self.is_active:
            self.clear_shape()
        for name in ("view_rgba.png", "view_depth.exr"):
            (self.scratch / name).unlink(missing_ok=True)
        if self._own_scratch and self.scratch.is_dir() and not any(self.scratch.iterdir()):
            self.scratch.rmdir()


_ACTIVE_RENDERER: BlenderRenderer | None = None

_CLEARED_COLLECTIONS = (
    "objects", "meshes", "materials", "images", "textures", "node_groups", "cameras", "lights",
    "collections", "actions", "armatures", "curves", "worlds",
)


# --------------------------------------------------------------------------- files


def _atomic_write(path: Path, writer) -> None:
    """Call ``writer(file_object)`` on a temporary file beside ``path``, then rename it to ``path``."""
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "wb") as fh:
            writer(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def _write_json(path: Path, data: Any) -> None:
    _atomic_write(path, lambda fh: fh.write((json.dumps(data, indent=1) + "\n").encode("utf-8")))


def _view_paths(shape_dir: Path, k: int) -> dict[str, Path]:
    stem = f"view_{k:03d}"
    return {"png": shape_dir / f"{stem}.png", "npz": shape_dir / f"{stem}.npz", "json": shape_dir / f"{stem}.json"}


def view_is_complete(shape_dir: str | os.PathLike, k: int) -> bool:
    """True iff view ``k`` of the shape folder has all three files (the JSON is written last)."""
    return all(p.is_file() for p in _view_paths(Path(shape_dir), k).values())


def load_view(shape_dir: str | os.PathLike, k: int) -> dict[str, Any]:
    """Read back view ``k``: ``rgb`` (H, W, 3) uint8, ``depth`` (H, W) float32, ``mask`` (H, W) float32, ``camera`` dict."""
    paths = _view_paths(Path(shape_dir), k)
    if not view_is_complete(shape_dir, k):
        raise ValueError(f"{shape_dir}: view {k} is not complete")
    from PIL import Image  # noqa: PLC0415

    with Image.open(paths["png"]) as im:
        rgb = np.asarray(im.convert("RGB"), dtype=np.uint8).copy()
    with np.load(paths["npz"]) as z:
        depth, mask = z["depth"].copy(), z["mask"].copy()
    camera = json.loads(paths["json"].read_text())
    return {"rgb": rgb, "depth": depth, "mask": mask, "camera": camera}


@dataclass(frozen=True)
class ShapeEntry:
    """One shape to render: its id (also the output sub-folder), mesh path, optional class/split/groups."""

    id: str
    path: Path
    cls: str | None = None
    split: str | None = None
    groups: tuple[str, ...] = ()


def render_shape(
    renderer: BlenderRenderer,
    shape: ShapeEntry,
    views: Sequence[tuple[float, float]],
    out_dir: str | os.PathLike,
    seed: int,
    on_view=None,
) -> int:
    """Render the missing views of one shape into ``out_dir/<shape.id>/``; returns how many were rendered.

    ``views``: (azimuth, elevation) pairs in degrees; view k is stored as
    ``view_KKK.*``.  Complete views are skipped (the mesh is not even loaded
    when all are complete).  ``on_view(k)`` is called after each view,
    rendered or skipped.
    """
    import torch  # noqa: PLC0415

    from genre_backend import frame  # noqa: PLC0415

    if not shape.id or "/" in shape.id or "\\" in shape.id or shape.id.startswith("."):
        raise ValueError(f"shape id {shape.id!r} is not usable as a folder name")
    shape_dir = Path(out_dir) / shape.id
    todo = [k for k in range(len(views)) if not view_is_complete(shape_dir, k)]
    for k in range(len(views)):
        if k not in todo and on_view:
            on_view(k)
    if not todo:
        return 0
    renderer.load_shape(shape.path)
    shape_dir.mkdir(parents=True, exist_ok=True)
    # Temporary files of a killed earlier run (one process renders a shape at a time).
    for stale in shape_dir.glob(".view_*.tmp-*"):
        stale.unlink(missing_ok=True)
    cam = renderer.config.camera
    size = renderer.size
    for k in todo:
        az, el = (float(v) for v in views[k])
        out = renderer.render_view(az, el, view_rng(seed, shape.id, k, _STREAM_LIGHT))
        background, bg_info = make_background(view_rng(seed, shape.id, k, _STREAM_BACKGROUND), size)
        rgb = composite_over(out["rgba"], background)
        depth = frame.encode_raw_depth(torch.from_numpy(out["raw_depth"])).numpy().astype(np.float32)
        mask = out["rgba"][..., 3].astype(np.float32) / 255.0
        paths = _view_paths(shape_dir, k)
        from PIL import Image  # noqa: PLC0415

        _atomic_write(paths["png"], lambda fh: Image.fromarray(rgb, "RGB").save(fh, format="PNG"))
        _atomic_write(paths["npz"], lambda fh: np.savez_compressed(fh, depth=depth, mask=mask))
        rot = out["rotation"]
        meta = {
            "shape_id": shape.id,
            "class": shape.cls,
            "split": shape.split,
            "mesh": str(shape.path),
            "view": k,
            "preset": getattr(renderer.config, "preset", None),
            "seed": int(seed),
            "image_size": size,
            "azimuth_deg": az,
            "elevation_deg": el,
            "distance": float(cam.distance),
            "lens_mm": float(cam.lens_mm),
            "sensor_mm": float(cam.sensor_mm),
            "focal_px": float(cam.focal_px(size)),
            "rotation_cam_to_obj": rot.tolist(),
            "camera_location": (rot[:, 2] * float(cam.distance)).tolist(),
            "depth": "planar Z-pass, encoded with frame.encode_raw_depth (background 0)",
            "mask": "film alpha in [0, 1]",
            "samples": renderer.settings.samples,
            "lighting": out["lighting"],
            "background": bg_info,
        }
        _write_json(paths["json"], meta)
        if on_view:
            on_view(k)
    return len(todo)


# --------------------------------------------------------------------------- shape lists


def _entry_list(data: Any, where: str) -> list[dict]:
    if isinstance(data, list):
        entries = data
    elif isinstance(data, dict):
        for key in ("shapes", "entries", "items"):
            if isinstance(data.get(key), list):
                entries = data[key]
                break
        else:
            raise ValueError(f"{where}: expected a list of shapes or an object with a 'shapes' list")
    else:
        raise ValueError(f"{where}: expected a list or an object, got {type(data).__name__}")
    for i, e in enumerate(entries):
        if not isinstance(e, dict) or not isinstance(e.get("id"), str) or not e["id"]:
            raise ValueError(f"{where}: entry {i} has no string 'id'")
    return entries


def discover_shapes(source: str | os.PathLike) -> list[ShapeEntry]:
    """The shapes named by a manifest JSON or found in a folder, in a stable order.

    Manifest: a list (or ``{"shapes": [...]}``) of entries with ``id`` and
    optionally ``class``, ``split``, ``groups`` and ``mesh`` (relative to the
    manifest's folder); without ``mesh`` the mesh is
    ``<manifest folder>/shapes/<id>.glb``.  Folder: every mesh file under it
    (recursively); the id is the relative path without suffix with ``/``
    replaced by ``__``, the class is the first sub-folder (if any).
    """
    src = Path(source)
    if src.is_file():
        try:
            data = json.loads(src.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ValueError(f"{src}: not a readable JSON manifest ({exc})") from None
        base = src.parent
        shapes = []
        seen = set()
        for e in _entry_list(data, str(src)):
            # ("path" in corpus manifests is the *source* file, never the normalised mesh.)
            rel = e.get("mesh")
            path = (base / rel) if rel else base / "shapes" / f"{e['id']}.glb"
            if e["id"] in seen:
                raise ValueError(f"{src}: duplicate shape id {e['id']!r}")
            seen.add(e["id"])
            groups = tuple(str(g) for g in e.get("groups") or ())
            shapes.append(ShapeEntry(e["id"], path, e.get("class"), e.get("split"), groups))
        return shapes
    if src.is_dir():
        shapes = []
        for p in sorted(src.rglob("*")):
            if p.is_file() and p.suffix.lower() in MESH_SUFFIXES and not p.name.startswith("."):
                rel = p.relative_to(src)
                sid = "__".join(rel.with_suffix("").parts)
                cls = rel.parts[0] if len(rel.parts) > 1 else None
                shapes.append(ShapeEntry(sid, p, cls, None))
        return shapes
    raise ValueError(f"{src}: neither a manifest file nor a folder")


# --------------------------------------------------------------------------- CLI


def _parse_shard(text: str) -> tuple[int, int]:
    try:
        i, n = (int(t) for t in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--shard expects I/N, got {text!r}") from None
    if n < 1 or not 0 <= i < n:
        raise argparse.ArgumentTypeError(f"--shard I/N needs 0 <= I < N, got {text!r}")
    return i, n


def _positive(text: str) -> int:
    v = int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text}")
    return v


def _build_parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog,
        description="Render RGB, planar depth, mask and camera JSON for every shape (Blender Cycles, CPU).",
    )
    p.add_argument("--shapes", required=True, help="a manifest JSON (data/corpus/manifest.json) or a folder of meshes")
    p.add_argument("--out", required=True, help="output folder (one sub-folder per shape)")
    p.add_argument("--views", type=_positive, default=20, help="random views per shape (default 20)")
    p.add_argument("--preset", choices=["default", "paper"], default="default", help="image size preset")
    p.add_argument("--seed", type=int, default=0, help="seed of views, lighting and backgrounds")
    p.add_argument("--limit", type=_positive, default=None, help="render only the first K shapes")
    p.add_argument("--shard", type=_parse_shard, default=(0, 1), metavar="I/N", help="render every N-th shape from I")
    p.add_argument("--split", default=None, help="only manifest shapes of this split or group (e.g. train, unseen)")
    p.add_argument("--samples", type=_positive, default=RenderSettings.samples, help="Cycles samples per pixel")
    p.add_argument("--threads", type=_positive, default=RenderSettings.threads, help="Cycles CPU threads")
    p.add_argument("--no-denoise", dest="denoise", action="store_false", help="turn off the fast OIDN denoiser")
    p.add_argument("--retry-failed", action="store_true", help="try again shapes recorded as failed")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def _read_json(path: Path, default):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return default


def main(argv: Sequence[str] | None = None, prog: str = "genre data render") -> int:
    """``genre data render``: render every shape's views.

    Returns 0 when every shape is complete or was already recorded as failed,
    1 when a shape failed in this run (recorded in ``render_failures*.json``
    and skipped by later runs unless ``--retry-failed``), 2 on a usage error.
    A shape whose rendering was interrupted ``MAX_ATTEMPTS`` times (Blender
    crashed or the process was killed while on it) is recorded as failed.
    """
    args = _build_parser(prog).parse_args(list(sys.argv[1:] if argv is None else argv))
    from genre_backend.config import get_preset  # noqa: PLC0415

    try:
        config = get_preset(args.preset)
        shapes = discover_shapes(args.shapes)
    except ValueError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    if args.split is not None:
        shapes = [s for s in shapes if s.split == args.split or args.split in s.groups]
    shapes = shapes[args.shard[0]::args.shard[1]]
    if args.limit is not None:
        shapes = shapes[: args.limit]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    settings = RenderSettings(samples=args.samples, threads=args.threads, denoise=args.denoise)
    run_settings = {"preset": args.preset, "seed": args.seed, "image_size": config.geometry.image_size,
                    "camera": config.to_dict()["camera"]}
    previous = _read_json(out / _SETTINGS_FILE, None)
    if previous is not None and previous != run_settings:
        print(f"{prog}: error: {out} was rendered with other settings {previous}; use another --out", file=sys.stderr)
        return 2
    if previous is None:
        _write_json(out / _SETTINGS_FILE, run_settings)

    shard_tag = "" if args.shard[1] == 1 else f".shard{args.shard[0]}of{args.shard[1]}"
    failures_file = out / f"render_failures{shard_tag}.json"
    inflight_file = out / f".render_inflight{shard_tag}.json"
    failures: dict[str, str] = {}
    for path in sorted(out.glob(_FAILURES_GLOB)):
        failures.update(_read_json(path, {}))
    inflight: dict[str, int] = _read_json(inflight_file, {})
    if args.retry_failed:
        for path in out.glob(_FAILURES_GLOB):
            path.unlink(missing_ok=True)
        failures, inflight = {}, {}
    total_views = len(shapes) * args.views
    from tqdm import tqdm  # noqa: PLC0415

    bar = tqdm(total=total_views, unit="view", desc="render", disable=args.no_progress, dynamic_ncols=True)
    renderer = None
    rendered = 0
    new_failures = 0
    t0 = time.perf_counter()
    try:
        for shape in shapes:
            views = sample_views(shape.id, args.views, args.seed, config.camera)
            if shape.id in failures:
                bar.update(args.views)
                continue
            attempts = int(inflight.get(shape.id, 0))
            if attempts >= MAX_ATTEMPTS:
                failures[shape.id] = f"rendering was interrupted {attempts} times (Blender crashed or was killed)"
                _write_json(failures_file, failures)
                new_failures += 1
                bar.update(args.views)
                continue
            shape_dir = out / shape.id
            if all(view_is_complete(shape_dir, k) for k in range(args.views)):
                bar.update(args.views)
                continue
            inflight[shape.id] = attempts + 1
            _write_json(inflight_file, inflight)
            reported = [0]

            def on_view(k, reported=reported):
                reported[0] += 1
                bar.update(1)

            if renderer is None:  # started only when there is work; a failure here is fatal, not the shape's
                try:
                    renderer = BlenderRenderer(config, settings)
                except Exception as exc:  # noqa: BLE001
                    tqdm.write(f"{prog}: error: could not set up Blender: {type(exc).__name__}: {exc}", file=sys.stderr)
                    return 2
            try:
                rendered += render_shape(renderer, shape, views, out, args.seed, on_view=on_view)
            except Exception as exc:  # noqa: BLE001  (one bad shape must not stop the corpus)
                failures[shape.id] = f"{type(exc).__name__}: {exc}"
                _write_json(failures_file, failures)
                new_failures += 1
                tqdm.write(f"{prog}: skipped {shape.id}: {failures[shape.id]}", file=sys.stderr)
                bar.update(args.views - reported[0])
            inflight.pop(shape.id, None)
            _write_json(inflight_file, inflight)
    finally:
        bar.close()
        if renderer is not None:
            renderer.close()
    dt = time.perf_counter() - t0
    rate = f", {dt / rendered:.3f} s/view including start-up" if rendered else ""
    summary = f"rendered {rendered} views of {len(shapes)} shapes in {dt:.1f} s{rate}"
    if failures:
        summary += f"; {len(failures)} failed shapes are listed in {out / 'render_failures*.json'}"
    print(summary)
    return 1 if new_failures else 0


if __name__ == "__main__":
    sys.exit(main())
