"""Procedural furniture and lamps built from parts, for training the depth net only (CC0, written here).

Why: the depth net's error on unseen shapes follows the number of distinct shapes *of the product's kinds* it has
seen (about the −0.15 power of the count; ``results/stage_errors/depth.md``), the registries hold no more real ones
than the corpus has, and shapes of other kinds (0 A.D.'s buildings), features of a net trained on photographs and
stretched views did not stand in.  These are new shapes of the product's kinds, as many as asked for: each one
assembled from boxes, cylinders and lathed profiles in proportions drawn at random, in the styles real furniture
is made in.  The corpus's own procedural source (:mod:`.procedural`, kind ``assembly``) holds a fixed 80 such
assemblies of six kinds in the corpus's splits, and changing it would change the corpus; this module makes as many as
a training run asks for, of nine kinds and more styles.  Like the thin and squashed shapes they are never a corpus source or a test shape
(``genre data furniture`` writes them for ``genre data render``), and their classes are ``procedural-<kind>``, so
no evaluation mistakes them for the corpus's chairs and tables.

Kinds and their styles (shape ``k`` of a kind takes style ``k % len(STYLES[kind])``):

``table``      four posts, a pedestal on a foot, or two trestle panels with a stretcher; a square or round top
``chair``      four legs or a sled frame; a panel, slatted or open-frame back, leaning back; arms in a third of them
``stool``      three or four splayed legs (a foot ring in half of them), or a pedestal; a round or square seat
``bench``      posts or end panels; a backrest in half of them
``shelf``      two sides and 2–6 shelves; a back panel in half of them, a plinth in a third
``cabinet``    a body on legs or a plinth, its front doors or drawers (proud panels with handles)
``bed``        a frame on legs, a mattress, a headboard, a footboard in half of them
``sofa``       a base, 1–3 seat cushions, a back, arms (each side, or none), short legs
``lamp``       a foot, a straight or bent stem, a lathed shade (a drum, a cone or a dome)

Every shape stands upright in its own frame (object +Z up, as the corpus's after loading), is centred on its
axis-aligned bounding box and scaled to a bounding-box diagonal of 1, as the corpus normalises.  The parts are
closed meshes that may overlap (the renders and the depth need no union).  Shape ``k`` of a kind comes from
``numpy.random.default_rng([seed, KINDS.index(kind), k])``, so it does not depend on how many are made.
"""

from __future__ import annotations

import numpy as np
import trimesh

from .thin import _normalised

__all__ = ["KINDS", "STYLES", "furniture_shape"]

STYLES: dict[str, tuple[str, ...]] = {
    "table": ("posts", "pedestal", "trestle"),
    "chair": ("panel", "slats", "frame", "sled"),
    "stool": ("three", "four", "pedestal"),
    "bench": ("posts", "panels"),
    "shelf": ("open", "backed"),
    "cabinet": ("doors", "drawers"),
    "bed": ("legs", "panel"),
    "sofa": ("arms", "armless"),
    "lamp": ("drum", "cone", "dome"),
}
KINDS: tuple[str, ...] = tuple(STYLES)


def _box(centre, extents) -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents=np.asarray(extents, dtype=np.float64))
    mesh.apply_translation(np.asarray(centre, dtype=np.float64))
    return mesh


def _rod(a, b, radius: float, sections: int = 16) -> trimesh.Trimesh:
    """A cylinder from point ``a`` to point ``b``."""
    return trimesh.creation.cylinder(radius=radius, segment=np.asarray([a, b], dtype=np.float64), sections=sections)


def _lathe(radii, heights, sections: int = 32) -> trimesh.Trimesh:
    """A closed solid of revolution about +Z through the profile (radius, height) pairs, bottom to top."""
    profile = np.column_stack([np.concatenate([[0.0], radii, [0.0]]),
                               np.concatenate([[heights[0]], heights, [heights[-1]]])])
    return trimesh.creation.revolve(profile, sections=sections)


def _leg(x: float, y: float, top: float, width: float, round_legs: bool, splay=(0.0, 0.0)) -> trimesh.Trimesh:
    """A leg from the floor (z = 0, moved out by ``splay``) to height ``top`` under (x, y)."""
    foot = (x + splay[0], y + splay[1], 0.0)
    if round_legs or splay != (0.0, 0.0):
        return _rod(foot, (x, y, top), width / 2)
    return _box((x, y, top / 2), (width, width, top))


def _four_legs(w: float, d: float, top: float, width: float, inset: float, round_legs: bool, splay: float = 0.0):
    xs, ys = w / 2 - inset - width / 2, d / 2 - inset - width / 2
    return [_leg(sx * xs, sy * ys, top, width, round_legs, (sx * splay, sy * splay)) for sx in (-1, 1) for sy in (-1, 1)]


def _table(style: str, rng: np.random.Generator) -> list[trimesh.Trimesh]:
    w = rng.uniform(0.6, 2.0)
    d = w * rng.uniform(0.45, 1.0)
    h = rng.uniform(0.4, 0.8)
    t = rng.uniform(0.02, 0.06)
    round_top = rng.random() < 0.35
    if round_top:
        d = w
        parts = [_rod((0, 0, h - t), (0, 0, h), w / 2, sections=48)]
    else:
        parts = [_box((0, 0, h - t / 2), (w, d, t))]
    leg = rng.uniform(0.03, 0.08)
    if style == "posts":
        inset = (0.15 * w if round_top else rng.uniform(0.0, 0.08))
        parts += _four_legs(w, d, h - t, leg, inset, rng.random() < 0.5)
        if rng.random() < 0.5:  # an apron under the top
            a = rng.uniform(0.05, 0.12)
            parts.append(_box((0, 0, h - t - a / 2), (w * (0.7 if round_top else 0.95), d * (0.7 if round_top else 0.95), a)))
    elif style == "pedestal":
        parts.append(_rod((0, 0, 0.03), (0, 0, h - t), rng.uniform(0.04, 0.1)))
        parts.append(_rod((0, 0, 0), (0, 0, 0.03), min(w, d) * rng.uniform(0.25, 0.4), sections=32))
    else:  # trestle: two end panels and a stretcher
        px = w / 2 - rng.uniform(0.05, 0.2) * w
        for sx in (-1, 1):
            parts.append(_box((sx * px, 0, (h - t) / 2), (leg, d * rng.uniform(0.5, 0.85), h - t)))
        parts.append(_box((0, 0, (h - t) * rng.uniform(0.15, 0.5)), (2 * px, leg, leg * 1.5)))
    return parts


def _chair(style: str, rng: np.random.Generator) -> list[trimesh.Trimesh]:
    w, d = rng.uniform(0.4, 0.6), rng.uniform(0.4, 0.58)
    h = rng.uniform(0.38, 0.5)
    t = rng.uniform(0.03, 0.1)
    back_h = rng.uniform(0.3, 0.65)
    lean = np.radians(rng.uniform(0, 18))
    leg = rng.uniform(0.025, 0.05)
    parts = [_box((0, 0, h - t / 2), (w, d, t))]
    if style == "sled":
        for sx in (-1, 1):
            x = sx * (w / 2 - leg / 2)
            parts += [_rod((x, -d / 2, 0), (x, d / 2, 0), leg / 2), _rod((x, -d / 2 + leg, 0), (x, -d / 2 + leg, h - t), leg / 2),
                      _rod((x, d / 2 - leg, 0), (x, d / 2 - leg, h - t), leg / 2)]
    else:
        parts += _four_legs(w, d, h - t, leg, 0.0, rng.random() < 0.5)
    # the back: from the seat's rear edge (y = +d/2), leaning away from the seat by ``lean``
    top = np.array([0.0, d / 2 + back_h * np.sin(lean), h + back_h * np.cos(lean)])
    base = np.array([0.0, d / 2 - leg / 2, h])
    mid = (top + base) / 2
    bt = rng.uniform(0.02, 0.05)

    def leaning(centre, extents):
        part = _box((0, 0, 0), extents)
        part.apply_transform(trimesh.transformations.rotation_matrix(-lean, (1, 0, 0)))
        part.apply_translation(centre)
        return part

    if style in ("panel", "sled"):
        parts.append(leaning(mid, (w, bt, back_h)))
    else:
        for sx in (-1, 1):  # two uprights
            parts.append(leaning(mid + [sx * (w / 2 - leg / 2), 0, 0], (leg, bt, back_h)))
        rail = rng.uniform(0.05, 0.15)
        parts.append(leaning(top - [0, rail / 2 * np.sin(lean), rail / 2 * np.cos(lean)], (w, bt, rail)))
        if style == "slats":
            n = int(rng.integers(2, 6))
            for i in range(n):
                x = (i + 1) / (n + 1) * w - w / 2
                parts.append(leaning(mid + [x, 0, 0], (rng.uniform(0.02, 0.06), bt * 0.8, back_h)))
    if rng.random() < 1 / 3:  # arms
        ah = rng.uniform(0.18, 0.28)
        for sx in (-1, 1):
            x = sx * (w / 2 + 0.02)
            parts += [_box((x, 0, h + ah), (0.05, d, 0.04)), _box((x, -d / 2 + 0.03, h + ah / 2), (0.04, 0.04, ah))]
    return parts


def _stool(style: str, rng: np.random.Generator) -> list[trimesh.Trimesh]:
    h = rng.uniform(0.42, 0.8)
    r = rng.uniform(0.15, 0.22)
    t = rng.uniform(0.03, 0.07)
    square = rng.random() < 0.35
    parts = [_box((0, 0, h - t / 2), (2 * r, 2 * r, t)) if square else _rod((0, 0, h - t), (0, 0, h), r, sections=40)]
    leg = rng.uniform(0.02, 0.04)
    if style == "pedestal":
        parts += [_rod((0, 0, 0.02), (0, 0, h - t), rng.uniform(0.025, 0.05)), _rod((0, 0, 0), (0, 0, 0.02), r * 1.1, 32)]
        return parts
    n = 3 if style == "three" else 4
    splay = rng.uniform(0.0, 0.1)
    angles = np.arange(n) * 2 * np.pi / n + (np.pi / 4 if n == 4 else 0.0)
    top_r, foot_r = r * 0.7, r * 0.7 + splay
    for a in angles:
        parts.append(_rod((foot_r * np.cos(a), foot_r * np.sin(a), 0), (top_r * np.cos(a), top_r * np.sin(a), h - t), leg))
    if rng.random() < 0.5:  # a foot ring
        z = h * rng.uniform(0.25, 0.45)
        ring_r = top_r + splay * (1 - z / (h - t))
        parts.append(trimesh.creation.annulus(r_min=ring_r - leg, r_max=ring_r + leg, height=leg * 1.5, sections=32))
        parts[-1].apply_translation((0, 0, z))
    return parts


def _bench(style: str, rng: np.random.Generator) -> list[trimesh.Trimesh]:
    w, d = rng.uniform(0.9, 1.9), rng.uniform(0.3, 0.45)
    h, t = rng.uniform(0.38, 0.48), rng.uniform(0.03, 0.08)
    parts = [_box((0, 0, h - t / 2), (w, d, t))]
    leg = rng.uniform(0.04, 0.08)
    if style == "posts":
        parts += _four_legs(w, d, h - t, leg, rng.uniform(0.0, 0.1), rng.random() < 0.4)
    else:
        for sx in (-1, 1):
            parts.append(_box((sx * (w / 2 - rng.uniform(0.02, 0.15)), 0, (h - t) / 2), (leg, d * 0.9, h - t)))
    if rng.random() < 0.5:  # a backrest on two posts
        bh = rng.uniform(0.25, 0.45)
        for sx in (-1, 1):
            parts.append(_box((sx * (w / 2 - 0.1), d / 2 - 0.02, h + bh / 2), (0.04, 0.04, bh)))
        parts.append(_box((0, d / 2 - 0.02, h + bh * 0.75), (w, 0.03, bh * 0.5)))
    return parts


def _shelf(style: str, rng: np.random.Generator) -> list[trimesh.Trimesh]:
    w, h, d = rng.uniform(0.4, 1.4), rng.uniform(0.6, 2.1), rng.uniform(0.22, 0.45)
    t = rng.uniform(0.015, 0.04)
    plinth = rng.uniform(0.05, 0.12) if rng.random() < 1 / 3 else 0.0
    parts = [_box((sx * (w / 2 - t / 2), 0, h / 2), (t, d, h)) for sx in (-1, 1)]
    n = int(rng.integers(2, 7))
    for i in range(n + 1):
        z = plinth + t / 2 + i * (h - plinth - t) / n
        parts.append(_box((0, 0, z), (w - 2 * t, d, t)))
    if plinth:
        parts.append(_box((0, -d / 2 + 0.03, plinth / 2), (w - 2 * t, 0.02, plinth)))
    if style == "backed":
        parts.append(_box((0, d / 2 - 0.005, h / 2), (w, 0.01, h)))
    return parts


def _cabinet(style: str, rng: np.random.Generator) -> list[trimesh.Trimesh]:
    w, d = rng.uniform(0.4, 1.6), rng.uniform(0.35, 0.6)
    body = rng.uniform(0.4, 1.6)
    lift = rng.uniform(0.08, 0.25) if rng.random() < 0.5 else 0.0
    parts = [_box((0, 0, lift + body / 2), (w, d, body))]
    if lift:
        parts += _four_legs(w, d, lift, rng.uniform(0.03, 0.05), 0.02, rng.random() < 0.5)
    gap, proud = 0.006, rng.uniform(0.008, 0.02)
    front = -d / 2 - proud / 2
    if style == "doors":
        n = 1 if w < 0.6 else 2
        dw = w / n
        for i in range(n):
            x = -w / 2 + dw * (i + 0.5)
            parts.append(_box((x, front, lift + body / 2), (dw - 2 * gap, proud, body - 2 * gap)))
            toward = 1.0 if (n == 2 and i == 0) else -1.0  # a pair's handles meet in the middle; one door's on its left
            hx = x + toward * (dw / 2 - 0.06)
            parts.append(_box((hx, front - proud, lift + body * 0.6), (0.015, 0.02, 0.12)))
    else:
        n = int(rng.integers(2, 6))
        dh = body / n
        for i in range(n):
            z = lift + dh * (i + 0.5)
            parts.append(_box((0, front, z), (w - 2 * gap, proud, dh - 2 * gap)))
            parts.append(_box((0, front - proud, z + dh * 0.15), (min(0.2, w * 0.3), 0.02, 0.015)))
    return parts


def _bed(style: str, rng: np.random.Generator) -> list[trimesh.Trimesh]:
    w, length = rng.uniform(0.9, 1.9), rng.uniform(1.9, 2.2)
    frame_top = rng.uniform(0.2, 0.4)
    frame_t = rng.uniform(0.1, 0.25)
    mat = rng.uniform(0.12, 0.28)
    parts = [_box((0, 0, frame_top - frame_t / 2), (w, length, frame_t)),
             _box((0, 0, frame_top + mat / 2), (w * 0.97, length * 0.97, mat))]
    if style == "legs":
        parts += _four_legs(w, length, frame_top - frame_t, rng.uniform(0.04, 0.08), 0.02, rng.random() < 0.5)
    else:
        parts.append(_box((0, 0, (frame_top - frame_t) / 2), (w * 0.95, length * 0.95, frame_top - frame_t)))
    head = rng.uniform(0.5, 1.2)
    parts.append(_box((0, length / 2 + 0.03, head / 2), (w + 0.04, rng.uniform(0.03, 0.1), head)))
    if rng.random() < 0.5:
        foot = rng.uniform(0.3, 0.6)
        parts.append(_box((0, -length / 2 - 0.03, foot / 2), (w + 0.04, 0.04, foot)))
    return parts


def _sofa(style: str, rng: np.random.Generator) -> list[trimesh.Trimesh]:
    seats = int(rng.integers(1, 4))
    w, d = rng.uniform(0.7, 1.0) * seats + 0.2, rng.uniform(0.75, 1.0)
    legs = rng.uniform(0.03, 0.15)
    base = rng.uniform(0.15, 0.3)
    cushion = rng.uniform(0.1, 0.2)
    back_t, back_h = rng.uniform(0.15, 0.3), rng.uniform(0.35, 0.6)
    arm_w = rng.uniform(0.1, 0.25) if style == "arms" else 0.0
    inner = w - 2 * arm_w
    parts = [_box((0, 0, legs + base / 2), (w, d, base))]
    parts += _four_legs(w, d, legs, 0.05, 0.05, rng.random() < 0.5)
    cw = inner / seats
    for i in range(seats):
        parts.append(_box((-inner / 2 + cw * (i + 0.5), -back_t / 2, legs + base + cushion / 2),
                          (cw - 0.01, d - back_t, cushion)))
    parts.append(_box((0, d / 2 - back_t / 2, legs + base + back_h / 2), (inner, back_t, back_h)))
    if arm_w:
        arm_h = rng.uniform(0.15, 0.35)
        for sx in (-1, 1):
            parts.append(_box((sx * (w / 2 - arm_w / 2), 0, legs + (base + arm_h) / 2), (arm_w, d, base + arm_h)))
    return parts


def _lamp(style: str, rng: np.random.Generator) -> list[trimesh.Trimesh]:
    h = rng.uniform(0.35, 1.7)  # a table lamp to a floor lamp
    foot_r = rng.uniform(0.08, 0.2) * max(h, 0.6)
    stem_top = h * rng.uniform(0.7, 0.85)
    stem_r = rng.uniform(0.008, 0.025)
    top = np.array([0.0, 0.0, stem_top])
    if rng.random() < 0.3:  # a bent stem: up, then out to one side, over a foot wide enough to carry it
        knee = np.array([0.0, 0.0, stem_top * rng.uniform(0.6, 0.9)])
        top = np.array([rng.uniform(0.1, 0.35) * h, 0.0, stem_top])
        foot_r = max(foot_r, 1.2 * top[0])
        parts = [_rod((0, 0, 0), knee, stem_r), _rod(knee, top, stem_r)]
    else:
        parts = [_rod((0, 0, 0), top, stem_r)]
    parts.append(_lathe([foot_r, foot_r * 0.8], [0.0, rng.uniform(0.015, 0.05)]))
    sh = h - stem_top + rng.uniform(0.05, 0.15)
    r_top = rng.uniform(0.08, 0.25) * max(h, 0.5)
    wall = 0.01
    if style == "drum":
        radii = [r_top, r_top, r_top - wall, r_top - wall]
    elif style == "cone":
        r_bottom = r_top * rng.uniform(1.4, 2.2)
        radii = [r_bottom, r_top, r_top - wall, r_bottom - wall]
    else:  # a dome: a quarter ellipse from a wide rim to the top
        a = np.linspace(0.0, np.pi / 2, 9)
        radii = list(r_top * 1.5 * np.cos(a))[:-1] + [0.0]
        shade = _lathe(np.maximum(radii, 1e-3), list(top[2] - sh * 0.3 + sh * np.sin(a)))
        shade.apply_translation((top[0], top[1], 0.0))
        return parts + [shade]
    heights = [top[2] - sh * 0.6, top[2] + sh * 0.4, top[2] + sh * 0.4 - wall, top[2] - sh * 0.6 + wall]
    shade = _lathe(radii, heights)
    shade.apply_translation((top[0], top[1], 0.0))
    return parts + [shade]


_BUILDERS = {"table": _table, "chair": _chair, "stool": _stool, "bench": _bench, "shelf": _shelf,
             "cabinet": _cabinet, "bed": _bed, "sofa": _sofa, "lamp": _lamp}


def furniture_shape(kind: str, k: int, seed: int = 0) -> tuple[str, str, trimesh.Trimesh]:
    """Shape ``k`` of ``kind`` as ``(id, class, mesh)``: id ``furniture-<kind>-<k>``, class ``procedural-<kind>``."""
    if kind not in STYLES:
        raise ValueError(f"unknown furniture kind {kind!r}; known: {', '.join(KINDS)}")
    rng = np.random.default_rng([int(seed), KINDS.index(kind), int(k)])
    styles = STYLES[kind]
    mesh = trimesh.util.concatenate(_BUILDERS[kind](styles[k % len(styles)], rng))
    return f"furniture-{kind}-{k:04d}", f"procedural-{kind}", _normalised(mesh, np.eye(3))
