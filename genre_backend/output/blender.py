"""Blender (``bpy``) as a library: environment, quiet output, and mesh previews.

``bpy`` is imported only inside functions (it costs ~1 s and ~300 MB), so
importing this module is cheap.  The training renderer
(:mod:`training.render.scene`), the evaluation gallery and ``genre reconstruct
--preview`` all go through :func:`import_bpy`.
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import stat
import sys
import tempfile
from pathlib import Path

import numpy as np

from ..config import CameraConfig
from ..process import private_folder

# the fallback cache folder of a process (when <tmp>/genre-blender-<uid> cannot be trusted), and the folder of
# Blender's own session folder (blender_XXXXXX): both PREFIX<pid>-XXXXXXXX, removed when the process ends
FALLBACK_PREFIX = "genre-blender-p"
SESSION_PREFIX = "genre-bpy-"
_session_base: list[Path] = []

__all__ = ["prepare_blender_environment", "blender_session_folder", "factory_reset", "own_private_folder", "private_scratch", "quiet_stdout", "import_bpy", "render_meshes", "render_views", "PREVIEW_VIEWS", "render_textured"]


def prepare_blender_environment(cache_dir: str | os.PathLike | None = None) -> Path:
    """Point Blender's user resources and cache at ``cache_dir`` before ``import bpy``.

    Sets ``BLENDER_USER_RESOURCES`` and ``XDG_CACHE_HOME`` unless they are
    already set, so bpy never writes into the home folder.  The default
    folder is ``$GENRE_BLENDER_CACHE``, else ``<tmp>/genre-blender-<uid>``
    when that is a real folder of this user's that nobody else can write
    (:func:`own_private_folder`), else a fresh private folder of this process,
    ``genre-blender-p<pid>-XXXXXXXX``, removed when the process ends (and, after
    a kill, by the next process that needs one: :func:`genre_backend.process.private_folder`).
    Returns the folder used.
    """
    if cache_dir is None:
        cache_dir = os.environ.get("GENRE_BLENDER_CACHE")
    if cache_dir is None:
        uid = os.getuid() if hasattr(os, "getuid") else "user"
        root = own_private_folder(Path(tempfile.gettempdir()) / f"genre-blender-{uid}")
        if root is None:  # someone else's folder (or a link) took the shared name: a fresh one, removed at the end
            root = private_folder(FALLBACK_PREFIX)
    else:
        root = Path(cache_dir)
    (root / "user").mkdir(parents=True, exist_ok=True)
    (root / "xdg-cache").mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("BLENDER_USER_RESOURCES", str(root / "user"))
    os.environ.setdefault("XDG_CACHE_HOME", str(root / "xdg-cache"))
    return root


def own_private_folder(path: Path) -> Path | None:
    """``path`` as a folder only this user can enter (created 0700 when missing), or None when it cannot be trusted.

    A folder under a shared, world-writable parent (``/tmp``) with a
    predictable name may have been made by someone else, or be a symbolic
    link to somewhere else; either is refused (None) rather than written
    into.  An existing real folder of this user's is made 0700.
    """
    try:
        os.mkdir(path, 0o700)
    except FileExistsError:
        pass
    except OSError:
        return None
    try:
        st = os.lstat(path)
    except OSError:
        return None
    if not stat.S_ISDIR(st.st_mode):  # a symbolic link (lstat does not follow it) or a file
        return None
    if hasattr(os, "getuid"):
        if st.st_uid != os.getuid():
            return None
        if stat.S_IMODE(st.st_mode) & 0o077:
            try:
                os.chmod(path, 0o700, follow_symlinks=False)
            except (OSError, NotImplementedError):
                return None
    return path


def private_matplotlib_config() -> None:
    """Point ``MPLCONFIGDIR`` at a private folder of this process (``tempfile.mkdtemp``, removed at exit) unless the
    user set one, so that matplotlib never creates ``$HOME/.config/matplotlib`` or ``~/.cache/matplotlib``.

    Call before the first ``import matplotlib``.
    """
    if os.environ.get("MPLCONFIGDIR") or "matplotlib" in sys.modules:
        return
    import atexit
    import shutil

    folder = tempfile.mkdtemp(prefix="genre-matplotlib-")
    os.environ["MPLCONFIGDIR"] = folder
    atexit.register(shutil.rmtree, folder, True)


@contextlib.contextmanager
def private_scratch(prefix: str = "genre-"):
    """A fresh folder from :func:`tempfile.mkdtemp` (mode 0700, unpredictable name), removed on exit.

    Every temporary file of a render lies in one of these, so no name a
    render writes to can be guessed, or planted as a link, by another user.
    """
    folder = Path(tempfile.mkdtemp(prefix=prefix))
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


@contextlib.contextmanager
def quiet_stdout(enabled: bool = True):
    """Silence Blender's C-level prints ("Saved: ...", importer logs) on file descriptor 1."""
    if not enabled:
        yield
        return
    with _quiet_fd(1):
        yield


@contextlib.contextmanager
def _quiet_fd(fd: int):
    """Send file descriptor ``fd`` (1: stdout, 2: stderr) to the null device for the block (C-level prints too)."""
    stream = sys.stdout if fd == 1 else sys.stderr
    stream.flush()
    try:
        saved = os.dup(fd)
    except OSError:  # no real descriptor (embedded interpreter): nothing to silence
        yield
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
        yield
    finally:
        stream.flush()
        os.dup2(saved, fd)
        os.close(saved)
        os.close(devnull)


@contextlib.contextmanager
def blender_session_folder():
    """Blender makes its session folder (``blender_XXXXXX``, for its render results and caches) under ``$TMP`` or
    ``$TMPDIR`` when bpy is imported and again at each factory reset, and removes it only at a normal exit of
    the interpreter (never after ``os._exit``, as ``genre reconstruct`` ends, nor after a kill).  Inside this
    block those variables name a private folder of this process (``genre-bpy-<pid>-XXXXXXXX``,
    :func:`genre_backend.process.private_folder`), so that folder, and Blender's inside it, is removed when the
    process ends in any way it survives, and by the next process after a kill.  Wrap every ``import bpy`` and
    ``bpy.ops.wm.read_factory_settings``."""
    if not _session_base:  # (made by mkdtemp, which reads Python's temp folder, once, before the variables change)
        _session_base.append(private_folder(SESSION_PREFIX))
    names = ("TMP", "TMPDIR")
    saved = {name: os.environ.get(name) for name in names}
    for name in names:
        os.environ[name] = str(_session_base[0])
    try:
        yield _session_base[0]
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def import_bpy():
    """``import bpy`` after :func:`prepare_blender_environment` (first call only), Blender's session folder in a
    private folder of this process (:func:`blender_session_folder`)."""
    if "bpy" not in sys.modules:
        prepare_blender_environment()
    with blender_session_folder():  # (also made now when bpy came in otherwise: a stock Blender's, a test's)
        import bpy  # noqa: PLC0415  (deliberately lazy)

    return bpy


def factory_reset(bpy) -> None:
    """``bpy.ops.wm.read_factory_settings(use_empty=True)`` (quiet), Blender's session folder kept in this process's
    private folder (:func:`blender_session_folder`)."""
    with quiet_stdout(True), blender_session_folder():
        bpy.ops.wm.read_factory_settings(use_empty=True)


def _empty_scene(size: int):
    """(bpy, scene): Blender reset to an empty factory scene rendering size × size pixels."""
    bpy = import_bpy()
    factory_reset(bpy)
    scene = bpy.context.scene
    scene.render.resolution_x = scene.render.resolution_y = size
    return bpy, scene


def render_meshes(meshes: list[tuple[np.ndarray, np.ndarray]], size: int = 160, samples: int = 16,
                  camera: CameraConfig | None = None) -> list[list[np.ndarray]]:
    """Render view-frame meshes with Blender (Cycles, CPU) from the input camera and from the right side.

    ``meshes``: (vertices (V, 3) float, faces (F, 3) int) pairs in the view
    frame of :mod:`genre_backend.frame`.  Returns, per mesh, ``[front,
    side]`` RGB images (size, size, 3) uint8 on white.  Blender's world is
    the view frame itself: the input camera sits at (0, 0, d) looking along
    −z, the side camera at (d, 0, 0) looking along −x, both with the
    ``camera``'s lens, sensor and distance (default :class:`CameraConfig`).
    Resets Blender to an empty factory scene first.
    """
    if size < 1 or samples < 1:
        raise ValueError(f"size and samples must be positive, got {size}, {samples}")
    cam_cfg = camera or CameraConfig()
    bpy, scene = _empty_scene(size)
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_denoising = False
    scene.render.film_transparent = True
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGBA"
    world = bpy.data.worlds.new("w")
    if world.node_tree is None:
        world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.8, 0.8, 0.8, 1.0)
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.6
    scene.world = world
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy = 3.0
    sun.rotation_euler = (math.radians(-35), math.radians(35), 0.0)
    scene.collection.objects.link(sun)
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    cam.data.lens, cam.data.sensor_width, cam.data.sensor_fit = cam_cfg.lens_mm, cam_cfg.sensor_mm, "HORIZONTAL"
    scene.collection.objects.link(cam)
    scene.camera = cam
    mat = bpy.data.materials.new("clay")
    if mat.node_tree is None:  # Blender < 5 makes materials without nodes (5.0 deprecates use_nodes)
        mat.use_nodes = True
    mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (0.55, 0.62, 0.75, 1.0)
    d = cam_cfg.distance
    poses = [((0.0, 0.0, d), (0.0, 0.0, 0.0)), ((d, 0.0, 0.0), (0.0, math.pi / 2, 0.0))]
    from PIL import Image

    out = []
    with private_scratch("genre-mesh-render-") as scratch:
        tmp = scratch / "render.png"
        for verts, faces in meshes:
            me = bpy.data.meshes.new("m")
            me.from_pydata(np.asarray(verts, float).tolist(), [], np.asarray(faces, int).tolist())
            me.update()
            obj = bpy.data.objects.new("m", me)
            obj.data.materials.append(mat)
            scene.collection.objects.link(obj)
            images = []
            for loc, rot in poses:
                cam.location, cam.rotation_euler = loc, rot
                scene.render.filepath = str(tmp)
                with quiet_stdout(True):
                    bpy.ops.render.render(write_still=True)
                with Image.open(tmp) as im:
                    rgba = np.asarray(im.convert("RGBA"), np.float32) / 255.0
                images.append(((rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:])) * 255).astype(np.uint8))
            bpy.data.objects.remove(obj)
            bpy.data.meshes.remove(me)
            out.append(images)
    return out


# The preview's views: name → (camera location in units of the camera distance, Euler rotation).
# The view frame's camera looks along −z from +z; "side" is that camera turned 90° about the view
# frame's y axis to the object's right (+x), "back" turned 180° (behind the object, looking along +z).
PREVIEW_VIEWS = {
    "front": ((0.0, 0.0, 1.0), (0.0, 0.0, 0.0)),
    "side": ((1.0, 0.0, 0.0), (0.0, math.pi / 2, 0.0)),
    "back": ((0.0, 0.0, -1.0), (0.0, math.pi, 0.0)),
}


def _framing(vertices: np.ndarray, cam_cfg: CameraConfig, views: tuple[str, ...], margin: float) -> tuple[float, dict]:
    """(zoom, {view: (shift_x, shift_y)}): one lens zoom for all views and each view's lens shift so the mesh fills the frame.

    The cameras stay where :data:`PREVIEW_VIEWS` puts them (so the front view
    is the photo's own perspective, only cropped); the lens is lengthened by
    ``zoom`` and shifted so that the largest of the views' projected extents
    spans ``1 − 2·margin`` of the frame, centred.
    """
    v = np.asarray(vertices, np.float64)
    d = cam_cfg.distance
    scale = cam_cfg.lens_mm / (cam_cfg.sensor_mm / 2.0)  # tan → normalised frame coordinates (−1 … 1)
    extents, centres = [], {}
    for name in views:
        (lx, ly, lz), (_, ry, _) = PREVIEW_VIEWS[name]
        # camera axes (right, up, backward) in the view frame for the rotations used (about y only)
        right = np.array([math.cos(ry), 0.0, -math.sin(ry)])
        up = np.array([0.0, 1.0, 0.0])
        back = np.array([math.sin(ry), 0.0, math.cos(ry)])
        rel = v - np.array([lx, ly, lz]) * d
        depth = np.maximum(-(rel @ back), 1e-6)
        x, y = rel @ right / depth * scale, rel @ up / depth * scale
        extents.append(max(x.max() - x.min(), y.max() - y.min()))
        centres[name] = ((x.max() + x.min()) / 2.0, (y.max() + y.min()) / 2.0)
    zoom = 2.0 * (1.0 - 2.0 * margin) / max(max(extents), 1e-6)
    return zoom, {name: (zoom * cx / 2.0, zoom * cy / 2.0) for name, (cx, cy) in centres.items()}


def _loop_uvs(me, uv: np.ndarray, n_vertices: int, n_faces: int) -> np.ndarray:
    """The UVs (L, 2) of the Blender mesh ``me``'s loops from ``uv``: one per vertex (V, 2), or one per corner
    of its triangles (F, 3, 2), as a :class:`~.colour.PhotoTexture`'s ``face_uv``."""
    uvs = np.asarray(uv, np.float64)
    if uvs.shape == (n_faces, 3, 2) and len(me.loops) == 3 * n_faces:
        return uvs.reshape(-1, 2)  # (from_pydata keeps the faces' order and their corners')
    if uvs.shape != (n_vertices, 2):
        raise ValueError(f"expected uv (V, 2) or (F, 3, 2) for {n_vertices} vertices and {n_faces} faces, got {uvs.shape}")
    loops = np.zeros(len(me.loops), np.int64)
    me.loops.foreach_get("vertex_index", loops)
    return uvs[loops]


def _apply_photo_texture(bpy, me, n_vertices: int, uv: np.ndarray, texture: np.ndarray, scratch: Path) -> None:
    """Give the Blender mesh ``me`` a material showing ``texture`` (H, W, 3) uint8 at ``uv``: the vertices' (V, 2)
    or the faces' corners' (F, 3, 2)."""
    from PIL import Image

    tex = np.asarray(texture)
    if tex.ndim != 3 or tex.shape[2] != 3 or tex.dtype != np.uint8:
        raise ValueError(f"render_views: expected a texture (H, W, 3) uint8; got {tex.shape} {tex.dtype}")
    loop_uv = _loop_uvs(me, uv, n_vertices, len(me.polygons))
    tex_path = scratch / "texture.png"
    Image.fromarray(tex).save(tex_path)
    mat = bpy.data.materials.new("photo")
    if mat.node_tree is None:
        mat.use_nodes = True
    node = mat.node_tree.nodes.new("ShaderNodeTexImage")
    node.image = bpy.data.images.load(str(tex_path))
    node.interpolation = "Linear"
    node.extension = "EXTEND"
    mat.node_tree.nodes.active = node
    mat.node_tree.links.new(node.outputs["Color"], mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"])
    layer = me.uv_layers.new(name="photo")
    layer.data.foreach_set("uv", loop_uv.astype(np.float32).ravel())
    me.materials.append(mat)


def render_views(vertices: np.ndarray, faces: np.ndarray, size: int, camera: CameraConfig | None = None,
                 uv: np.ndarray | None = None, texture: np.ndarray | None = None,
                 views: tuple[str, ...] = ("front", "side", "back"), margin: float = 0.04) -> list[np.ndarray]:
    """The preview's mesh views: RGB (size, size, 3) uint8 on white, one per name in ``views`` (:data:`PREVIEW_VIEWS`).

    Workbench (studio light, flat shading, anti-aliased): about a tenth of
    a second a view on a CPU.  With ``uv`` (V, 2) or (F, 3, 2) and ``texture``
    (H, W, 3) uint8 (a :class:`~.colour.PhotoTexture`'s ``face_uv`` and
    ``image``) the mesh shows the photo's
    colour; otherwise a single clay colour.  Every view keeps the camera's
    position and lens axis (``camera``'s distance; the front view is the
    photo's perspective) but one common zoom and a lens shift per view
    frame the mesh (:func:`_framing`), so it fills the panel and the views
    share one scale.  Resets Blender to an empty factory scene first.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    if size < 1 or len(f) == 0:
        raise ValueError(f"render_views: expected size ≥ 1 and a non-empty mesh, got {size}, {len(f)} faces")
    if (uv is None) != (texture is None):
        raise ValueError("render_views: give both uv and texture, or neither")
    cam_cfg = camera or CameraConfig()
    zoom, shifts = _framing(v, cam_cfg, tuple(views), margin)
    bpy, scene = _empty_scene(size)
    scene.render.engine = "BLENDER_WORKBENCH"
    shading = scene.display.shading
    shading.light = "STUDIO"
    shading.color_type = "TEXTURE" if texture is not None else "SINGLE"
    shading.single_color = (0.75, 0.75, 0.75)  # neutral clay: any colour in a view is the photo's
    shading.show_specular_highlight = texture is None
    scene.view_settings.view_transform = "Standard"  # the photo's colours as they are
    scene.render.film_transparent = True
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGBA"
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    cam.data.lens, cam.data.sensor_width, cam.data.sensor_fit = cam_cfg.lens_mm * zoom, cam_cfg.sensor_mm, "HORIZONTAL"
    scene.collection.objects.link(cam)
    scene.camera = cam
    from PIL import Image

    out = []
    with private_scratch("genre-views-") as scratch:
        me = bpy.data.meshes.new("m")
        me.from_pydata(v.tolist(), [], f.tolist())
        # flat shading: Blender's smooth normals put dark specks on the marching-cubes mesh's small facets
        if texture is not None:
            _apply_photo_texture(bpy, me, len(v), uv, texture, scratch)
        me.update()
        obj = bpy.data.objects.new("m", me)
        scene.collection.objects.link(obj)
        tmp = scratch / "render.png"
        for name in views:
            loc, rot = PREVIEW_VIEWS[name]
            cam.location = tuple(c * cam_cfg.distance for c in loc)
            cam.rotation_euler = rot
            cam.data.shift_x, cam.data.shift_y = shifts[name]
            scene.render.filepath = str(tmp)
            with quiet_stdout(True), _quiet_fd(2):  # headless EGL says "EGL_BAD_MATCH" on stderr and renders anyway
                bpy.ops.render.render(write_still=True)
            with Image.open(tmp) as im:
                rgba = np.asarray(im.convert("RGBA"), np.float32) / 255.0
            out.append(np.rint((rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:])) * 255).astype(np.uint8))
    return out


def render_textured(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray, texture: np.ndarray, size: int,
                    camera: CameraConfig | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Render a view-frame mesh with its texture, unlit, through the input camera (Workbench, flat, no anti-aliasing).

    ``vertices`` (V, 3) float, ``faces`` (F, 3) int, ``uv`` (V, 2) or per
    face corner (F, 3, 2) float (v up), ``texture`` (H, W, 3) uint8.
    Returns ``(rgb (size, size, 3) uint8, covered (size, size) bool)``: the
    texture colour each pixel shows, as
    the photo would if the mesh and its UVs were exact, and where the mesh
    covers the image.  The check that colour from the photo lines up with it.
    Resets Blender to an empty factory scene first.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    uvs = np.asarray(uv, np.float64)
    tex = np.asarray(texture)
    if uvs.shape not in ((len(v), 2), (len(f), 3, 2)) or tex.ndim != 3 or tex.shape[2] != 3 or tex.dtype != np.uint8 or size < 1:
        raise ValueError(f"render_textured: expected uv (V, 2) or (F, 3, 2), texture (H, W, 3) uint8, size ≥ 1; "
                         f"got {uvs.shape}, {tex.shape} {tex.dtype}, {size}")
    cam_cfg = camera or CameraConfig()
    bpy, scene = _empty_scene(size)
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.display.shading.light = "FLAT"
    scene.display.shading.color_type = "TEXTURE"
    scene.display.render_aa = "OFF"
    scene.view_settings.view_transform = "Standard"
    scene.render.film_transparent = True
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGBA"
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    cam.data.lens, cam.data.sensor_width, cam.data.sensor_fit = cam_cfg.lens_mm, cam_cfg.sensor_mm, "HORIZONTAL"
    cam.location = (0.0, 0.0, cam_cfg.distance)
    scene.collection.objects.link(cam)
    scene.camera = cam
    from PIL import Image

    with private_scratch("genre-textured-") as scratch:
        out_path = scratch / "render.png"
        me = bpy.data.meshes.new("m")
        me.from_pydata(v.tolist(), [], f.tolist())
        _apply_photo_texture(bpy, me, len(v), uvs, tex, scratch)
        me.update()
        obj = bpy.data.objects.new("m", me)
        scene.collection.objects.link(obj)
        scene.render.filepath = str(out_path)
        with quiet_stdout(True):
            bpy.ops.render.render(write_still=True)
        with Image.open(out_path) as im:
            rgba = np.asarray(im.convert("RGBA"))
    return rgba[..., :3].copy(), rgba[..., 3] == 255

