"""The render contract under the base model's scene variety: stretched shapes (their normals),
gradient and gabor patterns, class materials, the procedural sky and the close-up wall (Blender renders
at 48-64 px: a few seconds in all, so not marked slow)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fixtures.render_scenes import controlled_spec, euler_xyz, interior, point_light, principled, sphere, tiny_params
from pilight.data import layout
from pilight.data.exr import read_exr
from pilight.params import RenderParams
from pilight.render.material_classes import pattern_material
from pilight.render.spec import SKY_IRRADIANCE, SKY_MODEL, scene_spec


def _maps(root, light=None):
    names = layout.VIEW_MAPS if light is None else layout.LIGHT_MAPS + layout.OPTIONAL_LIGHT_MAPS
    return {n: read_exr(layout.map_path(root, "train_0000", 0, n, light)) for n in names}


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cos = (a * b).sum(-1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _camera_rays(handles):
    """Per pixel: the camera's centre, the ray through the pixel's centre (world), and world_from_camera."""
    from pilight.render import scene

    cam = scene.camera_json(handles["camera"], handles["scene"])
    K, M = np.asarray(cam["K"]), np.asarray(cam["world_from_camera"])
    res = handles["scene"].render.resolution_x
    v, u = np.mgrid[0:res, 0:res] + 0.5
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], -(v - K[1, 2]) / K[1, 1], -np.ones_like(u)], -1)  # y up, -z ahead
    return M[:3, 3], d_cam @ M[:3, :3].T, M[:3, :3]


def test_stretched_sphere_has_the_ellipsoids_unit_normals(tmp_path, bpy_render):
    """An ellipsoid's normal is M^-T M^-1 x (M = R S): the normal pass of a stretched, rotated
    sphere must be that, not the sphere's radial normal carried along with the vertices."""
    stretch, rotation, size = [1.5, 1.0, 0.6], [20.0, 0.0, 35.0], 0.8
    obj = sphere(principled((0.6, 0.6, 0.6), 0.5, 0.0), scale=size)
    obj.update(stretch=stretch, rotation_deg=rotation)
    spec = controlled_spec([obj], [point_light((4.0, -3.0, 1.0))])
    _, handles = bpy_render(spec, tmp_path, tiny_params(resolution=64), verify=False)
    view = _maps(tmp_path)
    inner = interior(view["mask"])
    assert inner.sum() > 300
    eye, rays, world_from_camera = _camera_rays(handles)
    M = euler_xyz(rotation) @ np.diag(size * np.asarray(stretch))
    M_inv = np.linalg.inv(M)
    a, b = M_inv @ eye, rays[inner] @ M_inv.T  # the ray in the unit sphere's frame: a + t b
    qa, qb, qc = (b * b).sum(-1), 2 * b @ a, a @ a - 1.0
    t = (-qb - np.sqrt(qb**2 - 4 * qa * qc)) / (2 * qa)  # the nearer hit
    x = eye + t[:, None] * rays[inner]
    n_world = x @ (M_inv.T @ M_inv).T
    analytic = n_world @ world_from_camera  # camera space, as the normal map
    rendered = view["normal"][inner]
    np.testing.assert_allclose(np.linalg.norm(rendered, axis=-1), 1.0, atol=1e-3)
    error = _angle_deg(rendered, analytic)
    # A 48 x 24 UV sphere's smooth normals: measured median 0.35, 99% 0.94, max 1.5 degrees off.
    assert np.median(error) < 0.75 and np.quantile(error, 0.99) < 2.0, (np.median(error), error.max())
    radial = _angle_deg(rendered, x @ world_from_camera)  # the sphere's radial normals, carried along
    assert np.median(radial) > 8.0, "the test tells the ellipsoid's normals from the sphere's"


def _sky(direction, irradiance: float) -> dict:
    d = np.asarray(direction, dtype=np.float64)
    return {
        "model": SKY_MODEL,
        "sun_direction": (d / np.linalg.norm(d)).tolist(),
        "strength": irradiance / SKY_IRRADIANCE,
        "air": 1.0,
        "aerosol": 1.0,
        "sun_intensity": 1.0,
    }


SUN = np.array([3.0, -4.0, 3.0]) / np.linalg.norm([3.0, -4.0, 3.0])  # camera's right, in front, 31 degrees up
IRRADIANCE = 5.0  # the point light's irradiance at the scene centre, and so the sky's
BACKDROP = 0.05


@pytest.fixture(scope="module")
def variety_scene(tmp_path_factory, bpy_render):
    """A stretched sphere of painted metal (gabor mask) and a stretched cube of two-tone plastic
    (gradient), lit by the sky (light 0) and by a point light from the sun's direction (light 1)."""
    root = tmp_path_factory.mktemp("variety")
    painted_metal = pattern_material(
        ([0.9, 0.7, 0.31], 0.3, 1.0),
        ([0.1, 0.3, 0.7], 0.6, 0.0),
        {"texture": "gabor", "scale": 3.0, "edge": 0.05},
        **{"class": "metal"},
    )
    two_tone = pattern_material(
        ([0.7, 0.1, 0.1], 0.4, 0.0),
        ([0.9, 0.8, 0.1], 0.4, 0.0),
        {"texture": "gradient", "scale": 2.0, "edge": 0.05},
        **{"class": "plastic"},
    )
    ball = sphere(painted_metal, (-0.8, 0.0, 0.0), 0.55)
    ball.update(stretch=[1.2, 0.8, 1.5], rotation_deg=[10.0, 20.0, 30.0])
    box = sphere(two_tone, (0.85, 0.0, 0.0), 0.45)
    box.update(shape="cube", stretch=[1.4, 1.0, 0.7], rotation_deg=[0.0, 0.0, 25.0])
    point = point_light(6.0 * SUN, power=4 * math.pi * 36.0 * IRRADIANCE)  # irradiance = P / (4 pi d^2)
    lights = [{"points": [], "hdri": None, "sky": _sky(SUN, IRRADIANCE), "ambient": 0.02}, point]
    spec = controlled_spec([ball, box], lights)
    raw, handles = bpy_render(spec, root, tiny_params(camera_backdrop=BACKDROP))
    return root, raw, handles


@pytest.mark.parametrize("light", [0, 1])
def test_contract_holds_under_the_sky_and_on_stretched_class_materials(variety_scene, light):
    root, raw, _ = variety_scene
    view, lit = _maps(root), _maps(root, light)
    residual = np.abs(lit["image"] - view["albedo"] * lit["diffuse"] - lit["specular"])
    assert (residual <= 1e-4 * (np.abs(lit["image"]) + 1e-3)).all(), residual.max()
    assert (lit["diffuse"] >= 0).all() and (lit["specular"] >= 0).all()
    p = raw[light]
    rest = (
        p["Glossy Color"] * (p["Glossy Direct"] + p["Glossy Indirect"])
        + p["Transmission Color"] * (p["Transmission Direct"] + p["Transmission Indirect"])
        + p["Emission"]
        + p["Environment"]
    )
    np.testing.assert_allclose(lit["specular"], rest, rtol=1e-4, atol=1e-5)


def test_normals_mask_and_patterns_of_the_variety_scene(variety_scene):
    root, _, _ = variety_scene
    view = _maps(root)
    mask, n = view["mask"][..., 0], view["normal"]
    inner = interior(view["mask"])
    w = mask.shape[1]
    assert mask[:, : w // 2].sum() > 100 and mask[:, w // 2 :].sum() > 100, "both objects are masked in"
    assert mask[0, 0] == 0 and (n[mask == 0] == 0).all()
    np.testing.assert_allclose(np.linalg.norm(n[inner], axis=-1), 1.0, atol=1e-3)
    assert (n[inner][:, 2] > 0).all()
    metal = view["metallic"][inner][:, 0]
    assert (metal > 0.99).mean() > 0.05 and (metal < 0.01).mean() > 0.3, "painted metal shows metal and paint"
    albedo = view["albedo"][inner]
    assert albedo.min() >= 0.03 - 1e-3 and albedo.max() <= 0.9 + 1e-3


def test_camera_rays_see_the_backdrop_not_the_sky(variety_scene):
    root, _, _ = variety_scene
    corners = np.zeros(_maps(root)["mask"].shape[:2], bool)
    corners[:3, :3] = corners[:3, -3:] = True
    for light in (0, 1):
        np.testing.assert_allclose(_maps(root, light)["image"][corners], BACKDROP, rtol=1e-3)


def _ball_normals(shape) -> np.ndarray:
    """Camera-space normals of the orthographic ball's pixels within 0.95 of its radius (0 elsewhere)."""
    h, w = shape
    y, x = np.mgrid[0:h, 0:w]
    u, v = (x + 0.5) / w * 2 - 1, 1 - (y + 0.5) / h * 2
    n = np.stack([u, v, np.sqrt(np.clip(1 - u**2 - v**2, 0, 1))], -1)
    return np.where((u**2 + v**2 < 0.95**2)[..., None], n, 0.0)


def _peak_direction(ball: np.ndarray) -> np.ndarray:
    """The ball's brightest direction (camera space), from its pixels weighted by radiance^4."""
    peak = (_ball_normals(ball.shape) * (ball**4)[..., None]).sum((0, 1))
    return peak / np.linalg.norm(peak)


def test_the_ball_sees_the_sky_with_its_sun_where_the_point_light_is(variety_scene):
    """The light ball shares the world: under the sky it is lit from the sun's direction, as the
    point light from the same direction lights it, at a like level (SKY_IRRADIANCE)."""
    root, _, handles = variety_scene
    from pilight.render import scene

    sun_cam = SUN @ np.asarray(scene.camera_rotation(handles))
    sky, point = (_maps(root, light)["ball_lambertian"].mean(-1) for light in (0, 1))
    for ball in (sky, point):
        assert _angle_deg(_peak_direction(ball), sun_cam) < 20.0
        assert ball[0, 0] == 0 and ball[-1, -1] == 0, "outside the disk is 0 (film transparent)"
    assert 0.8 < sky.max() / point.max() < 1.6, (sky.max(), point.max())
    normals = _ball_normals(sky.shape)
    shade = (normals @ sun_cam < -0.3) & (np.linalg.norm(normals, axis=-1) > 0)
    assert sky[shade].mean() > 2 * point[shade].mean(), "the sky's dome lights the side the sun does not"


def test_closeup_wall_stands_where_the_spec_puts_it_and_faces_the_camera(tmp_path, bpy_render):
    """A drawn close-up view and wall around a gray sphere: every pixel whose ray misses the sphere sees
    the wall (on the mask, its albedo, its normal: the spec's rotation in camera space), none a floor."""
    p = RenderParams(scene={"room_fraction": 0.0, "closeup_fraction": 1.0})
    drawn = next(s for s in (scene_spec(p, 42, "train", i) for i in range(50)) if s["backdrop"] is not None)
    wall = drawn["backdrop"] | {"material": principled((0.3, 0.5, 0.7), 0.6, 0.0)}
    size = drawn["objects"][0]["scale"]
    view = drawn["views"][0]
    spec = controlled_spec(
        [sphere(principled((0.6, 0.6, 0.6), 0.5, 0.0), scale=size)],
        [point_light(np.asarray(view["location"]) + [0.0, 0.0, 1.0])],
        view=view,
    ) | {"kind": "closeup", "backdrop": wall}
    _, handles = bpy_render(spec, tmp_path, tiny_params(resolution=48), verify=False)
    maps = _maps(tmp_path)
    eye, rays, world_from_camera = _camera_rays(handles)
    d = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    b = d @ eye
    misses = b**2 - (eye @ eye - (1.02 * size) ** 2) < 0  # the ray passes the sphere by 2% of its radius
    misses &= interior(misses[..., None].astype(np.float32))  # away from the silhouette
    assert misses.sum() > 200, "the drawn framing leaves wall around the subject"
    normal = euler_xyz(wall["rotation_deg"]) @ np.array([0.0, 0.0, 1.0]) @ world_from_camera
    error = _angle_deg(maps["normal"][misses], np.broadcast_to(normal, (int(misses.sum()), 3)))
    assert error.max() < 1.0, error.max()
    assert (maps["mask"][misses] > 0.5).all()
    np.testing.assert_allclose(
        maps["albedo"][misses], np.broadcast_to((0.3, 0.5, 0.7), (int(misses.sum()), 3)), atol=0.02
    )
