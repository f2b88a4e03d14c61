"""The Blender scene that renders training views (Cycles, EEVEE or Workbench; Z-pass depth, film alpha).

One Blender process renders many shapes and views without restarting
Blender: the ``bpy`` module (5.0) or a stock Blender running
:mod:`training.render.blender_script` (tested with Debian's 3.4.1).  The few
API differences between those versions (compositor tree and File Output
node, importers, Cycles options) are handled here, by feature checks.
:func:`render_shape` writes each view through :mod:`training.data.views`
(RGB composited over a random background, planar depth encoded with
:func:`genre_backend.frame.encode_raw_depth`, the film alpha as mask, and the
camera JSON last, so a view is complete iff its JSON exists); re-running
skips complete views.

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

Lighting is seeded per (seed, shape, view), in one of :data:`LIGHTINGS`.
``random``: one of Blender's bundled world HDRIs
(``datafiles/studiolights/world``) at a random rotation and strength, plus
zero to two sun lights from anywhere above the ground (so half of them light
the object from behind); without the HDRIs, a grey world and one to three
suns.  ``camera-side``: as a product photo is lit, a key sun always shines
from within 60° of the camera's side (20–70° up), with a dimmer HDRI and
sometimes a weaker fill sun, so the shading the camera sees follows the
surface the same way from view to view.

Engines (:data:`ENGINES`) differ in the RGB only: every engine's raw depth
is the planar Z pass at the pixel centres with the background at 1e10, the
mask is the film alpha and the camera is the same.  EEVEE needs two things
for that: it writes about the far clip distance where no surface is
(:meth:`BlenderRenderer.render_view` maps it to 1e10), and its Z pass keeps
a jittered sample, so its depth comes from a second, one-sample render.
Workbench ignores the HDRI and suns: it lights with its default studio light,
fixed to the camera, and shows each material's viewport colour or image
texture.  EEVEE and Workbench need OpenGL through EGL (:func:`engine_problem`
checks first, since Blender aborts the process without it).

``bpy`` is imported only inside functions, so importing this module is cheap.
"""

from __future__ import annotations

import contextlib
import ctypes
import glob
import math
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from genre_backend.output.blender import factory_reset, import_bpy, prepare_blender_environment, quiet_stdout
from genre_backend.process import private_folder

from ..data.views import MESH_SUFFIXES, ShapeEntry, remove_stale_temporaries, view_is_complete, write_view
from .backgrounds import composite_over, make_background
from .randomness import STREAM_BACKGROUND, STREAM_LIGHT, view_rng

__all__ = [
    "ENGINES",
    "RAW_BACKGROUND",
    "NO_DENOISER_SAMPLE_FACTOR",
    "NO_DENOISER_NOISE_THRESHOLD",
    "engine_problem",
    "RenderSettings",
    "BlenderRenderer",
    "prepare_blender_environment",
    "release_active_renderer",
    "render_shape",
]

# glTF (x, y, z) is imported as Blender (x, -z, y); this rotation (-90° about X) undoes it.
_GLTF_UNDO = ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, -1.0, 0.0))

ENGINES = ("cycles", "eevee", "workbench")
LIGHTINGS = ("random", "camera-side")  # how render views are lit (the module's docstring)
# Blender's identifiers of each engine (EEVEE was BLENDER_EEVEE_NEXT in 4.2–4.5, BLENDER_EEVEE before and since 5.0).
_ENGINE_IDS = {"cycles": ("CYCLES",), "eevee": ("BLENDER_EEVEE", "BLENDER_EEVEE_NEXT"),
               "workbench": ("BLENDER_WORKBENCH",)}
# Workbench anti-aliasing takes one of these sample counts (or none).
_WORKBENCH_AA = (5, 8, 11, 16, 32)
# Without OpenImageDenoise (Debian's Blender 3.4.1 has no denoiser at all), Cycles samples adaptively up to
# this many times the samples asked for (at least twice as many), stopping where the noise falls under the
# threshold.  On 8 views of 4 textured corpus shapes at 128² (scripts/render_noise.py), the mean
# |RGB - a 512-sample render| inside the object: 16 samples 9.5, 64 samples 4.4, 128 samples 2.9, adaptive
# up to 256 at 0.02 2.5 (at 0.05: 4.3); its 99th percentile 45, 19, 12, 10; the speckle (|RGB - 3×3
# median|) 9.5, 5.3, 4.3, 4.0 (the 512-sample renders' own texture: 3.3).  bpy 5.0.1 at 16 samples with
# OIDN scores 5.2, 23 and 3.5 against its own reference.  Blender's Despeckle node (thresholds 0.5: no
# change; 0.03: speckle 5.9 but the error 9.7) and a 3×3 median on top of 64 samples (error 4.4 -> 4.6–4.9)
# did worse.  Cost on the shared 2-core machine: ~1 s a view more than 16 samples.
NO_DENOISER_SAMPLE_FACTOR = 16
NO_DENOISER_NOISE_THRESHOLD = 0.02
# The raw depth of background pixels, for every engine (what Cycles and Workbench write).
RAW_BACKGROUND = 1e10
# Camera clipping.  Shapes lie within ~0.9 of the origin and the camera 2.2 from it; a near clip of 0.1
# (not 0.01) cuts the rasterisers' depth error to a third (median vs Cycles: 1.2e-5 -> 4e-6).  EEVEE
# writes ~_CLIP_END where no surface is: raw depth beyond _EEVEE_BACKGROUND_FRACTION of it is background.
_CLIP_START, _CLIP_END = 0.1, 100.0
_EEVEE_BACKGROUND_FRACTION = 0.99
# Where glvnd looks for EGL drivers (Mesa's is 50_mesa.json).
_EGL_VENDOR_DIRS = ("/usr/share/glvnd/egl_vendor.d", "/etc/glvnd/egl_vendor.d", "/usr/local/share/glvnd/egl_vendor.d")


def engine_problem(engine: str) -> str | None:
    """Why ``engine`` cannot render on this machine (one line), or None; needs no ``bpy``.

    EEVEE and Workbench draw with OpenGL, which headless Blender gets through
    EGL; without libEGL or an EGL driver Blender *aborts the process* when it
    first renders with them, so this is checked before.  Whether this
    Blender has the engine at all is checked when the scene is set up.
    """
    if engine not in ENGINES:
        return f"unknown engine {engine!r}; expected one of {', '.join(ENGINES)}"
    if engine == "cycles" or not sys.platform.startswith("linux"):
        return None
    try:
        ctypes.CDLL("libEGL.so.1")
    except OSError:
        return (f"the {engine} engine needs OpenGL through EGL and libEGL.so.1 is missing "
                f"(Debian: apt-get install libegl1 libegl-mesa0); Blender would abort, so nothing was rendered")
    listed = os.environ.get("__EGL_VENDOR_LIBRARY_FILENAMES", "")
    dirs = [d for d in os.environ.get("__EGL_VENDOR_LIBRARY_DIRS", "").split(":") if d] or list(_EGL_VENDOR_DIRS)
    if not any(os.path.isfile(f) for f in listed.split(":") if f) and not any(
            glob.glob(os.path.join(d, "*.json")) for d in dirs):
        return (f"the {engine} engine needs an EGL driver and none is installed (no *.json in {', '.join(dirs)}; "
                f"Debian: apt-get install libegl-mesa0); Blender would abort, so nothing was rendered")
    return None


@dataclass(frozen=True)
class RenderSettings:
    """Engine and quality settings.

    ``engine``: one of :data:`ENGINES`.  ``samples``: per pixel for Cycles
    and EEVEE; Workbench's anti-aliasing samples (1: none; otherwise rounded
    up to one of 5, 8, 11, 16, 32).  ``threads``: CPU threads (Cycles).
    ``lighting``: one of :data:`LIGHTINGS` (the module's docstring).
    ``denoise`` (Cycles): OpenImageDenoise with its fast prefilter and
    quality.  At 16 samples the HDRI lighting leaves strong speckle noise on
    every surface; the fast denoiser removes it for ~0.05 s/view at 128²,
    far cheaper than the samples that would do the same.  A Blender built
    without OpenImageDenoise (Debian's 3.4.1) samples adaptively up to
    :data:`NO_DENOISER_SAMPLE_FACTOR` times the samples instead and says so
    (:attr:`BlenderRenderer.notes`).
    """

    samples: int = 16
    threads: int = 2
    denoise: bool = True
    engine: str = "cycles"
    lighting: str = "random"  # one of LIGHTINGS

    def __post_init__(self):
        if self.samples < 1:
            raise ValueError(f"samples must be >= 1, got {self.samples}")
        if self.threads < 1:
            raise ValueError(f"threads must be >= 1, got {self.threads}")
        if self.engine not in ENGINES:
            raise ValueError(f"engine must be one of {', '.join(ENGINES)}, got {self.engine!r}")
        if self.lighting not in LIGHTINGS:
            raise ValueError(f"lighting must be one of {', '.join(LIGHTINGS)}, got {self.lighting!r}")

    @property
    def workbench_aa(self) -> str:
        """Workbench's ``render_aa`` for :attr:`samples`: ``'OFF'`` for 1, else the next offered sample count."""
        if self.samples <= 1:
            return "OFF"
        return str(next((n for n in _WORKBENCH_AA if n >= self.samples), _WORKBENCH_AA[-1]))


class BlenderRenderer:
    """A Blender scene set up once (engine, camera, world, compositor) that renders shape after shape.

    ``config``: a :class:`genre_backend.config.GenreConfig` (camera + image
    size).  ``scratch_dir``: where the compositor's File Output node writes
    ``view_rgba*.png`` and ``view_depth*.exr`` for each view (a fresh
    temporary folder by default).  ``quiet``: silence Blender's own prints.

    Raises ValueError when this Blender lacks the settings' engine.
    :attr:`notes` lists what differs from the settings asked for (e.g. no
    denoiser in this Blender), one line each.  :attr:`denoise` is whether
    the denoiser is really on; :attr:`denoiser` says what stands for it
    (``"oidn"``, ``"samples"``: adaptive sampling up to
    :data:`NO_DENOISER_SAMPLE_FACTOR` times the samples, or None) and
    :attr:`samples` is Cycles' real (most) sample count.

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
        self.scratch = Path(scratch_dir) if scratch_dir is not None else private_folder("genre-render-")
        self.scratch.mkdir(parents=True, exist_ok=True)
        self.quiet = quiet
        self.notes: list[str] = []
        self.denoise = False
        self.denoiser: str | None = None
        self.samples = self.settings.samples
        self.bpy = import_bpy()
        self.blender_version = self.bpy.app.version_string
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
        factory_reset(bpy)
        scene = bpy.context.scene
        self.scene = scene
        render = scene.render
        self._set_engine()
        engine = self.settings.engine
        if engine == "cycles":
            self._setup_cycles()
        elif engine == "eevee":
            scene.eevee.taa_render_samples = self.settings.samples
        else:
            shading = scene.display.shading
            shading.light = "STUDIO"
            shading.color_type = "TEXTURE"  # image textures where a material has one, else its viewport colour
            shading.show_specular_highlight = True
            scene.display.render_aa = self.settings.workbench_aa
        render.threads_mode = "FIXED"
        render.threads = self.settings.threads
        render.resolution_x = render.resolution_y = self.size
        render.resolution_percentage = 100
        render.pixel_aspect_x = render.pixel_aspect_y = 1.0
        render.film_transparent = True
        render.use_compositing = True
        render.use_sequencer = False
        # Off: with Cycles' persistent data a view's noise depends on the views rendered before it in the
        # process (lights shown or hidden re-sync in another order), so a resumed run would not reproduce
        # an uninterrupted one.  Rebuilding costs nothing measurable for these scenes (0.22 vs 0.24 s/view).
        render.use_persistent_data = False
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
        cam_data.clip_start = _CLIP_START
        cam_data.clip_end = _CLIP_END
        self.camera = bpy.data.objects.new("genre_camera", cam_data)
        scene.collection.objects.link(self.camera)
        scene.camera = self.camera

        self._setup_world()
        self._setup_compositor()
        # Meshes imported without any material get this one, with a random colour per view.
        self.default_material = bpy.data.materials.new("genre_default")
        if self.default_material.node_tree is None:  # Blender < 5 makes materials without nodes
            self.default_material.use_nodes = True
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

    def _set_engine(self) -> None:
        render = self.scene.render
        tried = _ENGINE_IDS[self.settings.engine]
        for engine_id in tried:
            try:
                render.engine = engine_id
                return
            except TypeError:  # not an engine of this Blender
                continue
        raise ValueError(f"this Blender ({self.blender_version}) has no {self.settings.engine} engine "
                         f"(none of {', '.join(tried)} is among its engines)")

    def _setup_cycles(self) -> None:
        cycles = self.scene.cycles
        cycles.device = "CPU"
        self.denoiser = ("oidn" if _cycles_has_oidn() else "samples") if self.settings.denoise else None
        self.denoise = self.denoiser == "oidn"
        self.samples = self.settings.samples
        cycles.use_adaptive_sampling = False
        if self.denoiser == "samples":
            self.samples *= NO_DENOISER_SAMPLE_FACTOR
            cycles.use_adaptive_sampling = True
            cycles.adaptive_threshold = NO_DENOISER_NOISE_THRESHOLD
            cycles.adaptive_min_samples = 2 * self.settings.samples
            self.notes.append(f"this Blender's Cycles ({self.blender_version}) has no OpenImageDenoise: sampling "
                              f"adaptively up to {self.samples} samples instead of {self.settings.samples} "
                              f"(--no-denoise: {self.settings.samples}, noisy)")
        cycles.samples = self.samples
        cycles.use_denoising = self.denoiser == "oidn"
        if self.denoiser == "oidn":
            cycles.denoiser = "OPENIMAGEDENOISE"
            cycles.denoising_prefilter = "FAST"
            cycles.denoising_input_passes = "RGB"
            _set_if_present(cycles, "denoising_quality", "FAST")  # Blender 4.1+
        # Clamping and glossy blur remove most fireflies at a small bias (irrelevant for training data).
        cycles.sample_clamp_direct = 4.0
        cycles.sample_clamp_indirect = 2.0
        cycles.blur_glossy = 1.0
        cycles.max_bounces = 4
        cycles.diffuse_bounces = 2
        cycles.glossy_bounces = 2
        cycles.transmission_bounces = 4
        cycles.volume_bounces = 0
        cycles.caustics_reflective = False
        cycles.caustics_refractive = False
        # The light tree (Blender 3.5+) pays off with many lights; with at most three suns it only adds set-up work.
        _set_if_present(cycles, "use_light_tree", False)
        cycles.transparent_max_bounces = 8

    def _setup_world(self) -> None:
        bpy = self.bpy
        world = bpy.data.worlds.new("genre_world")
        self.scene.world = world
        if world.node_tree is None:  # Blender < 5 makes worlds without nodes (5.0 deprecates use_nodes)
            world.use_nodes = True
        nt = world.node_tree
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
        """Render layers → a File Output node writing the RGBA (8-bit PNG) and the Z pass (32-bit EXR).

        Blender 5.0: the tree is ``scene.compositing_node_group``, the node has
        ``file_output_items`` and writes ``view_rgba.png``; earlier versions
        (3.4 tested): ``scene.node_tree`` with ``use_nodes``, ``file_slots``,
        a frame number in the names (``view_rgba0001.png``) and a Composite
        node, without which rendering refuses to start.
        """
        bpy = self.bpy
        scene = self.scene
        if hasattr(scene, "compositing_node_group"):
            tree = bpy.data.node_groups.new("genre_compositor", "CompositorNodeTree")
            scene.compositing_node_group = tree
        else:
            scene.use_nodes = True
            tree = scene.node_tree
            tree.nodes.clear()
        layers = tree.nodes.new("CompositorNodeRLayers")
        layers.scene = scene
        image_out = layers.outputs["Image"]
        depth_out = layers.outputs.get("Depth") or layers.outputs["Z"]
        if hasattr(bpy.types, "CompositorNodeComposite"):
            tree.links.new(image_out, tree.nodes.new("CompositorNodeComposite").inputs["Image"])
        fo = tree.nodes.new("CompositorNodeOutputFile")
        if hasattr(fo, "file_output_items"):
            fo.directory = str(self.scratch)
            fo.file_name = "view_"
            fo.format.media_type = "IMAGE"
            _png_rgba(fo.format)
            fo.file_output_items.clear()
            fo.file_output_items.new("RGBA", "rgba")
            fo.file_output_items.new("FLOAT", "depth")
            # Item handles go stale when the collection grows: look them up again.
            depth = fo.file_output_items["depth"]
            depth.override_node_format = True
            depth.format.media_type = "IMAGE"
            _exr_float(depth.format)
            inputs = [sock for sock in fo.inputs if sock.identifier != "__extend__"]
        else:
            fo.base_path = str(self.scratch)
            _png_rgba(fo.format)
            fo.file_slots.clear()
            fo.file_slots.new("view_rgba")
            fo.file_slots.new("view_depth")
            depth = fo.file_slots["view_depth"]
            depth.use_node_format = False
            _exr_float(depth.format)
            inputs = list(fo.inputs)
        tree.links.new(image_out, inputs[0])
        tree.links.new(depth_out, inputs[1])
        if not (inputs[0].is_linked and inputs[1].is_linked):
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
                with _numpy_bool_alias():
                    bpy.ops.import_scene.gltf(filepath=str(path), loglevel=50)
            elif suffix == ".obj":
                options = bpy.ops.wm.obj_import.get_rna_type().properties.keys()
                split = {k: False for k in ("use_split_objects", "use_split_groups") if k in options}  # 3.5+
                bpy.ops.wm.obj_import(filepath=str(path), forward_axis="Y", up_axis="Z", **split)
            elif "ply_import" in dir(bpy.ops.wm):  # Blender 3.6+
                bpy.ops.wm.ply_import(filepath=str(path), forward_axis="Y", up_axis="Z")
            else:  # the older Python importer keeps the stored axes
                bpy.ops.import_mesh.ply(filepath=str(path))
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
                colours = _colour_attribute(obj.data)
                if colours is not None:  # what Blender 4+/5's glTF importer makes; 3.4's makes no material
                    slots.append(self._vertex_colour_material(colours))
                else:
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

    def _vertex_colour_material(self, attribute: str):
        """A material showing the colour attribute ``attribute`` (Principled BSDF: metallic 0, roughness 0.5),
        as the glTF importer of Blender 4 and 5 makes for a mesh with vertex colours and no material."""
        mat = self.bpy.data.materials.new("genre_vertex_colour")
        if mat.node_tree is None:
            mat.use_nodes = True
        nodes = mat.node_tree.nodes
        bsdf = next(n for n in nodes if n.type == "BSDF_PRINCIPLED")
        bsdf.inputs["Metallic"].default_value = 0.0
        bsdf.inputs["Roughness"].default_value = 0.5
        node = nodes.new("ShaderNodeVertexColor")
        node.layer_name = attribute
        mat.node_tree.links.new(node.outputs["Color"], bsdf.inputs["Base Color"])
        return mat

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
        """Light the view in the settings' :data:`LIGHTINGS` kind; returns a description.

        ``random``: the world HDRI, its rotation and strength, and 0–2 suns from anywhere (1–3 without HDRIs).
        ``camera-side``: a key sun from the camera's side (call after :meth:`place_camera`), a dimmer HDRI
        (or grey world) and, half the time, a fill sun; see the module's docstring.
        Also gives the default material (used by meshes imported without one) a random colour.
        """
        camera_side = self.settings.lighting == "camera-side"
        info: dict[str, Any] = {"kind": self.settings.lighting} if camera_side else {}
        if self.hdris:
            img = self.hdris[int(rng.integers(len(self.hdris)))]
            self.env_texture.image = img
            rot_z = float(rng.uniform(0.0, 2.0 * math.pi))
            self.env_mapping.inputs["Rotation"].default_value = (0.0, 0.0, rot_z)
            strength = float(rng.uniform(0.25, 0.6) if camera_side else rng.uniform(0.6, 1.6))
            self.world_background.inputs["Strength"].default_value = strength
            info.update(hdri=img.name, hdri_rotation_deg=round(math.degrees(rot_z), 2), hdri_strength=round(strength, 3))
            n_suns = int(rng.integers(1, 3) if camera_side else rng.integers(0, 3))
        else:
            grey = float(rng.uniform(0.1, 0.3) if camera_side else rng.uniform(0.2, 0.6))
            self.world_background.inputs["Color"].default_value = (grey, grey, grey, 1.0)
            self.world_background.inputs["Strength"].default_value = 1.0
            info.update(world_grey=round(grey, 3))
            n_suns = int(rng.integers(1, 3) if camera_side else rng.integers(1, 4))
        # the camera's own azimuth in the suns' convention (x = cos, y = sin), for camera-side lighting
        cam = self.camera.matrix_world.translation
        cam_az = math.atan2(cam.y, cam.x)
        suns = []
        for i, obj in enumerate(self.suns):
            obj.hide_render = i >= n_suns
            if i >= n_suns:
                continue
            if not camera_side:
                az = float(rng.uniform(0.0, 2.0 * math.pi))
                el = float(rng.uniform(math.radians(10.0), math.radians(80.0)))
                strength = float(rng.uniform(1.0, 4.0))
            elif i == 0:  # the key: within 60° of the camera's side
                az = cam_az + float(rng.uniform(-1.0, 1.0)) * math.radians(60.0)
                el = float(rng.uniform(math.radians(20.0), math.radians(70.0)))
                strength = float(rng.uniform(2.5, 4.5))
            else:  # the fill: weaker, from the camera's other flank or further round
                az = cam_az + float(rng.choice([-1.0, 1.0]) * rng.uniform(math.radians(40.0), math.radians(120.0)))
                el = float(rng.uniform(math.radians(10.0), math.radians(60.0)))
                strength = float(rng.uniform(0.5, 1.5))
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
            self.default_material.diffuse_color = (*(float(c) for c in colour), 1.0)  # what Workbench shows
            roughness = float(rng.uniform(0.3, 0.9))
            self.default_bsdf.inputs["Roughness"].default_value = roughness
            info["default_material"] = {"colour": [round(float(c), 4) for c in colour], "roughness": round(roughness, 3)}
        return info

    def render_view(self, azimuth_deg: float, elevation_deg: float, light_rng: np.random.Generator) -> dict[str, Any]:
        """Render one view of the loaded shape.

        Returns ``rgba`` (H, W, 4) uint8 (straight alpha, transparent film),
        ``raw_depth`` (H, W) float32 (the Z pass: planar depth, background
        :data:`RAW_BACKGROUND` for every engine), row 0 at the top of the
        image, ``rotation`` (3, 3) float64 camera-to-object, and ``lighting``
        (a JSON-able description).
        """
        self._check_active()
        if self.shape_path is None:
            raise ValueError("render_view: no shape loaded (call load_shape first)")
        rot = self.place_camera(azimuth_deg, elevation_deg)
        lighting = self.randomise_lighting(light_rng)
        rgba_path, depth_path = self._render()
        from PIL import Image  # noqa: PLC0415

        with Image.open(rgba_path) as im:
            rgba = np.asarray(im.convert("RGBA"), dtype=np.uint8).copy()
        if self.settings.engine == "eevee" and self.settings.samples > 1:
            # EEVEE's Z pass keeps one of its jittered samples per pixel (off by ~1e-3 where the surface
            # slopes); a one-sample render puts it at the pixel centre, where Cycles and Workbench take it.
            eevee = self.scene.eevee
            eevee.taa_render_samples = 1
            try:
                _, depth_path = self._render()
            finally:
                eevee.taa_render_samples = self.settings.samples
        raw_depth = self._read_depth(depth_path)
        if self.settings.engine == "eevee":  # EEVEE's background is ~the far clip distance
            raw_depth[raw_depth >= _EEVEE_BACKGROUND_FRACTION * _CLIP_END] = RAW_BACKGROUND
        if rgba.shape[:2] != (self.size, self.size) or raw_depth.shape != (self.size, self.size):
            raise RuntimeError(f"unexpected render size {rgba.shape} / {raw_depth.shape}, expected {self.size}²")
        return {"rgba": rgba, "raw_depth": raw_depth, "rotation": rot, "lighting": lighting}

    def _render(self) -> tuple[Path, Path]:
        """Render the scene; returns the File Output node's RGBA PNG and depth EXR."""
        self._clear_scratch()
        with quiet_stdout(self.quiet):
            self.bpy.ops.render.render(write_still=False)
        written = {kind: sorted(self.scratch.glob(pattern)) for kind, pattern in _SCRATCH_FILES.items()}
        if any(len(found) != 1 for found in written.values()):
            found = sorted(p.name for p in self.scratch.iterdir())
            raise RuntimeError(f"the compositor wrote {found}, expected one view_rgba*.png and one view_depth*.exr")
        return written["rgba"][0], written["depth"][0]

    def _read_depth(self, depth_path: Path) -> np.ndarray:
        """The EXR's first channel (H, W) float32, row 0 at the top."""
        bpy = self.bpy
        img = bpy.data.images.load(str(depth_path))
        try:
            img.colorspace_settings.name = "Non-Color"
            w, h = img.size
            buf = np.empty(w * h * img.channels, dtype=np.float32)
            img.pixels.foreach_get(buf)
        finally:
            bpy.data.images.remove(img)
        return buf.reshape(h, w, -1)[::-1, :, 0].copy()  # Blender rows are bottom-up

    def close(self) -> None:
        """Drop the shape and remove the scratch folder if this renderer made it."""
        if self.is_active:
            self.clear_shape()
        self._clear_scratch()
        if self._own_scratch and self.scratch.is_dir() and not any(self.scratch.iterdir()):
            self.scratch.rmdir()


    def _clear_scratch(self) -> None:
        for pattern in _SCRATCH_FILES.values():
            for f in self.scratch.glob(pattern):
                f.unlink(missing_ok=True)


# What the File Output node writes per view (Blender < 5 adds the frame number).
_SCRATCH_FILES = {"rgba": "view_rgba*.png", "depth": "view_depth*.exr"}


@contextlib.contextmanager
def _numpy_bool_alias():
    """``numpy.bool`` for the length of the block where this numpy lacks it (1.24–1.26).

    Blender 3.4's glTF importer writes ``np.bool`` (``set_poly_smoothing``), an
    alias numpy 1.24 removed and 2.0 brought back as ``np.bool_``.  Debian's
    Blender 3.4.1 runs on the system's Python with whatever numpy that Python
    imports (the virtual environment's 1.26, or Debian's own 1.24, which lacks
    it too), so every ``.glb`` import failed.  The alias is the one numpy 2
    has, and it is removed again afterwards.
    """
    added = "bool" not in np.__dict__
    if added:
        np.bool = np.bool_
    try:
        yield
    finally:
        if added:
            np.__dict__.pop("bool", None)


def _colour_attribute(mesh) -> str | None:
    """The name of ``mesh``'s first colour attribute (glTF ``COLOR_0``: ``Col`` in 3.4, ``Color`` in 5.0), or None."""
    attributes = getattr(mesh, "color_attributes", None)  # Blender 3.2+
    if attributes is None:
        attributes = getattr(mesh, "vertex_colors", ())
    return attributes[0].name if len(attributes) else None


def _set_if_present(owner, name: str, value) -> None:
    """Set an option that only some Blender versions have."""
    if hasattr(owner, name):
        setattr(owner, name, value)


def _cycles_has_oidn() -> bool:
    """Whether this Blender's Cycles was built with OpenImageDenoise (Debian's 3.4.1 was not)."""
    try:
        import _cycles  # noqa: PLC0415  (Cycles' own module, present once bpy is imported)
    except ImportError:
        return False
    return bool(getattr(_cycles, "with_openimagedenoise", False))


def _png_rgba(fmt) -> None:
    fmt.file_format = "PNG"
    fmt.color_mode = "RGBA"
    fmt.color_depth = "8"


def _exr_float(fmt) -> None:
    fmt.file_format = "OPEN_EXR"
    try:
        fmt.color_mode = "BW"
    except TypeError:  # Blender < 4 writes EXR in RGB(A) only; the depth is read from the first channel
        fmt.color_mode = "RGB"
    fmt.color_depth = "32"
    fmt.exr_codec = "NONE"


_ACTIVE_RENDERER: BlenderRenderer | None = None

_CLEARED_COLLECTIONS = (
    "objects", "meshes", "materials", "images", "textures", "node_groups", "cameras", "lights",
    "collections", "actions", "armatures", "curves", "worlds",
)


def release_active_renderer() -> None:
    """Forget the active renderer: call before other code resets Blender's scene (e.g.
    :func:`genre_backend.output.blender.render_meshes`); the next render builds its scene anew."""
    global _ACTIVE_RENDERER
    _ACTIVE_RENDERER = None


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
    view ``k`` of :mod:`training.data.views`.  Complete views are skipped (the mesh is not even loaded
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
    remove_stale_temporaries(shape_dir)
    cam = renderer.config.camera
    size = renderer.size
    for k in todo:
        az, el = (float(v) for v in views[k])
        out = renderer.render_view(az, el, view_rng(seed, shape.id, k, STREAM_LIGHT))
        background, bg_info = make_background(view_rng(seed, shape.id, k, STREAM_BACKGROUND), size)
        rgb = composite_over(out["rgba"], background)
        depth = frame.encode_raw_depth(torch.from_numpy(out["raw_depth"])).numpy().astype(np.float32)
        mask = out["rgba"][..., 3].astype(np.float32) / 255.0
        rot = out["rotation"]
        meta = {
            "shape_id": shape.id,
            "class": shape.cls,
            "split": shape.split,
            "groups": list(shape.groups),
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
            "engine": renderer.settings.engine,
            "samples": renderer.samples,
            "denoise": renderer.denoise,
            "denoiser": renderer.denoiser,
            "blender": renderer.blender_version,
            "lighting": out["lighting"],
            "background": bg_info,
        }
        write_view(shape_dir, k, rgb, depth, mask, meta)
        if on_view:
            on_view(k)
    return len(todo)
