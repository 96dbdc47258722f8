"""Shapes with a hole through them: a tube (a short, thick-walled pipe) and a frame (a square picture frame).

Blender's only holed primitive is the torus, which the base's held-out split keeps unseen, and stage 1
trained on shapes without holes reads that torus as a filled disc (docs/lab-notebook/2026-12-07.md,
twenty-first section). These two have holes without being tori: straight walls, flat faces, sharp rims.

Both are a ring of ``sides`` wall segments between an outer and an inner polygon, closed by flat top and
bottom annuli. Walls and caps get vertices of their own (split at every rim), and so does each wall face of
the frame, so the area-weighted vertex normals that pilight/render/scene.py bakes are exact: a cap's normal
is its face's, a tube's wall normal is radial (outward outside, inward in the bore), a frame's wall normal
is its face's.
"""

from __future__ import annotations

import math

import numpy as np

# (sides, outer radius, inner radius, half height): the tube fits the unit sphere's scale as the other
# shapes do (bounding radius sqrt(1 + 0.45^2) = 1.10); the frame's outer square has half-side 0.8
# (circumradius 0.8 sqrt 2 = 1.13), its opening half-side 0.45, and it is 0.4 thick.
HOLED = {
    "tube": (48, 1.0, 0.55, 0.45),
    "frame": (4, 0.8 * math.sqrt(2), 0.45 * math.sqrt(2), 0.2),
}


def holed_mesh(name: str) -> tuple[np.ndarray, list[tuple[int, ...]]]:
    """Vertices (n, 3) and faces (counter-clockwise seen from outside) of a holed shape."""
    sides, r_out, r_in, h = HOLED[name]
    # The frame's corners sit at 45 degrees, so its sides are axis-aligned.
    angles = 2 * math.pi * np.arange(sides) / sides + (math.pi / 4 if sides == 4 else 0.0)
    ring = np.stack([np.cos(angles), np.sin(angles)], -1)
    split_walls = sides == 4  # flat walls: one set of vertices per face; round ones share theirs
    verts: list[np.ndarray] = []
    faces: list[tuple[int, ...]] = []

    def add(points: np.ndarray) -> int:
        verts.append(points)
        return sum(len(v) for v in verts) - len(points)

    def quad_strip(xy_a: np.ndarray, z_a: float, xy_b: np.ndarray, z_b: float) -> None:
        """Quads between loop a and loop b (a then b counter-clockwise seen from the side they face)."""
        a = np.column_stack([xy_a, np.full(sides, z_a)])
        b = np.column_stack([xy_b, np.full(sides, z_b)])
        if split_walls:
            for i in range(sides):
                j = (i + 1) % sides
                s = add(np.stack([a[i], a[j], b[j], b[i]]))
                faces.append((s, s + 1, s + 2, s + 3))
        else:
            sa, sb = add(a), add(b)
            faces.extend((sa + i, sa + (i + 1) % sides, sb + (i + 1) % sides, sb + i) for i in range(sides))

    outer, inner = r_out * ring, r_in * ring
    quad_strip(outer, -h, outer, h)  # outer wall, facing out
    quad_strip(inner, h, inner, -h)  # the bore's wall, facing in
    for z, lo, hi in ((h, outer, inner), (-h, inner, outer)):  # top and bottom annuli, facing +z and -z
        so, si = add(np.column_stack([lo, np.full(sides, z)])), add(np.column_stack([hi, np.full(sides, z)]))
        faces.extend((so + i, so + (i + 1) % sides, si + (i + 1) % sides, si + i) for i in range(sides))
    return np.concatenate(verts), faces


def add_holed_shape(name: str):
    """Link a new object of the holed shape to the scene, make it active and return it (as bpy.ops would)."""
    import bpy  # here, so holed_mesh is plain numpy

    co, faces = holed_mesh(name)
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(co.tolist(), [], faces)
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.collection.objects.link(obj)
    bpy.context.view_layer.objects.active = obj
    return obj
