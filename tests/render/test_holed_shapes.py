"""The holed shapes (pilight/render/holed_shapes.py): closed, outward-facing meshes of the stated size, and
in a render a hole the camera sees through with exact normals on the face around it (Blender at 96 px)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fixtures.render_scenes import controlled_spec, point_light, principled, sphere, tiny_params
from pilight.data import layout
from pilight.data.exr import read_exr
from pilight.params import RenderParams
from pilight.render.holed_shapes import HOLED, holed_mesh


def _signed_volume(co: np.ndarray, faces) -> float:
    """Divergence theorem over fan triangles: positive when every face points out of the solid."""
    return sum(
        float(np.dot(co[f[0]], np.cross(co[f[k]], co[f[k + 1]]))) / 6.0 for f in faces for k in range(1, len(f) - 1)
    )


def _polygon_area(sides: int, circumradius: float) -> float:
    return sides / 2 * circumradius**2 * math.sin(2 * math.pi / sides)


@pytest.mark.parametrize("name", sorted(HOLED))
def test_a_holed_shape_is_a_closed_ring_of_its_stated_volume_facing_out(name):
    sides, r_out, r_in, h = HOLED[name]
    co, faces = holed_mesh(name)
    expected = (_polygon_area(sides, r_out) - _polygon_area(sides, r_in)) * 2 * h
    assert _signed_volume(co, faces) == pytest.approx(expected, rel=1e-9)
    # closed: every edge, by position, is shared by exactly two faces, once in each direction
    key = lambda v: tuple(np.round(co[v], 9))
    directed = [(key(f[k]), key(f[(k + 1) % len(f)])) for f in faces for k in range(len(f))]
    assert len(set(directed)) == len(directed)
    assert set(directed) == {(b, a) for a, b in directed}


def _vertex_normals(co: np.ndarray, faces) -> tuple[np.ndarray, list[np.ndarray]]:
    """Area-weighted vertex normals, as pilight/render/scene.py bakes them, and each face's unit normal."""
    vert_n, face_n = np.zeros_like(co), []
    for f in faces:
        n = sum(np.cross(co[f[k]], co[f[(k + 1) % len(f)]]) for k in range(len(f)))  # Newell
        face_n.append(n / np.linalg.norm(n))
        for v in f:
            vert_n[v] += n
    return vert_n / np.linalg.norm(vert_n, axis=1, keepdims=True), face_n


@pytest.mark.parametrize("name", sorted(HOLED))
def test_the_baked_normals_are_exact_the_rims_stay_sharp(name):
    """Smooth shading would round a rim whose vertices two faces share: caps keep their own vertices, and
    the frame's walls too, so each vertex normal is its face's (a tube's walls share theirs: radial)."""
    co, faces = holed_mesh(name)
    vert_n, face_n = _vertex_normals(co, faces)
    for f, n in zip(faces, face_n, strict=True):
        if abs(n[2]) > 0.5 or name == "frame":  # a cap, or any face of the frame
            np.testing.assert_allclose(vert_n[list(f)], np.tile(n, (len(f), 1)), atol=1e-12)
        else:  # a tube's wall: horizontal, along the radius
            radial = co[list(f), :2] / np.linalg.norm(co[list(f), :2], axis=1, keepdims=True)
            np.testing.assert_allclose(vert_n[list(f), 2], 0.0, atol=1e-12)
            np.testing.assert_allclose(np.abs((vert_n[list(f), :2] * radial).sum(1)), 1.0, atol=1e-12)


def test_the_default_shapes_are_not_holed_and_a_holed_one_is_allowed():
    assert not set(RenderParams().scene.shapes) & set(HOLED)  # the default's scenes keep their draws
    assert RenderParams.model_validate({"scene": {"shapes": ["tube", "frame"]}}).scene.shapes == ("tube", "frame")
    with pytest.raises(ValueError, match="unknown shape"):
        RenderParams.model_validate({"scene": {"shapes": ["donut"]}})


@pytest.mark.parametrize("name", sorted(HOLED))
def test_the_camera_sees_through_the_hole_and_the_face_around_it_faces_the_camera(name, tmp_path, bpy_render):
    """Axis turned to the camera (5 m down +y, 50 mm): the centre pixel is background, and the front face
    around the hole is masked in with normals straight at the camera."""
    obj = sphere(principled((0.6, 0.6, 0.6), 0.5, 0.0))
    obj.update(shape=name, rotation_deg=[90.0, 0.0, 0.0])
    spec = controlled_spec([obj], [point_light((3.0, -4.0, 2.0))])
    bpy_render(spec, tmp_path, tiny_params(resolution=96), verify=False)
    mask = read_exr(layout.map_path(tmp_path, "train_0000", 0, "mask"))[..., 0]
    normal = read_exr(layout.map_path(tmp_path, "train_0000", 0, "normal"))
    c = 48  # the axis, between pixels 47 and 48
    assert mask[c - 2 : c + 2, c - 2 : c + 2].max() == 0, "the hole is background"
    # on the front face, about 27 px a metre: the tube's annulus 0.55-1.0 m (its bore's wall shows 2-3 px
    # inside the rim), the frame's 0.45-0.8 m, and the frame's corners, where a round band would have ended
    r = {"tube": 21, "frame": 16}[name]
    face = [(c + dy, c + dx) for dy, dx in ((0, r), (0, -r - 1), (r, 0), (-r - 1, 0))]
    if name == "frame":
        face += [(c + 17, c + 17), (c - 18, c - 18)]
    for y, x in face:
        assert mask[y, x] == 1, (y, x)
        np.testing.assert_allclose(normal[y, x], [0.0, 0.0, 1.0], atol=2e-3)


def test_the_shapes_params_allow_are_the_shapes_the_renderer_builds():
    """The names live in two places (params cannot import the renderer): a shape allowed but not built
    would fail inside Blender; one built but not allowed could never be asked for."""
    from pilight.params import EXTRA_SHAPES

    assert set(EXTRA_SHAPES) == set(HOLED)
