"""One reconstruction from start to finish, as plain functions and a class that take explicit arguments.

The modal operator (``ops.py``) calls :func:`prepare_job`, then
:meth:`Job.tick` on every timer tick, then :meth:`Job.apply` once the backend
has answered; the tests call the same functions without a GUI.  Only
:meth:`Job.apply` and the image helpers touch ``bpy`` (always from the main
thread); :class:`~.backend.Request` does the talking.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from dataclasses import dataclass, field
from typing import Any

import bpy
from mathutils import Matrix, Vector

from .annotations import find_annotation, guidance_from_annotation
from .backend import STAGE_LABELS, BackendError, BackendManager, Request, private_temp_root
from .schema import QUALITIES
from .protocol import Result
from .geometry import VIEW_TO_BLENDER_FRONT, MeshFileError, camera_setup, read_obj, to_blender_frame, upright_pixels

__all__ = ["UserError", "JobSpec", "JobLimits", "Job", "prepare_job", "work_root", "COLLECTION_NAME", "BackendError"]

COLLECTION_NAME = "GenRe"


class UserError(ValueError):
    """Something the artist has to fix before a reconstruction can start (one line)."""


@dataclass
class JobSpec:
    """Everything a reconstruction needs, fixed when the artist presses Reconstruct."""

    name: str  # the new object's name (the photo's)
    image_path: str  # the file the backend reads
    work_dir: str  # this job's own temporary folder
    mask_path: str = ""
    strokes_path: str = ""  # strokes image made from the annotation drawn over the photo (annotations.py)
    box: tuple[float, float, float, float] | None = None  # the annotation's Box layer, the photo's pixels
    # the pixels strokes and box are drawn over: "stored" (as the file stores them, EXIF orientation ignored: what
    # Blender's Image Editor shows), so the backend turns them as it turns the photo; '' without them
    guidance_frame: str = ""
    quality: str = "best"  # the backend's named set of options (schema.QUALITIES)
    options: dict[str, Any] = field(default_factory=dict)  # the Advanced rows ticked: option name → value
    smoothing: int = 0
    target_faces: int = 0
    add_camera: bool = True
    colour_from_photo: bool = True
    photo_image: str = ""  # name of an image datablock showing the photo (when chosen in Blender)
    photo_file: str = ""  # else: the photo's file, loaded as the camera's background when needed

    @property
    def output_path(self) -> str:
        return os.path.join(self.work_dir, "mesh.obj")

    @property
    def intermediates_dir(self) -> str:
        """Where the backend writes its pictures of the run: the panel shows ``mask_overlay.png`` from it."""
        return os.path.join(self.work_dir, "intermediates")

    def request_payload(self) -> dict[str, Any]:
        options = {**self.options, "quality": self.quality, "format": "obj", "save_intermediates": self.intermediates_dir}
        if self.colour_from_photo:
            options["texture"] = True
        payload: dict[str, Any] = {"image": self.image_path, "output": self.output_path, "options": options}
        if self.mask_path:
            payload["mask"] = self.mask_path
        if self.strokes_path:
            payload["strokes"] = self.strokes_path
        if self.box is not None:
            payload["box"] = [float(v) for v in self.box]
        if self.guidance_frame and (self.strokes_path or self.box is not None):
            payload["guidance_frame"] = self.guidance_frame
        return payload


def row_overrides(rows) -> dict[str, Any]:
    """The Advanced rows that are ticked, as request options (name → value); :class:`UserError` for a value out of range.

    ``rows``: the scene's ``genre.options`` items (:class:`~.props.GENRE_PG_option`) or anything with their attributes.
    """
    import json

    from .schema import check_value

    out = {}
    for row in rows:
        if not row.override:
            continue
        value = {"float": lambda r: round(float(r.float_value), 6), "int": lambda r: int(r.int_value), "bool": lambda r: bool(r.bool_value),
                 "choice": lambda r: str(r.choice_value)}.get(row.kind, lambda r: None)(row)
        entry = {"type": row.kind, "label": row.label, "name": row.name, "min": row.lo, "max": row.hi,
                 "min_open": row.lo_open, "max_open": row.hi_open, "choices": json.loads(row.choices or "null")}
        problem = check_value(entry, value)
        if problem:
            raise UserError(problem)
        out[row.name] = value
    return out


def work_root(package: str) -> str:
    """Where job folders go: the extension's user folder (Blender 4.2+ extension), else the system temp folder."""
    root = None
    path_user = getattr(bpy.utils, "extension_path_user", None)
    if path_user is not None:
        try:
            root = path_user(package, path="jobs", create=True)
        except (ValueError, KeyError, OSError):
            root = None  # a legacy add-on has no extension folder
    if not root:
        root = private_temp_root(f"genre-addon-jobs-{os.getuid() if hasattr(os, 'getuid') else 'user'}")
    return root


def _abspath(path: str) -> str:
    return os.path.normpath(bpy.path.abspath(path)) if path else ""


def _check_file(path: str, what: str) -> None:
    if not os.path.exists(path):
        raise UserError(f"{what} not found: {path}")
    if os.path.isdir(path):
        raise UserError(f"{what} is a folder, not an image file: {path}")
    if not os.access(path, os.R_OK):
        raise UserError(f"{what} is not readable: {path}")


def _image_file_on_disk(image: bpy.types.Image) -> str:
    """The file an image datablock shows, when it is an unmodified file on disk; else ''."""
    if image.source != "FILE" or image.packed_file is not None or image.is_dirty:
        return ""
    path = _abspath(image.filepath)
    return path if path and os.path.isfile(path) else ""


def _save_image_copy(image: bpy.types.Image, path: str) -> None:
    """Write an image datablock's pixels to a PNG (packed, generated or painted images), leaving the datablock as it is."""
    width, height = image.size
    if width == 0 or height == 0:
        raise UserError(f"the image '{image.name}' has no pixels (is its file missing?)")
    copy = bpy.data.images.new("genre-photo-copy", width, height, alpha=True, float_buffer=image.is_float)
    try:
        pixels = [0.0] * (width * height * 4)
        image.pixels.foreach_get(pixels)
        copy.pixels.foreach_set(pixels)
        copy.filepath_raw = path
        copy.file_format = "PNG"
        copy.save()
    finally:
        bpy.data.images.remove(copy)


def annotation_guidance(spec: JobSpec, settings) -> None:
    """Fill ``spec``'s strokes file and box from an annotation drawn over the photo in an Image Editor.

    The photo's Image datablock: the chosen image (source Image), else an
    image whose file is the photo (source File).  Nothing when no Image
    Editor shows it with an annotation, or the annotation has no strokes.
    Blender shows a file's pixels as stored, ignoring its EXIF orientation
    (3.4 and 5.0 alike), so the strokes and box are over the stored pixels:
    the request says so (``guidance_frame`` ``"stored"``) and the backend
    turns them as it turns the photo (``docs/protocol.md``).
    """
    image = settings.image if settings.source == "IMAGE" else None
    if image is None:
        for candidate in bpy.data.images:
            if candidate.source == "FILE" and _abspath(candidate.filepath) == spec.image_path:
                image = candidate
                break
    if image is None:
        return
    annotation = find_annotation(image, bpy.context.window_manager)
    if annotation is None:
        return
    width, height = image.size
    if width == 0 or height == 0:
        return
    spec.strokes_path, spec.box = guidance_from_annotation(annotation, int(width), int(height), spec.work_dir)
    spec.guidance_frame = "stored"


def require_photo(settings) -> None:
    """The first thing a reconstruction needs, asked for before anything about the backend: the photo."""
    if settings.source == "IMAGE":
        if settings.image is None:
            raise UserError("choose an image to reconstruct from (or switch the source to File)")
    else:
        path = _abspath(settings.photo_path)
        if not path:
            raise UserError("choose a photo to reconstruct from")
        _check_file(path, "photo")


def prepare_job(settings, work_base: str) -> JobSpec:
    """Check the panel's settings and fix them in a :class:`JobSpec`; :class:`UserError` when something is missing.

    ``settings`` is the scene's ``genre`` settings (or anything with the same
    attributes); ``work_base`` the folder for job folders (:func:`work_root`).
    """
    require_photo(settings)
    mask = _abspath(settings.mask_path)
    if mask:
        _check_file(mask, "mask")
    overrides = row_overrides(getattr(settings, "options", ()))  # (before any folder is made)
    work_dir = ""
    try:
        if settings.source == "IMAGE":
            image = settings.image
            name = os.path.splitext(image.name)[0] or image.name
            path = _image_file_on_disk(image)
            work_dir = tempfile.mkdtemp(prefix="job-", dir=work_base)
            if not path:
                path = os.path.join(work_dir, "photo.png")
                _save_image_copy(image, path)
            spec = JobSpec(name=name, image_path=path, work_dir=work_dir, photo_image=image.name)
        else:
            path = _abspath(settings.photo_path)
            work_dir = tempfile.mkdtemp(prefix="job-", dir=work_base)
            name = os.path.splitext(os.path.basename(path))[0] or "GenRe"
            spec = JobSpec(name=name, image_path=path, work_dir=work_dir, photo_file=path)
    except BaseException:
        if work_dir:
            shutil.rmtree(work_dir, ignore_errors=True)
        raise
    spec.mask_path = mask
    if not mask and getattr(settings, "use_annotation", False):
        try:
            annotation_guidance(spec, settings)
        except BaseException:
            shutil.rmtree(work_dir, ignore_errors=True)
            raise
    spec.quality = next((name for ident, _, _, name in QUALITIES if ident == getattr(settings, "quality", "BEST")), "best")
    spec.options = overrides
    spec.smoothing = int(settings.smoothing)
    spec.target_faces = int(settings.target_faces)
    spec.add_camera = bool(settings.add_camera)
    spec.colour_from_photo = bool(getattr(settings, "colour_from_photo", False))
    return spec


# the image the panel shows after a run: the mask the backend used, over the photo (Job.load_mask_overlay)
MASK_IMAGE = "GenRe mask"


@dataclass
class JobLimits:
    startup_timeout: float = 120.0
    timeout: float = 600.0
    cancel_grace: float = 20.0


@dataclass
class Job:
    """A reconstruction in flight: ``tick()`` until ``finished``, then ``apply()`` (when ``state == 'done'``), then ``cleanup()``."""

    spec: JobSpec
    manager: BackendManager
    argv: list[str]
    limits: JobLimits = field(default_factory=JobLimits)
    request: Request | None = None
    objects: tuple = ()  # what apply() created: (mesh object, camera object or None)

    def __post_init__(self):
        self.request = self.manager.request(
            self.argv, "reconstruct", self.spec.request_payload(),
            startup_timeout=self.limits.startup_timeout, timeout=self.limits.timeout, cancel_grace=self.limits.cancel_grace,
        )

    # progress, as the panel shows it
    @property
    def state(self) -> str:
        return self.request.state

    @property
    def finished(self) -> bool:
        return self.request.finished

    @property
    def fraction(self) -> float:
        return self.request.fraction

    @property
    def stage_label(self) -> str:
        return STAGE_LABELS.get(self.request.stage, self.request.stage)

    @property
    def error(self) -> str:
        return self.request.error

    def tick(self, now: float | None = None) -> str:
        return self.request.tick(now)

    def cancel(self) -> None:
        self.request.cancel()

    def apply(self, scene, cursor_location=(0.0, 0.0, 0.0)):
        """Add the result to ``scene`` (main thread only); returns (object, camera or None).

        All or nothing: on any failure everything made so far is removed and
        :class:`UserError` says why.
        """
        if self.state != "done" or self.request.result is None:
            raise RuntimeError("Job.apply() needs a finished, successful job")
        made: list = []
        try:
            self.objects = _add_result(scene, self.spec, self.request.result, cursor_location, made)
        except (MeshFileError, ValueError, RuntimeError, OSError) as exc:
            _remove(made)
            reason = str(exc).strip().removeprefix("Error: ")  # bpy's RuntimeError texts start with "Error: "
            raise UserError(f"could not add the result to the scene: {reason}") from None
        except BaseException:
            _remove(made)
            raise
        return self.objects

    @property
    def mask_warning(self) -> str:
        """The result's ``mask_warning`` (the backend found the mask doubtful), or ''."""
        warning = getattr(self.request.result, "mask_warning", None)
        return warning if isinstance(warning, str) else ""

    def result_line(self) -> str:
        """'<name>: 1,234 vertices, 2,460 faces in 4.2 s' for the panel."""
        res = self.request.result or Result()
        obj = self.objects[0] if self.objects else None
        faces = res.faces
        line = f"{self.spec.name}: {res.vertices:,} vertices, {faces:,} faces"
        if isinstance(res.mask_source, str):
            line += f", mask: {res.mask_source}"
        if isinstance(res.primitive, str):
            line += f", a fitted {res.primitive}"
        if obj is not None and self.spec.target_faces and faces > self.spec.target_faces:
            line += f" (decimated to ~{self.spec.target_faces:,})"
        return f"{line} in {self.request.elapsed:.1f} s"

    def load_mask_overlay(self):
        """The backend's picture of the mask it used over the photo (``mask_overlay.png``) as the packed image
        :data:`MASK_IMAGE`, which the panel shows (any older one replaced); None when the backend wrote none."""
        old = bpy.data.images.get(MASK_IMAGE)
        if old is not None:
            bpy.data.images.remove(old)
        folder = ((self.request.payload or {}).get("options") or {}).get("save_intermediates")
        path = os.path.join(folder, "mask_overlay.png") if isinstance(folder, str) else ""
        if not path or not os.path.isfile(path):
            return None
        image = bpy.data.images.load(path, check_existing=False)
        image.name = MASK_IMAGE
        image.pack()  # the job's folder is removed next
        if hasattr(image, "preview_ensure"):
            image.preview_ensure()  # the panel draws its preview icon
        return image

    def cleanup(self) -> None:
        """Remove the job's temporary folder (the mesh file and any photo copy)."""
        shutil.rmtree(self.spec.work_dir, ignore_errors=True)


def _remove(made: list) -> None:
    """Delete datablocks created by a failed apply (objects first, then their data)."""
    for block in reversed(made):
        try:
            if isinstance(block, bpy.types.Object):
                bpy.data.objects.remove(block, do_unlink=True)
            elif isinstance(block, bpy.types.Mesh):
                bpy.data.meshes.remove(block)
            elif isinstance(block, bpy.types.Camera):
                bpy.data.cameras.remove(block)
            elif isinstance(block, bpy.types.Image):
                bpy.data.images.remove(block)
            elif isinstance(block, bpy.types.Material):
                bpy.data.materials.remove(block)
            elif isinstance(block, bpy.types.Collection):
                bpy.data.collections.remove(block)
        except ReferenceError:
            pass


def _contains(parent, coll) -> bool:
    return any(child == coll or _contains(child, coll) for child in parent.children)


def _collection(scene, made: list):
    """The scene's "GenRe" collection, created (and linked under the scene) when missing."""
    coll = bpy.data.collections.get(COLLECTION_NAME)
    if coll is None or coll.library is not None:
        coll = bpy.data.collections.new(COLLECTION_NAME)
        made.append(coll)
    if not _contains(scene.collection, coll):
        scene.collection.children.link(coll)
    return coll


def _add_result(scene, spec: JobSpec, result: Result, cursor_location, made: list):
    mesh_path = result.mesh or spec.output_path
    data = read_obj(mesh_path)
    coll = _collection(scene, made)

    mesh = bpy.data.meshes.new(spec.name)
    made.append(mesh)
    mesh.from_pydata(to_blender_frame(data.vertices), [], data.faces)
    if spec.colour_from_photo and data.face_uvs is not None:
        texture = _texture_file(result, mesh_path)
        _add_photo_material(mesh, data, texture, made)
    mesh.update()
    if hasattr(mesh, "shade_smooth"):  # Blender 4.1+
        mesh.shade_smooth()
    else:
        mesh.polygons.foreach_set("use_smooth", [True] * len(mesh.polygons))
    obj = bpy.data.objects.new(spec.name, mesh)
    made.append(obj)
    coll.objects.link(obj)
    obj.location = Vector(cursor_location)

    if spec.smoothing > 0:
        mod = obj.modifiers.new("GenRe smoothing", "SMOOTH")
        mod.factor = 0.5
        mod.iterations = spec.smoothing
    if spec.target_faces > 0 and len(mesh.polygons) > spec.target_faces:
        mod = obj.modifiers.new("GenRe decimate", "DECIMATE")
        mod.decimate_type = "COLLAPSE"
        mod.ratio = spec.target_faces / len(mesh.polygons)

    cam_obj = None
    if spec.add_camera and isinstance(result.camera, dict):
        cam_obj = _add_camera(scene, spec, result.camera, obj, coll, made)
    return obj, cam_obj


def _texture_file(result: Result, mesh_path: str) -> str:
    """The texture image the backend wrote beside an OBJ (listed in the result's ``files``)."""
    for path in result.files or ():
        if isinstance(path, str) and path.lower().endswith(".png"):
            return path
    return os.path.splitext(mesh_path)[0] + "_texture.png"


def _add_photo_material(mesh, data, texture_path: str, made: list) -> None:
    """UVs from the OBJ and a material showing the photo's texture through them (image packed into the .blend,
    since the job's folder is removed afterwards)."""
    if not os.path.isfile(texture_path):
        raise MeshFileError(f"the backend's texture {texture_path} is missing")
    layer = mesh.uv_layers.new(name="Photo")
    flat = [c for face in data.face_uvs for i in face for c in data.uvs[i]]
    layer.data.foreach_set("uv", flat)
    image = bpy.data.images.load(texture_path)
    made.append(image)
    image.name = f"{mesh.name} photo"
    image.pack()
    mat = bpy.data.materials.new(f"{mesh.name} photo")
    made.append(mat)
    if mat.node_tree is None:  # Blender < 5 makes materials without nodes
        mat.use_nodes = True
    nodes = mat.node_tree.nodes
    bsdf = nodes.get("Principled BSDF")
    node = nodes.new("ShaderNodeTexImage")
    node.image = image
    node.extension = "EXTEND"
    node.location = (-320.0, 260.0)
    mat.node_tree.links.new(node.outputs["Color"], bsdf.inputs["Base Color"])
    nodes.active = node  # what Workbench and Texture Paint show
    rough = bsdf.inputs.get("Roughness")
    if rough is not None:
        rough.default_value = 0.8
    mesh.materials.append(mat)


def _photo_image(spec: JobSpec, made: list):
    if spec.photo_image:
        image = bpy.data.images.get(spec.photo_image)
        if image is not None:
            return image
    path = spec.photo_file or spec.image_path
    before = set(bpy.data.images)
    image = bpy.data.images.load(path, check_existing=True)
    if image not in before:
        made.append(image)
    return image


def _upright_copy(image, orientation: int, made: list):
    """A packed copy of ``image`` turned as its file's EXIF ``orientation`` says (Blender shows the stored pixels).

    Plain Python (``array``; Debian's Blender has no numpy)."""
    from array import array

    width, height = image.size
    channels = image.channels
    pixels = array("f", bytes(4 * width * height * channels))
    image.pixels.foreach_get(pixels)
    up, up_w, up_h = upright_pixels(pixels, width, height, channels, orientation)
    copy = bpy.data.images.new(f"{image.name} (upright)", up_w, up_h, alpha=channels == 4, float_buffer=image.is_float)
    made.append(copy)
    if copy.colorspace_settings.name != image.colorspace_settings.name:  # (before the pixels: it regenerates the image)
        copy.colorspace_settings.name = image.colorspace_settings.name
    rgba = array("f", [1.0]) * (up_w * up_h * 4)  # a new image holds RGBA; grey (1 or 2 channels) fills R, G, B
    for k in range(3):
        rgba[k::4] = up[k::channels] if channels >= 3 else up[0::channels]
    if channels in (2, 4):
        rgba[3::4] = up[channels - 1::channels]
    copy.pixels.foreach_set(rgba)
    copy.pack()  # the job's files go when it ends; the .blend keeps the turned photo
    return copy


def _add_camera(scene, spec: JobSpec, camera: dict, parent, coll, made: list):
    image = _photo_image(spec, made)
    orientation = camera.get("exif_orientation", 1)
    if orientation != 1:  # (upright_pixels refuses anything but a tag 1-8)
        # the backend read the file upright; Blender shows it as stored: give the camera the photo as the mesh sees it
        stored = image
        image = _upright_copy(stored, orientation, made)
        if stored in made:  # loaded for this job only: the turned copy replaces it
            made.remove(stored)
            bpy.data.images.remove(stored)
    width, height = image.size
    if width == 0 or height == 0:
        raise ValueError(f"cannot read the photo's size from {spec.photo_file or spec.photo_image}")
    setup = camera_setup(camera, (width, height))
    cam = bpy.data.cameras.new(f"{parent.name} camera")
    made.append(cam)
    cam.lens = setup.lens_mm
    cam.sensor_fit = "AUTO"
    cam.sensor_width = setup.sensor_mm
    cam.sensor_height = setup.sensor_mm
    cam.shift_x = setup.shift_x
    cam.shift_y = setup.shift_y
    cam.show_background_images = True
    bg = cam.background_images.new()
    bg.image = image
    bg.alpha = 0.6
    bg.frame_method = "FIT"
    cam_obj = bpy.data.objects.new(f"{parent.name} camera", cam)
    made.append(cam_obj)
    coll.objects.link(cam_obj)
    # The camera is the mesh's child: moving, turning or scaling the mesh keeps them lined up.
    cam_obj.parent = parent
    cam_obj.matrix_parent_inverse = Matrix.Identity(4)
    cam_obj.matrix_basis = Matrix.Translation(Vector(setup.location)) @ Matrix(VIEW_TO_BLENDER_FRONT).to_4x4()
    if scene.camera is None:
        scene.camera = cam_obj
    scene.render.resolution_x, scene.render.resolution_y = setup.resolution
    return cam_obj
