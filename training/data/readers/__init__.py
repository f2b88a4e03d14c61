"""Small readers for mesh formats that trimesh cannot load by itself.

* :func:`read_ac3d` — AC3D ``.ac`` and TORCS ``.acc`` (text; nested objects,
  per-object ``rot``/``loc``, polygons and triangle strips).
* :func:`read_3ds` — Autodesk 3D Studio ``.3ds`` (binary chunks).
* :func:`read_pmd` — 0 A.D.'s compiled meshes ``.pmd`` (binary; positions, UVs,
  triangles; no materials: 0 A.D.'s actor files name the textures).

The first two return one :class:`trimesh.Trimesh` with every part merged, in the
file's own coordinates (no axis conversion: that is the source modules' job),
with per-face colours taken from the file's materials; ``read_pmd`` returns the
mesh with its UVs in ``metadata``.  All three raise :class:`ValueError` with a
readable message when the input cannot be used.
"""

from .ac3d import read_ac3d
from .pmd import read_pmd
from .threeds import read_3ds

__all__ = ["read_ac3d", "read_3ds", "read_pmd"]
