"""Procedurally generated regular shapes: primitives, CSG solids, extrusions,
solids of revolution and furniture-like assemblies (no package, CC0).

Why: the product model must reconstruct regular shapes well (boxes, cylinders,
turned and extruded parts, simple furniture), and the Debian CAD models hold
few clean ones.  The shapes are drawn from a seeded :class:`numpy.random.Generator`
(:data:`SEED`), so :func:`enumerate_shapes` returns the same records, and every
``load()`` the same vertex arrays, on every call and machine.

Kinds (each is also the shape's ``class_hint``; none is a class of the
research protocol, so the seen/unseen splits do not change: these shapes land
in the ``unassigned`` split):

``primitive``
    cube, box, cylinder, cone, torus, sphere (the first one round, the
    others ellipsoids: a sphere scaled per axis), equal numbers of each.
``csg``
    unions and differences of 2-3 primitives through ``trimesh.boolean`` with
    the ``manifold3d`` engine: a plate with holes, a box with a pocket or a
    step, a tube or cup, a sphere with flat cuts, a box with a boss, a
    dumbbell, a cross of boxes, a bracket with a hole.
``extrusion``
    L, U, T, star, rounded-rectangle and random star-shaped polygon with a
    hole profiles (shapely, triangulated by ``manifold3d``), extruded along Z.
``lathe``
    vase, bottle, bowl and goblet profiles revolved about Z
    (``trimesh.creation.revolve``, :data:`LATHE_SECTIONS` sections).
``assembly``
    chair, stool, table, shelf, cabinet and bench built from boxes and
    cylinders (parts overlap and are not merged; each part is watertight).

Frame: every generator builds its shape in its own frame, +Z up; the record's
``rotation`` carries the pose.  Primitives, CSG solids, extrusions and lathes
get a uniformly random rotation (a random unit quaternion); assemblies are
built standing (+Z up, front toward −Y, a chair's back and a cabinet's back
toward +Y) and get a random heading about Z only.

Sizes: no nominal bounding-box side of a shape (in its own frame) is thinner
than :data:`MIN_SIDE` times the box's diagonal, far above the corpus junk rule
(``corpus.MIN_THICKNESS``).  Tessellation: cylinders and cones
:data:`CYLINDER_SECTIONS` segments, tori :data:`TORUS_SECTIONS`, spheres an
icosphere of :data:`SPHERE_SUBDIVISIONS` subdivisions (1,280 triangles).

The parameters that define a shape (all numbers rounded to :data:`DECIMALS`
decimals before use) are kept in ``extra`` (``kind``, ``subkind``, ``size``,
``params``, ``pose``, ``seed``) and ``load`` rebuilds the mesh from them with
:func:`build_parts`: records hold no meshes.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import trimesh

from . import ShapeRecord

# shapely and manifold3d are imported where used: importing the corpus (which lists this source)
# does not need them; enumerating (profile checks) and loading the shapes do.

__all__ = [
    "PACKAGES",
    "SEED",
    "COUNTS",
    "CLASSES",
    "SUBKINDS",
    "CYLINDER_SECTIONS",
    "TORUS_SECTIONS",
    "SPHERE_SUBDIVISIONS",
    "LATHE_SECTIONS",
    "MIN_SIDE",
    "DECIMALS",
    "enumerate_shapes",
    "build_parts",
    "primitive_mesh",
    "primitive_size",
    "quaternion_matrix",
]

PACKAGES: tuple[str, ...] = ()

SEED = 20_260_517
# Shapes per kind (about 400 in all); the kinds are the class hints.
COUNTS: dict[str, int] = {"primitive": 120, "csg": 80, "extrusion": 60, "lathe": 60, "assembly": 80}
CLASSES: tuple[str, ...] = tuple(COUNTS)
# Sub-kinds, assigned round-robin (shape i of a kind is SUBKINDS[kind][i % len]).
SUBKINDS: dict[str, tuple[str, ...]] = {
    "primitive": ("cube", "box", "cylinder", "cone", "torus", "sphere"),
    "csg": ("plate_with_holes", "box_with_pocket", "tube", "cut_sphere", "box_with_boss", "dumbbell", "cross",
            "bracket"),
    "extrusion": ("l", "u", "t", "star", "rounded_rectangle", "polygon_with_hole"),
    "lathe": ("vase", "bottle", "bowl", "goblet"),
    "assembly": ("chair", "stool", "table", "shelf", "cabinet", "bench"),
}
CYLINDER_SECTIONS = 48
TORUS_SECTIONS = (48, 24)  # (around the axis, around the tube)
SPHERE_SUBDIVISIONS = 3
LATHE_SECTIONS = 48
ROUNDED_CORNER_SEGMENTS = 8  # straight segments per rounded corner of a rounded rectangle
MIN_SIDE = 0.08  # thinnest nominal bbox side / bbox diagonal, in the shape's own frame
DECIMALS = 4  # every generating number is rounded to this many decimals before use
GENERATOR_VERSION = 1

_CREATOR = "GenRe project (generated)"
_LICENCE = "CC0"
_MAX_TRIES = 200


# ----------------------------------------------------------------------------- small helpers


def _r(x: float) -> float:
    """``x`` rounded to :data:`DECIMALS` decimals, as a plain float (0.0, never -0.0)."""
    return round(float(x), DECIMALS) + 0.0


def _rv(values) -> list[float]:
    return [_r(v) for v in values]


def _thick_enough(size) -> bool:
    size = np.asarray(size, dtype=np.float64)
    return bool(size.min() >= MIN_SIDE * np.linalg.norm(size))


def quaternion_matrix(q) -> np.ndarray:
    """Rotation matrix of a quaternion.

    Args:
        q: ``(4,) float`` quaternion ``(w, x, y, z)``, any non-zero norm (it
            is normalised).

    Returns:
        ``(3, 3) float`` proper rotation.
    """
    q = np.asarray(q, dtype=np.float64)
    if q.shape != (4,) or not np.all(np.isfinite(q)):
        raise ValueError(f"quaternion must be 4 finite numbers, got {q!r}")
    norm = float(np.linalg.norm(q))
    if norm < 1e-9:
        raise ValueError("quaternion must not be zero")
    w, x, y, z = q / norm
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _heading_matrix(degrees: float) -> np.ndarray:
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------- primitives (specs)

# Exact axis permutations taking the cylinder's +Z axis onto X or Y (proper rotations).
_AXIS_TO = {
    "z": np.eye(3),
    "x": np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]),
    "y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
}


def _positive(spec: dict, key: str, n: int | None = None):
    if key not in spec:
        raise ValueError(f"{spec.get('type')} spec needs {key!r}: {spec}")
    value = np.asarray(spec[key], dtype=np.float64)
    if n is None:
        ok = value.shape == () and np.isfinite(value) and value > 0
    else:
        ok = value.shape == (n,) and np.all(np.isfinite(value)) and np.all(value > 0)
    if not ok:
        raise ValueError(f"{spec.get('type')} {key!r} must be {n or 1} positive finite number(s), got {spec[key]!r}")
    return float(value) if n is None else value


def primitive_size(spec: dict) -> np.ndarray:
    """Nominal axis-aligned bounding-box extents of a primitive spec.

    Nominal: the ideal shape's box (a cylinder's ``2r``), not its
    tessellation's (an icosphere's is up to ~1 % smaller).

    Args:
        spec: a primitive spec (see :func:`primitive_mesh`).

    Returns:
        ``(3,) float`` extents along X, Y, Z.
    """
    kind = spec.get("type")
    if kind == "box":
        ext = _positive(spec, "extents", 3)
        yaw = math.radians(float(spec.get("yaw", 0.0)))
        c, s = abs(math.cos(yaw)), abs(math.sin(yaw))
        return np.array([c * ext[0] + s * ext[1], s * ext[0] + c * ext[1], ext[2]])
    if kind == "cylinder":
        r, h = _positive(spec, "radius"), _positive(spec, "height")
        axis = spec.get("axis", "z")
        if axis not in _AXIS_TO:
            raise ValueError(f"cylinder axis must be x, y or z, got {axis!r}")
        return np.abs(_AXIS_TO[axis]) @ np.array([2 * r, 2 * r, h])
    if kind == "cone":
        r, h = _positive(spec, "radius"), _positive(spec, "height")
        return np.array([2 * r, 2 * r, h])
    if kind == "torus":
        big, small = _positive(spec, "major_radius"), _positive(spec, "minor_radius")
        return np.array([2 * (big + small), 2 * (big + small), 2 * small])
    if kind == "sphere":
        return 2.0 * _positive(spec, "radii", 3)
    raise ValueError(f"unknown primitive type {kind!r}")


def _spec_bounds(spec: dict) -> np.ndarray:
    centre = np.asarray(spec.get("centre", (0.0, 0.0, 0.0)), dtype=np.float64)
    half = primitive_size(spec) / 2.0
    return np.stack([centre - half, centre + half])


def primitive_mesh(spec: dict) -> trimesh.Trimesh:
    """The watertight mesh of one primitive spec.

    A spec is a JSON-able dict with ``type`` and optional ``centre``
    (``(3,)``, the centre of its bounding box, default the origin):

    - ``{"type": "box", "extents": (3,), "yaw": degrees about Z (optional)}``
    - ``{"type": "cylinder", "radius", "height", "axis": "x"|"y"|"z"}``
      (:data:`CYLINDER_SECTIONS` segments)
    - ``{"type": "cone", "radius", "height"}`` (apex toward +Z)
    - ``{"type": "torus", "major_radius", "minor_radius"}`` (axis Z,
      :data:`TORUS_SECTIONS`; ``minor_radius < major_radius``)
    - ``{"type": "sphere", "radii": (3,)}`` (an icosphere of
      :data:`SPHERE_SUBDIVISIONS` subdivisions scaled per axis)

    Args:
        spec: the primitive, validated up front (``ValueError`` on unknown
            types, missing keys, non-positive or non-finite sizes).

    Returns:
        A new :class:`trimesh.Trimesh` with outward normals.
    """
    if not isinstance(spec, dict):
        raise ValueError(f"a primitive spec is a dict, got {type(spec).__name__}")
    kind = spec.get("type")
    centre = np.asarray(spec.get("centre", (0.0, 0.0, 0.0)), dtype=np.float64)
    if centre.shape != (3,) or not np.all(np.isfinite(centre)):
        raise ValueError(f"centre must be 3 finite numbers, got {spec.get('centre')!r}")
    primitive_size(spec)  # validates the sizes
    if kind == "box":
        mesh = trimesh.creation.box(extents=_positive(spec, "extents", 3))
        yaw = float(spec.get("yaw", 0.0))
        if yaw:
            rot = np.eye(4)
            rot[:3, :3] = _heading_matrix(yaw)
            mesh.apply_transform(rot)
    elif kind == "cylinder":
        mesh = trimesh.creation.cylinder(radius=_positive(spec, "radius"), height=_positive(spec, "height"),
                                         sections=CYLINDER_SECTIONS)
        axis = spec.get("axis", "z")
        if axis != "z":
            rot = np.eye(4)
            rot[:3, :3] = _AXIS_TO[axis]
            mesh.apply_transform(rot)
    elif kind == "cone":
        height = _positive(spec, "height")
        mesh = trimesh.creation.cone(radius=_positive(spec, "radius"), height=height, sections=CYLINDER_SECTIONS)
        mesh.apply_translation((0.0, 0.0, -height / 2.0))
    elif kind == "torus":
        big, small = _positive(spec, "major_radius"), _positive(spec, "minor_radius")
        if small >= big:
            raise ValueError(f"torus minor_radius {small} must be smaller than major_radius {big}")
        mesh = trimesh.creation.torus(major_radius=big, minor_radius=small,
                                      major_sections=TORUS_SECTIONS[0], minor_sections=TORUS_SECTIONS[1])
    elif kind == "sphere":
        mesh = trimesh.creation.icosphere(subdivisions=SPHERE_SUBDIVISIONS, radius=1.0)
        mesh.apply_transform(np.diag(np.append(_positive(spec, "radii", 3), 1.0)))
    else:  # pragma: no cover - primitive_size raised already
        raise ValueError(f"unknown primitive type {kind!r}")
    if np.any(centre):
        mesh.apply_translation(centre)
    return mesh


def _box(extents, centre=(0.0, 0.0, 0.0), yaw: float = 0.0) -> dict:
    spec = {"type": "box", "extents": _rv(extents), "centre": _rv(centre)}
    if yaw:
        spec["yaw"] = _r(yaw)
    return spec


def _cyl(radius, height, centre=(0.0, 0.0, 0.0), axis: str = "z") -> dict:
    return {"type": "cylinder", "radius": _r(radius), "height": _r(height), "axis": axis, "centre": _rv(centre)}


def _sphere(radii, centre=(0.0, 0.0, 0.0)) -> dict:
    return {"type": "sphere", "radii": _rv(radii), "centre": _rv(centre)}


# ----------------------------------------------------------------------------- building


def _remove_slivers(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """``mesh`` through a ``manifold3d.Manifold`` and its ``simplify`` at the
    manifold's own (float32-precision) tolerance.

    A boolean's output can hold needle triangles where two curved surfaces
    cross near a vertex (a dumbbell's balls on its bar: heights down to 1e-7
    of the diagonal, degenerate once stored as float32 in a GLB).  Collapsing
    the edges shorter than the tolerance removes them; the volume changes by
    less than 1e-8 of itself.
    """
    import manifold3d

    solid = manifold3d.Manifold(manifold3d.Mesh(np.asarray(mesh.vertices, dtype=np.float32),
                                                np.asarray(mesh.faces, dtype=np.uint32)))
    out = solid.simplify(0.0).to_mesh()
    return trimesh.Trimesh(np.asarray(out.vert_properties, dtype=np.float64)[:, :3],
                           np.asarray(out.tri_verts, dtype=np.int64))


def _csg_mesh(steps: list) -> trimesh.Trimesh:
    if not steps or steps[0][0] != "base":
        raise ValueError("csg steps must start with ['base', spec]")
    result = primitive_mesh(steps[0][1])
    for op, spec in steps[1:]:
        tool = primitive_mesh(spec)
        if op == "union":
            result = trimesh.boolean.union([result, tool], engine="manifold")
        elif op == "difference":
            result = trimesh.boolean.difference([result, tool], engine="manifold")
        else:
            raise ValueError(f"csg operation must be 'union' or 'difference', got {op!r}")
    return _remove_slivers(result)


def _polygon(shell, holes=()):
    from shapely.geometry import Polygon
    from shapely.geometry.polygon import orient

    poly = Polygon(shell, [h for h in holes])
    if not poly.is_valid or poly.area <= 0:
        raise ValueError("extrusion profile is not a valid polygon")
    return orient(poly, 1.0)


def _extrusion_mesh(shell, holes, depth: float) -> trimesh.Trimesh:
    depth = float(depth)
    if not (np.isfinite(depth) and depth > 0):
        raise ValueError(f"extrusion depth must be positive, got {depth!r}")
    poly = _polygon(shell, holes)
    vertices, faces = trimesh.creation.triangulate_polygon(poly, engine="manifold")
    mesh = trimesh.creation.extrude_triangulation(vertices, faces, depth)
    mesh.apply_translation((0.0, 0.0, -depth / 2.0))
    return mesh


def _profile_polygon(profile):
    """The closed region (a shapely ``Polygon``) a lathe profile bounds with the Z axis."""
    from shapely.geometry import Polygon

    return Polygon(np.asarray(profile, dtype=np.float64))


def _lathe_mesh(profile) -> trimesh.Trimesh:
    profile = np.asarray(profile, dtype=np.float64)
    if profile.ndim != 2 or profile.shape[1] != 2 or len(profile) < 3:
        raise ValueError(f"lathe profile must be (n >= 3, 2) (radius, z) points, got shape {profile.shape}")
    if profile[0, 0] != 0.0 or profile[-1, 0] != 0.0 or np.any(profile[1:-1, 0] <= 0):
        raise ValueError("lathe profile must start and end on the axis (radius 0) and stay off it in between")
    if not _profile_polygon(profile).is_valid:
        raise ValueError("lathe profile crosses itself")
    mesh = trimesh.creation.revolve(profile, sections=LATHE_SECTIONS)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def build_parts(kind: str, params: dict) -> list[trimesh.Trimesh]:
    """Rebuild a shape's meshes from its recorded parameters.

    Args:
        kind: one of :data:`CLASSES`.
        params: ``extra["params"]`` of the record (see the generators):
            ``primitive`` a primitive spec; ``csg`` ``{"steps": [["base",
            spec], [op, spec], ...]}``; ``extrusion`` ``{"shell": (n, 2),
            "holes": [(m, 2), ...], "depth"}``; ``lathe`` ``{"profile": (n, 2)
            (radius, z)}``; ``assembly`` ``{"parts": [spec, ...]}``.

    Returns:
        ``list[trimesh.Trimesh]`` in the shape's own frame: one watertight
        mesh, or one per part for an assembly.
    """
    if kind == "primitive":
        return [primitive_mesh(params)]
    if kind == "csg":
        return [_csg_mesh(params["steps"])]
    if kind == "extrusion":
        return [_extrusion_mesh(params["shell"], params.get("holes", []), params["depth"])]
    if kind == "lathe":
        return [_lathe_mesh(params["profile"])]
    if kind == "assembly":
        parts = params.get("parts") or []
        if not parts:
            raise ValueError("an assembly needs at least one part")
        return [primitive_mesh(p) for p in parts]
    raise ValueError(f"unknown procedural kind {kind!r}; known: {', '.join(CLASSES)}")


# ----------------------------------------------------------------------------- generators: primitives


def _draw_primitive(sub: str, index: int, rng: np.random.Generator) -> dict:
    u = rng.uniform
    for _ in range(_MAX_TRIES):
        if sub == "cube":
            s = u(0.2, 1.0)
            spec = _box((s, s, s))
        elif sub == "box":
            spec = _box(u(0.15, 1.0, size=3))
        elif sub in ("cylinder", "cone"):
            spec = {"type": sub, "radius": _r(u(0.1, 0.6)), "height": _r(u(0.15, 1.5))}
            if sub == "cylinder":
                spec["axis"] = "z"
        elif sub == "torus":
            big = u(0.3, 1.0)
            spec = {"type": "torus", "major_radius": _r(big), "minor_radius": _r(big * u(0.15, 0.6))}
        elif sub == "sphere":
            r = u(0.2, 1.0)
            # the first "sphere" is round, the others ellipsoids: round ones differ only by a pose
            # that cannot be seen, and the corpus would drop them as near-duplicates
            radii = (r, r, r) if index == 0 else (r, r * u(0.55, 1.0), r * u(0.55, 1.0))
            spec = _sphere(radii)
        else:
            raise ValueError(f"unknown primitive {sub!r}")
        spec.setdefault("centre", [0.0, 0.0, 0.0])
        if _thick_enough(primitive_size(spec)):
            return {"params": spec, "size": _rv(primitive_size(spec))}
    raise RuntimeError(f"no thick enough {sub} in {_MAX_TRIES} draws")


# ----------------------------------------------------------------------------- generators: csg


def _csg_plate_with_holes(rng: np.random.Generator) -> tuple[list, dict, tuple | list]:
    """One draw of the CSG shape ``plate_with_holes``: (its steps, what it records, its size)."""
    u = rng.uniform
    a, b, c = u(0.4, 1.0), u(0.4, 1.0), u(0.15, 0.5)
    n = int(rng.integers(1, 3))
    through = bool(rng.random() < 0.6)
    if through:
        z0, z1 = -0.75 * c, 0.75 * c
    else:
        depth = u(0.4, 0.8) * c
        z0, z1 = c / 2 - depth, 0.75 * c
    steps = [["base", _box((a, b, c))]]
    if n == 1:
        r = u(0.15, 0.35) * min(a, b)
        room_x, room_y = max(0.0, a / 2 - r - 0.12 * a), max(0.0, b / 2 - r - 0.12 * b)
        centres = [(u(-1, 1) * room_x, u(-1, 1) * room_y)]
    else:
        r = u(0.6, 1.0) * min(0.18 * a, 0.35 * b)
        centres = [(-a / 4, 0.0), (a / 4, 0.0)]
    for cx, cy in centres:
        steps.append(["difference", _cyl(r, z1 - z0, (cx, cy, (z0 + z1) / 2))])
    info = {"holes": n, "through": through, "base": _rv((a, b, c))}
    size = (a, b, c)
    return steps, info, size


def _csg_box_with_pocket(rng: np.random.Generator) -> tuple[list, dict, tuple | list]:
    """One draw of the CSG shape ``box_with_pocket``: (its steps, what it records, its size)."""
    u = rng.uniform
    a, b, c = u(0.3, 1.0), u(0.3, 1.0), u(0.2, 0.8)
    variant = "pocket" if rng.random() < 0.5 else "step"
    if variant == "pocket":
        wa, wb = u(0.08, 0.2) * a, u(0.08, 0.2) * b
        depth = u(0.3, 0.8) * c
        tool = _box((a - 2 * wa, b - 2 * wb, depth + 0.25 * c),
                    (0.0, 0.0, c / 2 - depth + (depth + 0.25 * c) / 2))
    else:
        la, depth = u(0.3, 0.6) * a, u(0.3, 0.7) * c
        tool = _box((la + 0.25 * a, 1.5 * b, depth + 0.25 * c),
                    (a / 2 - la + (la + 0.25 * a) / 2, 0.0, c / 2 - depth + (depth + 0.25 * c) / 2))
    steps = [["base", _box((a, b, c))], ["difference", tool]]
    info = {"variant": variant}
    size = (a, b, c)
    return steps, info, size


def _csg_tube(rng: np.random.Generator) -> tuple[list, dict, tuple | list]:
    """One draw of the CSG shape ``tube``: (its steps, what it records, its size)."""
    u = rng.uniform
    big, h = u(0.15, 0.6), u(0.2, 1.2)
    small = big * u(0.4, 0.8)
    through = bool(rng.random() < 0.6)
    if through:
        tool = _cyl(small, 1.5 * h)
    else:
        depth = u(0.5, 0.9) * h
        tool = _cyl(small, depth + 0.25 * h, (0.0, 0.0, h / 2 - depth + (depth + 0.25 * h) / 2))
    steps = [["base", _cyl(big, h)], ["difference", tool]]
    info = {"through": through}
    size = (2 * big, 2 * big, h)
    return steps, info, size


def _csg_cut_sphere(rng: np.random.Generator) -> tuple[list, dict, tuple | list]:
    """One draw of the CSG shape ``cut_sphere``: (its steps, what it records, its size)."""
    u = rng.uniform
    r = u(0.3, 0.8)
    top = u(-0.3, 0.6) * r
    steps = [["base", _sphere((r, r, r))], ["difference", _box((3 * r, 3 * r, 2 * r), (0.0, 0.0, top + r))]]
    bottom = -r
    if rng.random() < 0.5:
        bottom = -u(0.3, 0.8) * r
        steps.append(["difference", _box((3 * r, 3 * r, 2 * r), (0.0, 0.0, bottom - r))])
    info = {"cut_top": _r(top), "cut_bottom": _r(bottom)}
    width = 2 * r if top >= 0 else 2 * math.sqrt(r * r - top * top)  # the equator may be cut away
    size = (width, width, top - bottom)
    return steps, info, size


def _csg_box_with_boss(rng: np.random.Generator) -> tuple[list, dict, tuple | list]:
    """One draw of the CSG shape ``box_with_boss``: (its steps, what it records, its size)."""
    u = rng.uniform
    a, b, c = u(0.3, 1.0), u(0.3, 1.0), u(0.15, 0.6)
    r = u(0.15, 0.4) * min(a, b)
    hb = u(0.2, 0.8) * max(a, b)
    z0 = c / 2 - 0.3 * c
    steps = [["base", _box((a, b, c))], ["union", _cyl(r, c / 2 + hb - z0, (0.0, 0.0, (z0 + c / 2 + hb) / 2))]]
    bored = bool(rng.random() < 0.5)
    if bored:
        steps.append(["difference", _cyl(r * u(0.35, 0.7), 2 * (c + hb), (0.0, 0.0, 0.0))])
    info = {"bored": bored}
    size = (a, b, c + hb)
    return steps, info, size


def _csg_dumbbell(rng: np.random.Generator) -> tuple[list, dict, tuple | list]:
    """One draw of the CSG shape ``dumbbell``: (its steps, what it records, its size)."""
    u = rng.uniform
    info: dict = {}
    r, length = u(0.05, 0.2), u(0.5, 1.2)
    ball = r * u(1.3, 2.2)
    steps = [["base", _cyl(r, length)],
             ["union", _sphere((ball, ball, ball), (0.0, 0.0, length / 2))],
             ["union", _sphere((ball, ball, ball), (0.0, 0.0, -length / 2))]]
    size = (2 * ball, 2 * ball, length + 2 * ball)
    return steps, info, size


def _csg_cross(rng: np.random.Generator) -> tuple[list, dict, tuple | list]:
    """One draw of the CSG shape ``cross``: (its steps, what it records, its size)."""
    u = rng.uniform
    l1, l2 = u(0.5, 1.0), u(0.5, 1.0)
    w1 = u(0.1, 0.3)
    w2 = w1 * (u(0.6, 0.85) if rng.random() < 0.5 else u(1.15, 1.5))
    h1 = u(0.1, 0.3)
    h2 = h1 * u(0.55, 0.85)
    steps = [["base", _box((l1, w1, h1))], ["union", _box((w2, l2, h2))]]
    size = [l1, l2, h1]
    if rng.random() < 0.5:
        w3 = min(w1, w2) * u(0.5, 0.8)
        l3 = u(0.5, 1.0)
        steps.append(["union", _box((w3, w3 * u(0.8, 0.95), l3))])
        size[2] = max(h1, l3)
    info = {"arms": len(steps)}
    return steps, info, size


def _csg_bracket(rng: np.random.Generator) -> tuple[list, dict, tuple | list]:
    """One draw of the CSG shape ``bracket``: (its steps, what it records, its size)."""
    u = rng.uniform
    info: dict = {}
    a, b, t1 = u(0.4, 1.0), u(0.25, 0.7), u(0.06, 0.2)
    t2, h = u(0.06, 0.2), u(0.3, 0.9)
    b2 = b * u(0.6, 0.9)
    x0, x1 = a / 2 - 0.7 * t2, a / 2 + 0.3 * t2
    steps = [["base", _box((a, b, t1))],
             ["union", _box((t2, b2, h), ((x0 + x1) / 2, 0.0, h / 2))]]
    free = a - 0.7 * t2  # plate length left of the upright
    r = u(0.15, 0.3) * min(free, b)
    steps.append(["difference", _cyl(r, 3 * t1, (-a / 2 + free / 2, 0.0, 0.0))])
    size = (x1 + a / 2, b, h + t1 / 2)
    return steps, info, size


_CSG_DRAWERS = {
    "plate_with_holes": _csg_plate_with_holes,
    "box_with_pocket": _csg_box_with_pocket,
    "tube": _csg_tube,
    "cut_sphere": _csg_cut_sphere,
    "box_with_boss": _csg_box_with_boss,
    "dumbbell": _csg_dumbbell,
    "cross": _csg_cross,
    "bracket": _csg_bracket,
}


def _draw_csg(sub: str, rng: np.random.Generator) -> dict:
    """A CSG shape of kind ``sub``, drawn again until it is thick enough: {"params": its steps and record, "size"}."""
    if sub not in _CSG_DRAWERS:
        raise ValueError(f"unknown csg shape {sub!r}")
    for _ in range(_MAX_TRIES):
        steps, info, size = _CSG_DRAWERS[sub](rng)
        if _thick_enough(size):
            return {"params": {"steps": steps, **info}, "size": _rv(size)}
    raise RuntimeError(f"no thick enough {sub} in {_MAX_TRIES} draws")


# ----------------------------------------------------------------------------- generators: extrusions


def _rounded_rectangle(a: float, b: float, radius: float) -> list[tuple[float, float]]:
    pts = []
    corners = [(a / 2 - radius, b / 2 - radius, 0.0), (-a / 2 + radius, b / 2 - radius, 90.0),
               (-a / 2 + radius, -b / 2 + radius, 180.0), (a / 2 - radius, -b / 2 + radius, 270.0)]
    for cx, cy, start in corners:
        for k in range(ROUNDED_CORNER_SEGMENTS + 1):
            t = math.radians(start + 90.0 * k / ROUNDED_CORNER_SEGMENTS)
            pts.append((cx + radius * math.cos(t), cy + radius * math.sin(t)))
    return pts


def _segment_distance(p, q) -> float:
    """Distance from the origin to the segment ``p``-``q``."""
    p, q = np.asarray(p), np.asarray(q)
    d = q - p
    t = np.clip(-(p @ d) / (d @ d), 0.0, 1.0)
    return float(np.linalg.norm(p + t * d))


def _draw_extrusion(sub: str, rng: np.random.Generator) -> dict:
    u = rng.uniform
    for _ in range(_MAX_TRIES):
        holes: list = []
        info: dict = {}
        if sub == "l":
            w, h = u(0.3, 1.0), u(0.3, 1.0)
            ta, tb = h * u(0.15, 0.5), w * u(0.15, 0.5)
            shell = [(0, 0), (w, 0), (w, ta), (tb, ta), (tb, h), (0, h)]
            info = {"width": w, "height": h, "foot": ta, "upright": tb}
        elif sub == "u":
            w, h = u(0.3, 1.0), u(0.3, 1.0)
            ts, tb = w * u(0.1, 0.3), h * u(0.15, 0.5)
            shell = [(0, 0), (w, 0), (w, h), (w - ts, h), (w - ts, tb), (ts, tb), (ts, h), (0, h)]
            info = {"width": w, "height": h, "side": ts, "base": tb}
        elif sub == "t":
            w, h = u(0.3, 1.0), u(0.3, 1.0)
            tb, ws = h * u(0.15, 0.4), w * u(0.15, 0.5)
            shell = [(-ws / 2, 0), (ws / 2, 0), (ws / 2, h - tb), (w / 2, h - tb), (w / 2, h), (-w / 2, h),
                     (-w / 2, h - tb), (-ws / 2, h - tb)]
            info = {"width": w, "height": h, "bar": tb, "stem": ws}
        elif sub == "star":
            n = int(rng.integers(5, 9))
            outer = u(0.3, 0.8)
            inner = outer * u(0.4, 0.7)
            phase = u(0.0, 2 * math.pi / n)
            shell = [((outer if k % 2 == 0 else inner) * math.cos(phase + k * math.pi / n),
                      (outer if k % 2 == 0 else inner) * math.sin(phase + k * math.pi / n)) for k in range(2 * n)]
            info = {"points": n, "outer_radius": outer, "inner_radius": inner}
        elif sub == "rounded_rectangle":
            a, b = u(0.3, 1.0), u(0.3, 1.0)
            radius = min(a, b) * u(0.05, 0.45)
            shell = _rounded_rectangle(a, b, radius)
            info = {"width": a, "height": b, "corner_radius": radius}
        elif sub == "polygon_with_hole":
            n = int(rng.integers(7, 15))
            big = u(0.3, 0.8)
            angles = (np.arange(n) + u(-0.3, 0.3, size=n)) * 2 * math.pi / n
            radii = big * u(0.65, 1.0, size=n)
            shell = [(float(r * math.cos(t)), float(r * math.sin(t))) for r, t in zip(radii, angles)]
            clearance = min(_segment_distance(shell[k], shell[(k + 1) % n]) for k in range(n))
            hole_r = clearance * u(0.3, 0.6)
            sides = int(rng.integers(3, 25))
            spin = u(0.0, 2 * math.pi)
            turns = [spin + 2 * math.pi * k / sides for k in range(sides)]
            holes = [[(hole_r * math.cos(t), hole_r * math.sin(t)) for t in turns]]
            info = {"vertices": n, "radius": big, "hole_radius": hole_r, "hole_sides": sides}
        else:
            raise ValueError(f"unknown extrusion profile {sub!r}")
        shell = [_rv(p) for p in shell]
        holes = [[_rv(p) for p in hole] for hole in holes]
        try:
            poly = _polygon(shell, holes)
        except ValueError:
            continue
        lo_x, lo_y, hi_x, hi_y = poly.bounds
        span = max(hi_x - lo_x, hi_y - lo_y)
        depth = _r(span * u(0.15, 1.2))
        size = (hi_x - lo_x, hi_y - lo_y, depth)
        if _thick_enough(size) and len(poly.interiors) == len(holes):
            params = {"shell": shell, "holes": holes, "depth": depth,
                      **{k: (_r(v) if isinstance(v, float) else v) for k, v in info.items()}}
            return {"params": params, "size": _rv(size)}
    raise RuntimeError(f"no valid {sub} profile in {_MAX_TRIES} draws")


# ----------------------------------------------------------------------------- generators: lathes


def _draw_lathe(sub: str, rng: np.random.Generator) -> dict:
    from scipy.interpolate import PchipInterpolator

    u = rng.uniform
    for _ in range(_MAX_TRIES):
        height = u(0.3, 1.2)
        info: dict = {}
        if sub == "vase":
            zs = np.array([0.0, 0.25, 0.5, 0.75, 1.0]) * height
            rs = height * u(0.12, 0.4, size=5)
            rs[3] *= u(0.5, 1.0)  # often a neck below the lip
            wall, floor = height * u(0.015, 0.04), height * u(0.03, 0.1)
            if rs.min() < 2 * wall:  # pchip does not overshoot: rs.min() is the narrowest
                continue
            curve = PchipInterpolator(zs, rs)
            z_out = np.linspace(0.0, height, 25)
            z_in = np.linspace(height, floor, 24)
            profile = ([(0.0, 0.0)] + [(float(curve(z)), z) for z in z_out]
                       + [(float(curve(z)) - wall, z) for z in z_in] + [(0.0, floor)])
            info = {"control_radii": _rv(rs), "wall": _r(wall), "floor": _r(floor)}
        elif sub == "bottle":
            body = height * u(0.12, 0.3)
            shoulder = height * u(0.45, 0.7)
            neck_r = body * u(0.25, 0.45)
            neck_z = shoulder + height * u(0.1, 0.2)
            lip = height * u(0.02, 0.05)
            if neck_z >= height - 2 * lip:
                continue
            t = np.linspace(0.0, 1.0, 13)[1:-1]
            blend = [(neck_r + (body - neck_r) * (1 + math.cos(math.pi * s)) / 2, shoulder + s * (neck_z - shoulder))
                     for s in t]
            profile = ([(0.0, 0.0), (body * 0.94, 0.0), (body, 0.03 * height), (body, shoulder)] + blend
                       + [(neck_r, neck_z), (neck_r, height - lip), (neck_r * 1.15, height - lip),
                          (neck_r * 1.15, height), (0.0, height)])
            info = {"body_radius": _r(body), "shoulder": _r(shoulder), "neck_radius": _r(neck_r), "neck_z": _r(neck_z)}
        elif sub == "bowl":
            height = u(0.15, 0.5)
            rim = height * u(1.0, 2.5)
            foot = rim * u(0.3, 0.6)
            power = u(0.4, 0.8)
            wall = min(height, rim) * u(0.04, 0.1)
            floor = height * u(0.08, 0.2)
            s = np.linspace(0.0, 1.0, 25)
            outer = [(foot + (rim - foot) * v ** power, v * height) for v in s]
            inner = [((rim - wall) * v ** power, floor + v * (height - floor)) for v in s[::-1]]
            profile = [(0.0, 0.0)] + outer + inner[:-1] + [(0.0, floor)]
            info = {"rim_radius": _r(rim), "foot_radius": _r(foot), "power": _r(power), "wall": _r(wall),
                    "floor": _r(floor)}
        elif sub == "goblet":
            foot = height * u(0.2, 0.35)
            foot_t = height * u(0.03, 0.06)
            stem = height * u(0.03, 0.07)
            z0 = height * u(0.3, 0.55)
            rim = height * u(0.2, 0.4)
            wall = height * u(0.015, 0.03)
            z1 = z0 + height * u(0.05, 0.1)
            power = u(0.35, 0.7)
            s = np.linspace(0.0, 1.0, 21)
            outer = [(stem + (rim - stem) * v ** power, z0 + v * (height - z0)) for v in s]
            inner = [((rim - wall) * v ** power, z1 + v * (height - z1)) for v in s[::-1]]
            profile = ([(0.0, 0.0), (foot, 0.0), (foot, foot_t), (stem, foot_t + 0.04 * height)] + outer
                       + inner[:-1] + [(0.0, z1)])
            info = {"foot_radius": _r(foot), "stem_radius": _r(stem), "cup_bottom": _r(z0), "rim_radius": _r(rim),
                    "wall": _r(wall), "power": _r(power)}
        else:
            raise ValueError(f"unknown lathe shape {sub!r}")
        profile = [_rv(p) for p in profile]
        pts = np.asarray(profile)
        if np.any(pts[1:-1, 0] <= 0) or np.any(np.all(np.diff(pts, axis=0) == 0, axis=1)):
            continue
        region = _profile_polygon(pts)
        if not region.is_valid or region.area <= 0:
            continue
        width = 2 * float(pts[:, 0].max())
        size = (width, width, float(pts[:, 1].max() - pts[:, 1].min()))
        if _thick_enough(size):
            return {"params": {"profile": profile, "height": _r(height), **info}, "size": _rv(size)}
    raise RuntimeError(f"no valid {sub} profile in {_MAX_TRIES} draws")


# ----------------------------------------------------------------------------- generators: assemblies


def _leg(round_leg: bool, thickness: float, x: float, y: float, z0: float, z1: float) -> dict:
    if round_leg:
        return _cyl(thickness / 2, z1 - z0, (x, y, (z0 + z1) / 2))
    return _box((thickness, thickness, z1 - z0), (x, y, (z0 + z1) / 2))


def _chair(rng: np.random.Generator) -> tuple[list, dict]:
    u = rng.uniform
    w, d, hs, ts = u(0.4, 0.56), u(0.38, 0.52), u(0.4, 0.48), u(0.025, 0.06)
    round_legs = bool(rng.random() < 0.5)
    lt, inset = u(0.025, 0.055), u(0.0, 0.03)
    lx, ly = w / 2 - inset - lt / 2, d / 2 - inset - lt / 2
    seat_mid = hs - ts / 2
    parts = [_box((w, d, ts), (0.0, 0.0, seat_mid))]
    parts += [_leg(round_legs, lt, sx * lx, sy * ly, 0.0, seat_mid) for sx in (-1, 1) for sy in (-1, 1)]
    back_h = u(0.28, 0.5)
    back = "panel" if rng.random() < 0.5 else "slats"
    if back == "panel":
        tb = u(0.02, 0.04)
        parts.append(_box((w * u(0.85, 1.0), tb, hs + back_h - seat_mid),
                          (0.0, d / 2 - tb / 2, (seat_mid + hs + back_h) / 2)))
    else:
        parts += [_leg(round_legs, lt, sx * lx, ly, seat_mid, hs + back_h) for sx in (-1, 1)]
        rail_t, rail_h = u(0.02, 0.035), u(0.05, 0.12)
        parts.append(_box((2 * lx, rail_t, rail_h), (0.0, ly, hs + back_h - rail_h / 2)))
        n_slats = int(rng.integers(0, 5))
        slat_w = u(0.02, 0.05)
        for k in range(n_slats):
            x = -lx + 2 * lx * (k + 1) / (n_slats + 1)
            parts.append(_box((slat_w, rail_t * 0.8, back_h - rail_h + ts / 2),
                              (x, ly, (seat_mid + hs + back_h - rail_h) / 2)))
    stretchers = bool(rng.random() < 0.5)
    if stretchers:
        zs = u(0.1, 0.2)
        parts += [_box((lt * 0.6, 2 * ly, lt * 0.6), (sx * lx, 0.0, zs)) for sx in (-1, 1)]
    return parts, {"seat": _rv((w, d, hs)), "round_legs": round_legs, "legs": 4, "back": back, "stretchers": stretchers}


def _stool(rng: np.random.Generator) -> tuple[list, dict]:
    u = rng.uniform
    height, ts = u(0.45, 0.8), u(0.025, 0.05)
    round_seat = bool(rng.random() < 0.6)
    n_legs = int(rng.integers(3, 5))
    leg_r = u(0.012, 0.025)
    seat_mid = height - ts / 2
    if round_seat:
        radius = u(0.14, 0.22)
        parts = [_cyl(radius, ts, (0.0, 0.0, seat_mid))]
        ring = radius * u(0.6, 0.8)
    else:
        side = u(0.28, 0.42)
        parts = [_box((side, side, ts), (0.0, 0.0, seat_mid))]
        ring = side / 2 * u(0.75, 0.95)
    phase = math.pi / n_legs if n_legs == 4 else math.pi / 2
    feet = [(ring * math.cos(phase + 2 * math.pi * k / n_legs), ring * math.sin(phase + 2 * math.pi * k / n_legs))
            for k in range(n_legs)]
    parts += [_cyl(leg_r, seat_mid, (x, y, seat_mid / 2)) for x, y in feet]
    footrest = bool(rng.random() < 0.6)
    if footrest:
        zf = height * u(0.25, 0.4)
        bar = leg_r * 1.2
        for k in range(n_legs):
            (x0, y0), (x1, y1) = feet[k], feet[(k + 1) % n_legs]
            length = math.hypot(x1 - x0, y1 - y0)
            yaw = math.degrees(math.atan2(y1 - y0, x1 - x0))
            parts.append(_box((length, bar, bar), ((x0 + x1) / 2, (y0 + y1) / 2, zf), yaw=yaw))
    return parts, {"height": _r(height), "round_seat": round_seat, "legs": n_legs, "footrest": footrest}


def _table(rng: np.random.Generator) -> tuple[list, dict]:
    u = rng.uniform
    height, tt = u(0.4, 0.78), u(0.02, 0.06)
    top_mid = height - tt / 2
    round_top = bool(rng.random() < 0.35)
    info: dict = {"height": _r(height), "round_top": round_top}
    if round_top:
        diameter = u(0.5, 1.2)
        parts = [_cyl(diameter / 2, tt, (0.0, 0.0, top_mid))]
        column = u(0.03, 0.07)
        parts.append(_cyl(column, top_mid, (0.0, 0.0, top_mid / 2)))
        if rng.random() < 0.5:
            disc_h = u(0.02, 0.05)
            parts.append(_cyl(diameter / 2 * u(0.35, 0.6), disc_h, (0.0, 0.0, disc_h / 2)))
            info["base"] = "disc"
        else:
            reach, fw, fh = diameter * u(0.5, 0.7), u(0.04, 0.08), u(0.03, 0.06)
            parts += [_box((reach, fw, fh), (0.0, 0.0, fh / 2), yaw=yaw) for yaw in (0.0, 90.0)]
            info["base"] = "cross"
        info["legs"] = 1
        info["top"] = _rv((diameter, diameter, tt))
        return parts, info
    w, d = u(0.6, 1.8), u(0.5, 1.0)
    parts = [_box((w, d, tt), (0.0, 0.0, top_mid))]
    round_legs = bool(rng.random() < 0.4)
    lt, inset = u(0.03, 0.07), u(0.02, 0.1)
    lx, ly = w / 2 - inset - lt / 2, d / 2 - inset - lt / 2
    xs = [-lx, lx] + ([0.0] if w > 1.4 and rng.random() < 0.5 else [])
    parts += [_leg(round_legs, lt, x, sy * ly, 0.0, top_mid) for x in xs for sy in (-1, 1)]
    apron = bool(rng.random() < 0.5)
    if apron:
        ah, at = u(0.06, 0.12), u(0.015, 0.025)
        z = height - tt - ah / 2 + 0.005
        parts += [_box((2 * lx, at, ah), (0.0, sy * ly, z)) for sy in (-1, 1)]
        parts += [_box((at, 2 * ly, ah), (sx * lx, 0.0, z)) for sx in (-1, 1)]
    info.update({"top": _rv((w, d, tt)), "legs": len(xs) * 2, "round_legs": round_legs, "apron": apron})
    return parts, info


def _shelf(rng: np.random.Generator) -> tuple[list, dict]:
    u = rng.uniform
    w, d, height, t = u(0.4, 1.2), u(0.22, 0.45), u(0.5, 1.9), u(0.015, 0.03)
    boards = int(rng.integers(2, 7))
    plinth = u(0.04, 0.1) if rng.random() < 0.5 else 0.0
    parts = [_box((t, d, height), (sx * (w / 2 - t / 2), 0.0, height / 2)) for sx in (-1, 1)]
    z_bottom, z_top = plinth + t / 2, height - t / 2
    for k in range(boards):
        z = z_bottom + (z_top - z_bottom) * k / (boards - 1)
        parts.append(_box((w - t, d, t), (0.0, 0.0, z)))
    if plinth:
        parts.append(_box((w - t, t, plinth), (0.0, -d / 2 + t, plinth / 2)))
    back = bool(rng.random() < 0.6)
    if back:
        tb = u(0.006, 0.012)
        parts.append(_box((w - t, tb, height - plinth), (0.0, d / 2 - tb / 2, (height + plinth) / 2)))
    return parts, {"outer": _rv((w, d, height)), "board": _r(t), "boards": boards, "plinth": _r(plinth), "back": back}


def _cabinet(rng: np.random.Generator) -> tuple[list, dict]:
    u = rng.uniform
    w, d, height = u(0.4, 1.4), u(0.35, 0.6), u(0.5, 1.3)
    base = "legs" if rng.random() < 0.5 else "plinth"
    hb = u(0.06, 0.15) if base == "legs" else u(0.05, 0.1)
    parts = [_box((w, d, height - hb), (0.0, 0.0, hb + (height - hb) / 2))]
    if base == "legs":
        lr = u(0.015, 0.03)
        parts += [_cyl(lr, hb + 0.01, (sx * (w / 2 - 2 * lr), sy * (d / 2 - 2 * lr), (hb + 0.01) / 2))
                  for sx in (-1, 1) for sy in (-1, 1)]
    else:
        parts.append(_box((w - 0.06, d - 0.06, hb + 0.01), (0.0, 0.0, (hb + 0.01) / 2)))
    overhang = u(0.01, 0.04) if rng.random() < 0.5 else 0.0
    if overhang:
        tt = u(0.02, 0.04)
        parts.append(_box((w + 2 * overhang, d + overhang, tt), (0.0, -overhang / 2, height + tt / 2 - 0.005)))
    ft, gap, margin = u(0.012, 0.02), 0.004, 0.02
    y_front = -d / 2 - ft / 2 + 0.3 * ft
    front = str(rng.choice(["doors", "drawers", "mixed"]))
    x0, x1, z0, z1 = -w / 2 + margin, w / 2 - margin, hb + margin, height - margin
    panels: list[tuple[float, float, float, float, str]] = []  # x0, x1, z0, z1, kind
    if front == "drawers":
        n = int(rng.integers(2, 6))
        panels = [(x0, x1, z0 + (z1 - z0) * k / n, z0 + (z1 - z0) * (k + 1) / n, "drawer") for k in range(n)]
    else:
        z_split = z1 - (z1 - z0) * u(0.2, 0.3) if front == "mixed" else z1
        n = int(rng.integers(1, 4))
        panels = [(x0 + (x1 - x0) * k / n, x0 + (x1 - x0) * (k + 1) / n, z0, z_split, "door") for k in range(n)]
        if front == "mixed":
            panels.append((x0, x1, z_split, z1, "drawer"))
    knob = bool(rng.random() < 0.5)
    for k, (a0, a1, b0, b1, kind) in enumerate(panels):
        parts.append(_box((a1 - a0 - gap, ft, b1 - b0 - gap), ((a0 + a1) / 2, y_front, (b0 + b1) / 2)))
        if kind == "drawer":
            hx, hz = (a0 + a1) / 2, b1 - min(0.06, (b1 - b0) / 3)
        else:
            hx = a1 - 0.05 if k % 2 == 0 else a0 + 0.05
            hz = (b0 + b1) / 2
        y_handle = y_front - ft / 2
        if knob:
            parts.append(_cyl(0.012, 0.03, (hx, y_handle - 0.012, hz), axis="y"))
        else:
            parts.append(_box((0.1 if kind == "drawer" else 0.02, 0.03, 0.02 if kind == "drawer" else 0.1),
                              (hx, y_handle - 0.012, hz)))
    return parts, {"body": _rv((w, d, height)), "base": base, "front": front, "panels": len(panels), "knobs": knob}


def _bench(rng: np.random.Generator) -> tuple[list, dict]:
    u = rng.uniform
    length, d, height, ts = u(1.0, 2.0), u(0.3, 0.45), u(0.4, 0.5), u(0.03, 0.08)
    seat_mid = height - ts / 2
    slats = int(rng.integers(3, 6)) if rng.random() < 0.4 else 1
    if slats == 1:
        parts = [_box((length, d, ts), (0.0, 0.0, seat_mid))]
    else:
        g = u(0.005, 0.015)
        sw = (d - g * (slats - 1)) / slats
        parts = [_box((length, sw, ts), (0.0, -d / 2 + sw / 2 + k * (sw + g), seat_mid)) for k in range(slats)]
    legs = "slabs" if rng.random() < 0.4 else "posts"
    inset = u(0.03, 0.15)
    if legs == "slabs":
        tl = u(0.03, 0.07)
        x = length / 2 - inset - tl / 2
        parts += [_box((tl, d * u(0.8, 1.0), seat_mid), (sx * x, 0.0, seat_mid / 2)) for sx in (-1, 1)]
        if rng.random() < 0.5:
            parts.append(_box((2 * x, 0.03, 0.05), (0.0, 0.0, u(0.1, 0.2))))
        n_legs = 2
        post_y = d / 2 - tl / 2
        lt = tl
        round_legs = False
    else:
        round_legs = bool(rng.random() < 0.4)
        lt = u(0.04, 0.08)
        x = length / 2 - inset - lt / 2
        xs = [-x, x] + ([0.0] if length > 1.5 and rng.random() < 0.6 else [])
        post_y = d / 2 - lt / 2 - 0.01
        parts += [_leg(round_legs, lt, xx, sy * post_y, 0.0, seat_mid) for xx in xs for sy in (-1, 1)]
        n_legs = 2 * len(xs)
    backrest = bool(rng.random() < 0.4)
    if backrest:
        hb, bt, bh = u(0.25, 0.4), u(0.02, 0.04), u(0.08, 0.16)
        parts += [_leg(round_legs, min(lt, 0.05), sx * x, post_y, seat_mid, height + hb) for sx in (-1, 1)]
        parts.append(_box((length * u(0.9, 1.0), bt, bh),
                          (0.0, post_y + min(lt, 0.05) / 2 + bt / 2 - 0.005, height + hb - bh / 2)))
    return parts, {"seat": _rv((length, d, height)), "slats": slats, "legs": legs, "leg_count": n_legs,
                   "backrest": backrest}


_ASSEMBLERS = {"chair": _chair, "stool": _stool, "table": _table, "shelf": _shelf, "cabinet": _cabinet, "bench": _bench}


def _draw_assembly(sub: str, rng: np.random.Generator) -> dict:
    if sub not in _ASSEMBLERS:
        raise ValueError(f"unknown assembly {sub!r}")
    for _ in range(_MAX_TRIES):
        parts, info = _ASSEMBLERS[sub](rng)
        bounds = np.array([_spec_bounds(p) for p in parts])
        lo, hi = bounds[:, 0].min(axis=0), bounds[:, 1].max(axis=0)
        size = hi - lo
        if _thick_enough(size):
            return {"params": {"parts": parts, **info}, "size": _rv(size)}
    raise RuntimeError(f"no thick enough {sub} in {_MAX_TRIES} draws")


# ----------------------------------------------------------------------------- records


def _pose(kind: str, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    if kind == "assembly":
        heading = round(float(rng.uniform(0.0, 360.0)), 2)
        return _heading_matrix(heading), {"heading_deg": heading}
    while True:
        q = rng.normal(size=4)
        if np.linalg.norm(q) > 1e-3:
            break
    q = q / np.linalg.norm(q)
    q = [round(float(v), 6) + 0.0 for v in q]
    return quaternion_matrix(q), {"quaternion_wxyz": q}


def _record(kind: str, index: int) -> ShapeRecord:
    kind_index = CLASSES.index(kind)
    # one generator per shape: a shape does not change when the counts of other kinds do
    rng = np.random.default_rng([SEED, kind_index, index])
    subkinds = SUBKINDS[kind]
    sub = subkinds[index % len(subkinds)]
    if kind == "primitive":
        drawn = _draw_primitive(sub, index // len(subkinds), rng)
    elif kind == "csg":
        drawn = _draw_csg(sub, rng)
    elif kind == "extrusion":
        drawn = _draw_extrusion(sub, rng)
    elif kind == "lathe":
        drawn = _draw_lathe(sub, rng)
    else:
        drawn = _draw_assembly(sub, rng)
    rotation, pose = _pose(kind, rng)
    shape_id = f"procedural-{kind}-{index:03d}"
    params = drawn["params"]
    return ShapeRecord(
        shape_id=shape_id,
        source="procedural",
        package=None,
        path=f"procedural:{kind}/{index:03d}",
        name=f"{kind} {sub.replace('_', ' ')} {index:03d}",
        creator=_CREATOR,
        licence=_LICENCE,
        category=kind,
        class_hint=kind,
        rotation=rotation,
        load=functools.partial(build_parts, kind, params),  # rebuilt on each call; no mesh is kept
        family=shape_id,
        extra={
            "generator": f"training.data.sources.procedural v{GENERATOR_VERSION}",
            "seed": [SEED, kind_index, index],
            "kind": kind,
            "subkind": sub,
            "size": drawn["size"],
            "params": params,
            "pose": pose,
        },
    )


def enumerate_shapes(root=None, counts: dict[str, int] | None = None) -> list[ShapeRecord]:
    """The procedural shapes: ``procedural-<kind>-<NNN>`` for every kind of :data:`COUNTS`.

    Args:
        root: ignored (nothing is unpacked); accepted for the source interface.
        counts: shapes per kind (default :data:`COUNTS`); a kind left out
            gets none.  Shape ``i`` of a kind is the same whatever the counts.

    Returns:
        ``list[ShapeRecord]`` in kind order then index order; identical on
        every call.  Drawing the parameters is cheap (no mesh is built).
    """
    counts = dict(COUNTS if counts is None else counts)
    unknown = set(counts) - set(CLASSES)
    if unknown:
        raise ValueError(f"unknown procedural kinds {sorted(unknown)}; known: {', '.join(CLASSES)}")
    records = []
    for kind in CLASSES:
        n = int(counts.get(kind, 0))
        if n < 0 or n > 1000:
            raise ValueError(f"count of {kind} must be in [0, 1000], got {n}")
        records += [_record(kind, i) for i in range(n)]
    return records
