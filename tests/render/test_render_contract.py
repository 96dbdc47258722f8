"""The render stage's ground truth: the A*D+S contract, intrinsics, mask, normals and ball."""

from __future__ import annotations

import numpy as np
import pytest

from fixtures.render_scenes import controlled_spec, interior, point_light, principled, sphere, tiny_params
from pilight.data import layout
from pilight.data.exr import read_exr

pytestmark = pytest.mark.slow

RED = (0.8, 0.3, 0.2)


@pytest.fixture(scope="module")
def two_spheres(tmp_path_factory, bpy_render):
    """A constant Principled sphere (left) and a glass sphere (right), lit from the camera's right."""
    root = tmp_path_factory.mktemp("two_spheres")
    spec = controlled_spec(
        [
            sphere(principled(RED, 0.4, 0.3), (-0.9, 0, 0), 0.8),
            sphere({"type": "glass", "color": [0.9, 0.9, 0.9], "roughness": 0.0, "ior": 1.45}, (0.9, 0, 0), 0.8),
        ],
        [
            point_light((4.0, -3.0, 1.0)),
            point_light((-4.0, -3.0, 1.0), hdri={"name": "forest", "strength": 0.5, "rotation_deg": 30.0}),
        ],
    )
    raw, _ = bpy_render(spec, root)
    return root, raw


def _maps(root, light=None):
    names = layout.VIEW_MAPS if light is None else layout.LIGHT_MAPS + layout.OPTIONAL_LIGHT_MAPS
    return {n: read_exr(layout.map_path(root, "train_0000", 0, n, light)) for n in names}


@pytest.mark.parametrize("light", [0, 1])
def test_image_equals_albedo_times_diffuse_plus_specular(two_spheres, light):
    root, _ = two_spheres
    view, lit = _maps(root), _maps(root, light)
    residual = np.abs(lit["image"] - view["albedo"] * lit["diffuse"] - lit["specular"])
    assert (residual <= 1e-4 * (np.abs(lit["image"]) + 1e-3)).all(), residual.max()
    assert (lit["diffuse"] >= 0).all() and (lit["specular"] >= 0).all()


@pytest.mark.parametrize("light", [0, 1])
def test_specular_is_the_sum_of_the_non_diffuse_passes(two_spheres, light):
    """S is not a residual by fiat: it matches glossy + transmission + emission + background."""
    root, raw = two_spheres
    p = raw[light]
    rest = (
        p["Glossy Color"] * (p["Glossy Direct"] + p["Glossy Indirect"])
        + p["Transmission Color"] * (p["Transmission Direct"] + p["Transmission Indirect"])
        + p["Emission"]
        + p["Environment"]
    )
    s = _maps(root, light)["specular"]
    np.testing.assert_allclose(s, rest, rtol=1e-4, atol=1e-5)


def test_diffuse_colour_is_a_scalar_share_of_base_colour(two_spheres):
    """Cycles' Diffuse Color = k * Base Color with one k per pixel (the contract's premise)."""
    root, raw = two_spheres
    inner = interior(_maps(root)["mask"])
    ratio = raw[0]["Diffuse Color"][inner] / np.asarray(RED)
    assert inner.sum() > 50
    np.testing.assert_allclose(ratio, np.repeat(ratio.mean(axis=1, keepdims=True), 3, axis=1), rtol=1e-4)
    assert (ratio < 0.7 + 1e-6).all(), "metallic 0.3 leaves at most 70% to the diffuse lobe"


def test_constant_material_values_are_exact_on_interior_pixels(two_spheres):
    root, _ = two_spheres
    view = _maps(root)
    inner = interior(view["mask"])
    np.testing.assert_allclose(view["albedo"][inner], np.broadcast_to(RED, (inner.sum(), 3)), atol=1e-5)
    np.testing.assert_allclose(view["roughness"][inner], 0.4, atol=1e-3)  # float16 on disk
    np.testing.assert_allclose(view["metallic"][inner], 0.3, atol=1e-3)


def test_mask_excludes_glass_and_background(two_spheres):
    root, _ = two_spheres
    mask = _maps(root)["mask"][..., 0]
    h, w = mask.shape
    left, right = mask[:, : w // 2], mask[:, w // 2 :]
    assert left.sum() > 100, "the Principled sphere on the left is masked in"
    assert right.sum() == 0, "glass sphere and background are masked out"
    assert mask[0, 0] == 0


def test_normals_unit_camera_space(two_spheres):
    root, _ = two_spheres
    view = _maps(root)
    n, inner = view["normal"], interior(view["mask"])
    np.testing.assert_allclose(np.linalg.norm(n[inner], axis=-1), 1.0, atol=1e-3)
    assert (n[inner][:, 2] > 0).all(), "z points toward the camera on visible surfaces"
    assert (n[view["mask"][..., 0] == 0] == 0).all()
    # The left sphere's leftmost pixels face left (-x); its top faces up (+y).
    cols = np.where(inner.any(axis=0))[0]
    assert n[inner[:, cols[0]], cols[0], 0].mean() < -0.5
    rows = np.where(inner.any(axis=1))[0]
    assert n[rows[0], inner[rows[0]], 1].mean() > 0.5


@pytest.mark.parametrize("light, lit_side", [(0, "right"), (1, "left")])
def test_ball_brighter_on_the_side_facing_the_light(two_spheres, light, lit_side):
    root, _ = two_spheres
    lit = _maps(root, light)
    for name in ("ball", "ball_lambertian"):
        ball = lit[name].mean(axis=-1)
        w = ball.shape[1]
        left, right = ball[:, : w // 2].sum(), ball[:, w // 2 :].sum()
        assert (right > 1.5 * left) if lit_side == "right" else (left > 1.5 * right), (name, left, right)
        assert ball[0, 0] == 0 and ball[-1, -1] == 0, "outside the disk is 0"
        h = ball.shape[0]
        assert ball[h // 2, 1] > 0 or ball[h // 2, -2] > 0, "tangent to the borders"


def test_lambertian_ball_in_constant_light_is_half_the_ambient(tmp_path, bpy_render):
    """Under a constant environment of radiance a, a convex Lambertian surface has D = a, so the
    Lambertian ball (albedo 0.5) is 0.5 * a on the whole disk: the units E_diff = ball / 0.5 rest on."""
    a = 0.2
    spec = controlled_spec([sphere(principled(RED, 0.5, 0.0))], [{"points": [], "hdri": None, "ambient": a}])
    bpy_render(spec, tmp_path, tiny_params(cycles=dict(samples=64, adaptive_threshold=0.0)), verify=False)
    ball = _maps(tmp_path, 0)["ball_lambertian"]
    h, w, _ = ball.shape
    y, x = np.mgrid[0:h, 0:w]
    r = np.hypot((x + 0.5) / w * 2 - 1, (y + 0.5) / h * 2 - 1)
    disk = ball[r < 0.9]
    assert abs(disk.mean() / (0.5 * a) - 1) < 0.01  # Monte Carlo noise averages out over the disk
    assert np.quantile(np.abs(disk / (0.5 * a) - 1), 0.95) < 0.1
    # Cycles' pixel filter (1.5 px wide on each axis) reaches 0.75 * sqrt(2) px past the rim, no further.
    assert (ball[r > 1 + 2 * 1.07 / w] == 0).all()


def test_without_the_lambertian_ball_its_passes_are_not_rendered_and_the_gray_ball_is_unchanged(tmp_path, bpy_render):
    spec = controlled_spec([sphere(principled(RED, 0.5, 0.0))], [point_light((3.0, -2.0, 2.0))])
    bpy_render(spec, tmp_path / "with", verify=False, lambertian=True)
    _, handles = bpy_render(spec, tmp_path / "without", verify=False, lambertian=False)
    layer = handles["ball_scene"].view_layers[0]
    assert not (layer.use_pass_diffuse_direct or layer.use_pass_diffuse_indirect or layer.use_pass_diffuse_color)
    assert not layout.map_path(tmp_path / "without", "train_0000", 0, "ball_lambertian", 0).exists()
    gray = [layout.map_path(tmp_path / d, "train_0000", 0, "ball", 0).read_bytes() for d in ("with", "without")]
    assert gray[0] == gray[1]


@pytest.mark.parametrize("kind", ["subdivision", "displace", "bevel"])
def test_baked_modifier_geometry_is_snapped_to_the_grid(bpy_render, kind):
    """Threaded modifier evaluation may change the last bit of a position between runs; the
    baked mesh is snapped to 1 / POSITION_GRID so two runs give the same bytes."""
    import bpy

    from pilight.render import scene

    scene.reset_blender()
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.7)
    obj = bpy.context.active_object
    scene._modifier(obj, kind)
    scene.deterministic_normals(obj)
    assert not obj.modifiers and "pilight_displace" not in obj
    co = np.zeros(len(obj.data.vertices) * 3, np.float32)
    obj.data.vertices.foreach_get("co", co)
    scaled = co.astype(np.float64) * scene.POSITION_GRID
    assert np.array_equal(scaled, np.round(scaled))


def test_displacement_moves_vertices_along_the_normal(bpy_render):
    import bpy

    from pilight.render import scene

    scene.reset_blender()
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.7)
    obj = bpy.context.active_object
    scene._modifier(obj, "displace")
    scene.deterministic_normals(obj)
    co = np.zeros(len(obj.data.vertices) * 3, np.float32)
    obj.data.vertices.foreach_get("co", co)
    r = np.linalg.norm(co.reshape(-1, 3), axis=1)
    assert r.std() > 1e-3 and np.all(np.abs(r - 0.7) <= 0.5 * 0.12 + 0.01)  # |value - 0.5| * strength


# gabor at scale 2: its stripes (frequency 2) at 4 are finer than these 48 px resolve
@pytest.mark.parametrize("texture, scale", [("checker", 4.0), ("noise", 4.0), ("gradient", 4.0), ("gabor", 2.0)])
def test_shared_pattern_drives_colour_roughness_and_metal_together(tmp_path, bpy_render, texture, scale):
    """A textured material is two sub-materials along one mask, so every pixel (edges and
    anti-aliasing included) is one blend w of both: metallic (0 -> 1) gives w, and the albedo
    and roughness must then be the same blend."""
    a, b = (0.6, 0.1, 0.1), (0.1, 0.2, 0.7)
    material = {
        "type": "principled",
        "pattern": {"texture": texture, "scale": scale, "edge": 0.05},
        "base_color": {"values": [list(a), list(b)]},
        "roughness": {"values": [0.2, 0.8]},
        "metallic": {"values": [0.0, 1.0]},
    }
    bpy_render(controlled_spec([sphere(material, scale=1.2)], [point_light((4.0, -3.0, 1.0))]), tmp_path)
    view = _maps(tmp_path)
    inner = interior(view["mask"])
    w = view["metallic"][inner][:, :1]
    assert (w < 0.01).mean() > 0.1 and (w > 0.99).mean() > 0.1, "both sub-materials are visible"
    np.testing.assert_allclose(view["albedo"][inner], (1 - w) * np.asarray(a) + w * np.asarray(b), atol=2e-3)
    np.testing.assert_allclose(view["roughness"][inner][:, :1], 0.2 + 0.6 * w, atol=2e-3)


def test_camera_backdrop_is_the_same_behind_the_scene_for_every_light_while_the_hdri_still_lights_it(
    tmp_path, bpy_render
):
    """render.camera_backdrop: camera rays that miss the scene see the constant, whatever the light;
    the lighting HDRI still lights the sphere (its image differs between a dim and a bright HDRI)."""
    hdri = lambda strength: {"name": "forest", "strength": strength, "rotation_deg": 0.0}
    lights = [{"points": [], "hdri": hdri(0.3), "ambient": 0.02}, {"points": [], "hdri": hdri(1.0), "ambient": 0.05}]
    spec = controlled_spec([sphere(principled(RED, 0.5, 0.0), scale=0.6)], lights)
    bpy_render(
        spec, tmp_path, tiny_params(camera_backdrop=0.1, cycles=dict(samples=16, adaptive_threshold=0.0)), verify=False
    )
    view = _maps(tmp_path)
    a, b = _maps(tmp_path, 0)["image"], _maps(tmp_path, 1)["image"]
    mask = view["mask"].reshape(a.shape[:2])
    background = mask == 0
    corners = np.zeros_like(background)
    corners[:4, :4] = corners[:4, -4:] = True  # far from the sphere: no pixel-filter bleed
    np.testing.assert_allclose(a[corners], 0.1, rtol=1e-3)
    np.testing.assert_array_equal(a[corners], b[corners])
    inside = interior(view["mask"])
    assert b[inside].mean() > 1.5 * a[inside].mean()  # the brighter HDRI (and ambient) light the sphere more
    assert background.any()
