"""Procedural flat and thin shapes for training only (CC0, written here).

Why: real photos are often of flat or thin things lying on a table (a
lighter, a card, a leaf, a plate), and a model trained on the corpus alone
makes every object a rounded lump about as deep as wide.  These shapes go
into the GPU burst's training pack (``genre data pack --thin N``,
:mod:`training.data.pack`) and, lying on the ground, into rendered training
views (``genre data thin``, then ``genre data render``); they are **not** a corpus source
(no ``enumerate_shapes``, not in the manifest), so the corpus, its splits and
the product test split do not change, and none of them is ever a test shape.

Kinds (the class is ``thin-<kind>``; sub-kinds are assigned round-robin,
shape ``k`` of a kind is ``SUBKINDS[kind][k % len]``):

``plate``
    plates and dishes (shallow thin-walled lathes: a flat well, a rim
    rising to height 4-13 % of the diameter), coins (a disc with a raised rim
    and a sunk face) and discs (plain, or a washer / CD with a centre hole).
``card``
    cards (sharp-cornered thin boxes), rounded cards (rounded rectangles),
    bent cards (a rounded card bent about one axis) and sheets (very thin,
    A-paper proportions, often curled).
``book``
    closed books (two cover boards, a spine and a page block set back
    from the covers' edges), thick closed books, and open books (two halves,
    each a board with its pages, tilted 3-14 degrees up from the spine).
``leaf``
    a leaf outline (elliptic, lanceolate, lobed, or with a long stalk) as a
    thin slab, its midsurface bent along the midrib, folded across it and
    slightly twisted.
``bowl``
    thin-walled bowls: a superellipse profile revolved, the wall 1-3 % of
    the bounding-box diagonal (round, conical and footed bowls).  Bowls are
    deep (depth 20-50 % of the diameter); what is thin is their wall.
``rod``
    rods (cylinders), capsules, pens (a lathe with a cone tip, a grip, and
    in half of them a wider cap with a clip) and pencils (hexagonal, a
    sharpened tip).

Thickness: the thin extent over the largest is drawn log-uniformly, mostly
within 1-10 % (cards and sheets 0.3-6 %, leaves 0.6-3 % before the bend,
rods' diameter 1.5-10 % of their length).  The smallest extent along the
oriented bounding box over the largest: for the 200 non-bowl shapes of
``thin_shapes(40)``, median 0.059, below 0.10 for 83 % and below 0.15 for
97 % (the 6 above: thick books and the deepest dishes on a foot ring).

Size and pose: every shape is built in its own frame, turned by a uniformly
random rotation (a random unit quaternion: a flat thing is seen from every
side), then centred on its axis-aligned bounding box and scaled to a
bounding-box diagonal of 1, as the corpus normalises.  Every mesh is one
``trimesh.Trimesh`` of at most :data:`MAX_FACES` triangles (vertices ``(V,
3) float64``, faces ``(F, 3) int64``).

Determinism: shape ``k`` of kind ``K`` is drawn from its own generator,
``numpy.random.default_rng([seed, KINDS.index(K), k])``, so
:func:`thin_shapes` returns the same meshes on every call for a given seed,
and shape ``k`` does not depend on ``count_per_kind``.
"""

from __future__ import annotations

import math

import numpy as np
import trimesh

from .procedural import _extrusion_mesh, _rounded_rectangle, quaternion_matrix

__all__ = ["FLAT_KINDS", "FLAT_TEST_SEED", "GENERATOR_VERSION", "KINDS", "MAX_FACES", "SUBKINDS", "flat_test_shape", "lying_rotation", "lying_thin_shape",
           "thin_shape", "thin_shapes"]

KINDS: tuple[str, ...] = ("plate", "card", "book", "leaf", "bowl", "rod")
SUBKINDS: dict[str, tuple[str, ...]] = {
    "plate": ("plate", "dish", "coin", "disc"),
    "card": ("card", "rounded_card", "bent_card", "sheet"),
    "book": ("closed", "thick", "open"),
    "leaf": ("elliptic", "lanceolate", "lobed", "stalked"),
    "bowl": ("round", "conical", "footed"),
    "rod": ("rod", "capsule", "pen", "pencil"),
}
MAX_FACES = 2000
GENERATOR_VERSION = 1
_MAX_TRIES = 50


def _loguniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


# ----------------------------------------------------------------------------- building blocks


def _revolve(profile, sections: int) -> trimesh.Trimesh:
    """A (n, 2) (radius, z) profile revolved about Z with ``sections`` sections.

    The profile either starts and ends on the axis (radius 0) or is closed
    (first point == last point, off the axis: a ring).  Outward normals.
    """
    from shapely.geometry import Polygon

    profile = np.asarray(profile, dtype=np.float64)
    if profile.ndim == 2 and len(profile) > 1:  # consecutive repeats (a bevel of 0) dropped
        keep = np.concatenate([[True], np.any(np.diff(profile, axis=0) != 0, axis=1)])
        profile = profile[keep]
    if profile.ndim != 2 or profile.shape[1] != 2 or len(profile) < 3:
        raise ValueError(f"profile must be (n >= 3, 2), got shape {profile.shape}")
    if not Polygon(profile).is_valid:
        raise ValueError("profile crosses itself")
    mesh = trimesh.creation.revolve(profile, sections=int(sections))
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def _lathe_sections(n_points: int, limit: int = MAX_FACES, most: int = 64) -> int:
    """The most sections (≤ ``most``) that keep a revolved ``n_points`` profile within ``limit`` triangles."""
    return int(max(6, min(most, limit // (2 * (n_points - 1)))))


def _offset_curve(points: np.ndarray, distance: float) -> np.ndarray:
    """Points (n, 2) moved ``distance`` along the left normal of the polyline (toward the inside of a lathe)."""
    tangent = np.gradient(points, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)  # left of the direction of travel
    return points + distance * normal


def _shell_profile(outer: np.ndarray, wall: float) -> np.ndarray:
    """A thin-walled lathe profile: ``outer`` (n, 2) runs from the axis (radius 0) to the rim, and the
    inside surface is ``outer`` offset by ``wall`` (inward, up), back to the axis."""
    inner = _offset_curve(outer, wall)  # outer runs outward, then up: its left is the inside
    inner = inner[inner[:, 0] > 1e-9][::-1]
    z_axis = outer[0, 1] + wall
    return np.concatenate([outer, inner, [(0.0, z_axis)]])


def _slab(xs: np.ndarray, half_width, ns: int, mid, thickness: float) -> trimesh.Trimesh:
    """A closed thin slab over the region ``|y| <= half_width(x)``, ``x`` in ``xs`` (sorted, (nt + 1,)).

    ``ns`` cells across; ``mid(x, y)`` the midsurface height (arrays in,
    array out); the slab is ``thickness`` thick in z.  Where the half width is
    0 (a leaf's tip) the grid's points coincide and are merged.
    """
    xs = np.asarray(xs, dtype=np.float64)
    nt = len(xs) - 1
    s = np.linspace(-1.0, 1.0, ns + 1)
    w = np.asarray(half_width(xs), dtype=np.float64)
    gx = np.repeat(xs[:, None], ns + 1, axis=1)
    gy = w[:, None] * s[None, :]
    gz = np.asarray(mid(gx, gy), dtype=np.float64)
    top = np.stack([gx, gy, gz + thickness / 2], axis=-1).reshape(-1, 3)
    bottom = np.stack([gx, gy, gz - thickness / 2], axis=-1).reshape(-1, 3)
    n = len(top)
    idx = np.arange(n).reshape(nt + 1, ns + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    cells = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    ring = np.concatenate([idx[:, 0], idx[-1, 1:], idx[-2::-1, -1], idx[0, -2:0:-1]])  # counter-clockwise
    p, q = ring, np.roll(ring, -1)
    sides = np.concatenate([np.stack([p + n, q + n, q], -1), np.stack([p + n, q, p], -1)])
    faces = np.concatenate([cells, cells[:, ::-1] + n, sides])
    mesh = trimesh.Trimesh(np.concatenate([top, bottom]), faces, process=True)
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def _union(parts: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    """The boolean union of watertight parts (manifold3d); their concatenation if that fails."""
    try:
        out = trimesh.boolean.union(parts, engine="manifold")
    except Exception:  # noqa: BLE001 - a failed union falls back to overlapping parts
        return trimesh.util.concatenate(parts)
    return out if len(out.faces) else trimesh.util.concatenate(parts)


def _box(extents, centre=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents=np.asarray(extents, dtype=np.float64))
    mesh.apply_translation(centre)
    return mesh


def _rotation_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    m = np.eye(4)
    m[:3, :3] = [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
    return m


# ----------------------------------------------------------------------------- kinds


def _plate(sub: str, rng: np.random.Generator) -> trimesh.Trimesh:
    u = rng.uniform
    radius = 1.0
    if sub in ("plate", "dish"):
        height = 2 * radius * (u(0.04, 0.09) if sub == "plate" else u(0.08, 0.13))
        well = radius * (u(0.45, 0.7) if sub == "plate" else u(0.2, 0.5))
        wall = 2 * radius * _loguniform(rng, 0.008, 0.02)
        power = u(1.3, 2.5)
        s = np.linspace(0.0, 1.0, 12)[1:]
        if sub == "plate":  # a rim that flattens out (a marli)
            rise = np.sin(0.5 * math.pi * s) ** power
        else:  # a dish: steepening toward the rim
            rise = s ** power
        outer = np.concatenate([[(0.0, 0.0), (well * 0.5, 0.0), (well, 0.0)],
                                np.stack([well + (radius - well) * s, height * rise], 1)])
        profile = _shell_profile(outer, wall)
        if rng.uniform() < 0.5:  # a foot ring under the well
            return _union([_revolve(profile, _lathe_sections(len(profile), 1500)), _foot_ring(well * u(0.6, 0.9), wall)])
        return _revolve(profile, _lathe_sections(len(profile)))
    if sub == "coin":
        thick = 2 * radius * u(0.04, 0.1)
        rim = radius * u(0.05, 0.12)
        relief = thick * u(0.1, 0.25)
        profile = [(0.0, relief), (radius - rim, relief), (radius - rim, 0.0), (radius, 0.0), (radius, thick),
                   (radius - rim, thick), (radius - rim, thick - relief), (0.0, thick - relief)]
        return _revolve(profile, 64)
    if sub == "disc":
        thick = 2 * radius * _loguniform(rng, 0.01, 0.1)
        if rng.uniform() < 0.5:  # a plain disc (a coaster, a lid)
            return _revolve([(0.0, 0.0), (radius, 0.0), (radius, thick), (0.0, thick)], 64)
        hole = radius * u(0.08, 0.4)  # a washer, a CD
        return _revolve([(hole, 0.0), (radius, 0.0), (radius, thick), (hole, thick), (hole, 0.0)], 64)
    raise ValueError(f"unknown plate {sub!r}")


def _foot_ring(radius: float, wall: float) -> trimesh.Trimesh:
    """A small ring under a plate's well: from z = -1.5 wall up into the plate's floor."""
    ring = [(radius - wall, -1.5 * wall), (radius, -1.5 * wall), (radius, wall * 0.5), (radius - wall, wall * 0.5),
            (radius - wall, -1.5 * wall)]
    return _revolve(ring, 48)


def _corner_xs(length: float, radius: float, corner_steps: int, middle_steps: int) -> np.ndarray:
    """Stations along x in [0, length]: dense over the two rounded ends (by angle), sparse between."""
    theta = np.linspace(0.0, 0.5 * math.pi, corner_steps + 1)
    end = radius * (1.0 - np.cos(theta))
    middle = np.linspace(radius, length - radius, middle_steps + 1)[1:-1]
    return np.unique(np.concatenate([end, middle, length - end[::-1]]))


def _rounded_half_width(length: float, width: float, radius: float):
    def half_width(x):
        d = np.minimum(x, length - x)
        inside = np.clip(radius - d, 0.0, radius)
        return width / 2 - radius + np.sqrt(np.maximum(radius**2 - inside**2, 0.0))

    return half_width


def _card(sub: str, rng: np.random.Generator) -> trimesh.Trimesh:
    u = rng.uniform
    length = 1.0
    if sub == "sheet":
        width = length * rng.choice([1 / math.sqrt(2), u(0.6, 0.8)])
        thick = length * _loguniform(rng, 0.003, 0.012)
    else:
        width = length * u(0.45, 0.9)
        thick = length * _loguniform(rng, 0.006, 0.06)
    if sub == "card":
        return _box((length, width, thick))
    if sub == "rounded_card":
        radius = width * u(0.04, 0.2)
        return _extrusion_mesh(_rounded_rectangle(length, width, radius), [], thick)
    radius = width * (u(0.04, 0.2) if sub == "bent_card" else u(0.0, 0.03))
    sag = length * (u(0.015, 0.06) if sub == "bent_card" else u(0.0, 0.09))  # the bend's sagitta
    curl = u(-1.0, 1.0) * length * 0.05 if sub == "sheet" else 0.0  # a sheet's corner lifting
    xs = _corner_xs(length, radius, 6, 28) if radius > 0 else np.linspace(0.0, length, 29)

    def mid(x, y):
        t = x / length - 0.5
        return sag * 4 * t * t + curl * np.clip(t, 0, None) ** 2 * np.clip(y / width + 0.5, 0, 1) * 4

    return _slab(xs, _rounded_half_width(length, width, radius) if radius > 0 else (lambda x: np.full_like(x, width / 2)),
                 6 if sub == "sheet" else 2, mid, thick)


def _book(sub: str, rng: np.random.Generator) -> trimesh.Trimesh:
    u = rng.uniform
    height = 1.0  # along y
    width = height * u(0.6, 0.85)  # spine to fore-edge, along x
    board = height * u(0.006, 0.015)
    inset = height * u(0.01, 0.03)
    eps = board * 0.05
    if sub in ("closed", "thick"):
        thick = height * (_loguniform(rng, 0.025, 0.09) if sub == "closed" else u(0.09, 0.17))
        z0 = thick / 2 - board / 2
        parts = [_box((width, height, board), (0.0, 0.0, -z0)), _box((width, height, board), (0.0, 0.0, z0)),
                 _box((board, height, thick), (-width / 2 + board / 2, 0.0, 0.0))]
        pages_w = width - board - inset
        parts.append(_box((pages_w + eps, height - 2 * inset, thick - 2 * board + 2 * eps),
                          (-width / 2 + board - eps + (pages_w + eps) / 2, 0.0, 0.0)))
        return _union(parts)
    if sub == "open":
        pages = height * _loguniform(rng, 0.008, 0.04)  # each half's page stack
        tilt = math.radians(u(3.0, 14.0))
        half = [_box((width, height, board), (width / 2, 0.0, board / 2)),
                _box((width - inset, height - 2 * inset, pages + eps), (0.0 + (width - inset) / 2, 0.0, board + pages / 2))]
        right = _union(half)
        right.apply_transform(_rotation_y(-tilt))
        left = right.copy()
        left.apply_transform(trimesh.transformations.rotation_matrix(math.pi, (0.0, 0.0, 1.0)))
        spine = trimesh.creation.cylinder(radius=board + pages * 0.5, height=height - 2 * inset, sections=16)
        spine.apply_transform(trimesh.transformations.rotation_matrix(0.5 * math.pi, (1.0, 0.0, 0.0)))
        spine.apply_translation((0.0, 0.0, board + pages * 0.5 - board))
        return _union([right, left, spine])
    raise ValueError(f"unknown book {sub!r}")


def _leaf(sub: str, rng: np.random.Generator) -> trimesh.Trimesh:
    u = rng.uniform
    length = 1.0
    thick = length * _loguniform(rng, 0.006, 0.03)
    stalk = 0.0
    if sub == "lanceolate":
        width = length * u(0.1, 0.25)
    else:
        width = length * u(0.3, 0.65)
    if sub == "stalked":
        stalk = length * u(0.15, 0.3)
    p, q = u(0.5, 1.2), u(0.6, 1.4)  # p < q: widest toward the base (ovate); p > q: obovate
    lobes, lobe_depth = int(rng.integers(2, 5)), (u(0.15, 0.35) if sub == "lobed" else 0.0)
    blade = length - stalk
    t_peak = p / (p + q)
    peak = t_peak**p * (1 - t_peak) ** q
    stalk_half = thick * 1.2

    def half_width(x):
        t = np.clip((x - stalk) / blade, 0.0, 1.0)
        w = 0.5 * width * t**p * (1 - t) ** q / peak
        if lobe_depth:
            w = w * (1 - lobe_depth * (0.5 - 0.5 * np.cos(2 * math.pi * lobes * t)))
        return np.where(x < stalk, stalk_half, np.maximum(w, np.where(t < 0.05, stalk_half if stalk else 0.0, 0.0)))

    sag = length * u(0.0, 0.08)  # bent along the midrib
    fold = u(0.0, 0.25)  # the halves raised toward the edges (a gutter along the midrib)
    twist = u(-0.3, 0.3)

    def mid(x, y):
        t = x / length - 0.5
        return sag * 4 * t * t + fold * np.abs(y) * (1 - 2 * np.abs(t)) + twist * y * t

    xs = np.concatenate([np.linspace(0.0, stalk, 4)[:-1], np.linspace(stalk, length, 37)]) if stalk else \
        np.linspace(0.0, length, 41)
    return _slab(xs, half_width, 10, mid, thick)


def _bowl(sub: str, rng: np.random.Generator) -> trimesh.Trimesh:
    u = rng.uniform
    radius = 1.0
    depth = 2 * radius * u(0.2, 0.5)
    diag = math.hypot(2 * radius * math.sqrt(2), depth)
    wall = diag * _loguniform(rng, 0.01, 0.03)
    exponent = u(1.6, 3.0) if sub != "conical" else u(1.0, 1.3)
    theta = np.linspace(0.0, 0.5 * math.pi, 16)
    r = radius * np.sin(theta) ** (2 / exponent)
    z = depth - depth * np.cos(theta) ** (2 / exponent)
    if sub == "conical":  # a flat floor, then a straight flaring wall
        floor = radius * u(0.25, 0.5)
        r = floor + (radius - floor) * np.linspace(0.0, 1.0, 16)
        z = depth * np.linspace(0.0, 1.0, 16) ** u(0.8, 1.2)
        r = np.concatenate([[0.0], r])
        z = np.concatenate([[0.0], z])
    outer = np.stack([r, z], 1)
    profile = _shell_profile(outer, wall)
    if sub == "footed":
        bowl = _revolve(profile, _lathe_sections(len(profile), 1500))
        foot_r = radius * u(0.3, 0.5)
        foot_h = depth * u(0.06, 0.15)
        z_at = float(np.interp(foot_r, r, z))
        ring = [(foot_r - wall, -foot_h), (foot_r, -foot_h), (foot_r, z_at + wall * 0.5),
                (foot_r - wall, z_at + wall * 0.5), (foot_r - wall, -foot_h)]
        return _union([bowl, _revolve(ring, 40)])
    return _revolve(profile, _lathe_sections(len(profile)))


def _rod(sub: str, rng: np.random.Generator) -> trimesh.Trimesh:
    u = rng.uniform
    length = 1.0
    r = 0.5 * length * _loguniform(rng, 0.015, 0.1)
    if sub == "rod":
        bevel = r * u(0.0, 0.3)
        profile = [(0.0, 0.0), (r - bevel, 0.0), (r, bevel), (r, length - bevel), (r - bevel, length), (0.0, length)]
        return _revolve(profile, 24)
    if sub == "capsule":
        a = np.linspace(0.0, 0.5 * math.pi, 7)
        bottom = np.stack([r * np.sin(a), r - r * np.cos(a)], 1)
        top = np.stack([r * np.cos(a), length - r + r * np.sin(a)], 1)
        return _revolve(np.concatenate([bottom, top]), 24)
    if sub == "pen":
        tip, grip = length * u(0.04, 0.08), length * u(0.15, 0.3)
        capped = rng.uniform() < 0.5
        body = [(0.0, 0.0), (r * 0.15, 0.0), (r * 0.6, tip * 0.7), (r * 0.85, tip), (r * 0.85, tip + grip),
                (r, tip + grip + r * 0.5), (r, length - r * 0.5), (r * 0.6, length), (0.0, length)]
        pen = _revolve(body, 24)
        if not capped:
            return pen
        cap_len = length * u(0.25, 0.4)
        rc = r * 1.25
        cap = _revolve([(0.0, -r * 0.4), (rc * 0.7, -r * 0.4), (rc, 0.0), (rc, cap_len), (0.0, cap_len)], 24)
        cap.apply_translation((0.0, 0.0, -tip * 0.2))  # over the tip
        clip_l = cap_len * u(0.6, 0.85)
        clip = _box((r * 0.25, r * 0.5, clip_l), (rc + r * 0.2, 0.0, cap_len - clip_l / 2))
        return _union([pen, cap, clip])
    if sub == "pencil":
        tip = length * u(0.05, 0.1)
        profile = [(0.0, 0.0), (r * 0.3, tip * 0.25), (r, tip), (r, length), (0.0, length)]
        return _revolve(profile, 6)
    raise ValueError(f"unknown rod {sub!r}")


_BUILDERS = {"plate": _plate, "card": _card, "book": _book, "leaf": _leaf, "bowl": _bowl, "rod": _rod}


# ----------------------------------------------------------------------------- shapes


def _normalised(mesh: trimesh.Trimesh, rotation: np.ndarray) -> trimesh.Trimesh:
    """``mesh`` rotated, centred on its axis-aligned bounding box, its diagonal scaled to 1."""
    v = np.asarray(mesh.vertices, dtype=np.float64) @ rotation.T
    lo, hi = v.min(axis=0), v.max(axis=0)
    v = (v - (lo + hi) / 2) / float(np.linalg.norm(hi - lo))
    return trimesh.Trimesh(v, np.asarray(mesh.faces, dtype=np.int64), process=False)


def _built(kind: str, k: int, seed: int) -> tuple[np.random.Generator, trimesh.Trimesh]:
    """Shape ``k`` of ``kind`` in its builder's own frame, and the generator that drew it (its pose comes next)."""
    if kind not in KINDS:
        raise ValueError(f"unknown thin kind {kind!r}; known: {', '.join(KINDS)}")
    rng = np.random.default_rng([int(seed), KINDS.index(kind), int(k)])
    subkinds = SUBKINDS[kind]
    sub = subkinds[k % len(subkinds)]
    for _ in range(_MAX_TRIES):
        try:
            mesh = _BUILDERS[kind](sub, rng)
        except ValueError:  # a drawn profile crossed itself: draw again
            continue
        if 0 < len(mesh.faces) <= MAX_FACES:
            return rng, mesh
    raise RuntimeError(f"thin-{kind}-{k:03d}: no valid {sub} in {_MAX_TRIES} draws")


def thin_shape(kind: str, k: int, seed: int = 0) -> tuple[str, str, trimesh.Trimesh]:
    """Shape ``k`` of ``kind``: ``(id, class, mesh)``, ``id = thin-<kind>-<k:03d>``, ``class = thin-<kind>``."""
    rng, mesh = _built(kind, k, seed)
    while True:
        q = rng.normal(size=4)
        if np.linalg.norm(q) > 1e-3:
            break
    return f"thin-{kind}-{k:03d}", f"thin-{kind}", _normalised(mesh, quaternion_matrix(q))


def lying_rotation(vertices: np.ndarray, yaw: float, flip: bool) -> np.ndarray:
    """The (3, 3) rotation that lays a shape flat: its thinnest principal axis along +Z, turned ``yaw`` about Z.

    The principal axes are the eigenvectors of the vertices' covariance; the
    largest lies along X before the yaw; ``flip`` turns the shape upside down
    (a half turn about X).
    """
    v = np.asarray(vertices, np.float64)
    v = v - v.mean(axis=0)
    _, vectors = np.linalg.eigh(v.T @ v)  # ascending: the thinnest axis first
    axes = np.stack([vectors[:, 2], vectors[:, 1], vectors[:, 0]])  # rows: largest → X, middle → Y, thinnest → Z
    if np.linalg.det(axes) < 0:
        axes[1] *= -1
    c, s = math.cos(yaw), math.sin(yaw)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    if flip:
        turn = turn @ np.diag([1.0, -1.0, -1.0])
    return turn @ axes


FLAT_KINDS: tuple[str, ...] = ("plate", "card", "book", "leaf")  # what lies flat on a table (bowls are deep; rods are not flat)
FLAT_TEST_SEED = 20261128  # not the pack's seed (0): no flat test shape is a training shape


def lying_thin_shape(kind: str, k: int, seed: int = 0) -> tuple[str, str, trimesh.Trimesh]:
    """Shape ``k`` of ``kind`` (the mesh :func:`thin_shape` draws) lying on the ground plane, not in a random pose.

    Posed by :func:`lying_rotation` (its thinnest axis along +Z, a random yaw,
    upside down for half of them), as a thing lies on a table, so that views
    from -10° to 88° elevation see it from the side up to from above.  With
    the pack's seed (0) these are the training set's rendered thin shapes
    (``genre data thin``); ``id = thin-<kind>-<k:03d>``, class ``thin-<kind>``.
    """
    rng, mesh = _built(kind, k, seed)
    rotation = lying_rotation(mesh.vertices, float(rng.uniform(0.0, 2 * math.pi)), bool(rng.random() < 0.5))
    return f"thin-{kind}-{k:03d}", f"thin-{kind}", _normalised(mesh, rotation)


def flat_test_shape(kind: str, k: int, seed: int = FLAT_TEST_SEED) -> tuple[str, str, trimesh.Trimesh]:
    """Shape ``k`` of a flat ``kind`` lying on the ground plane, for ``genre eval``'s flat-from-above group.

    :func:`lying_thin_shape` drawn from another seed than the training set's
    thin shapes (the pack's, 0), so that no test shape is a training shape.
    ``id = flat-<kind>-<k:03d>``, class ``thin-<kind>``.
    """
    if kind not in FLAT_KINDS:
        raise ValueError(f"{kind!r} is not a flat kind; flat kinds: {', '.join(FLAT_KINDS)}")
    _, cls, mesh = lying_thin_shape(kind, k, seed)
    return f"flat-{kind}-{k:03d}", cls, mesh


def thin_shapes(count_per_kind: int = 40, seed: int = 0) -> list[tuple[str, str, trimesh.Trimesh]]:
    """``count_per_kind`` shapes of every kind of :data:`KINDS`, in kind order then index order.

    Returns:
        ``list[(id, class, trimesh.Trimesh)]`` of ``len(KINDS) *
        count_per_kind`` shapes, each normalised (centred on its bounding
        box, diagonal 1) and in a uniformly random pose; identical on every
        call for a given ``seed``.
    """
    if isinstance(count_per_kind, bool) or not isinstance(count_per_kind, (int, np.integer)) \
            or not 0 <= count_per_kind <= 1000:
        raise ValueError(f"count_per_kind: expected an int in [0, 1000], got {count_per_kind!r}")
    return [thin_shape(kind, k, seed) for kind in KINDS for k in range(int(count_per_kind))]
