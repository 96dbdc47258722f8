"""benchmarks/visibility_oracle.py: the camera projection and the screen-space shadow march it measures stage 2's
gains against. A box on a ground plane, seen from straight above, with a point light low on one side: the
ground behind the box is hidden from the light, the ground elsewhere is not, and an occluder thinner than the
gap does not hide."""

from __future__ import annotations

import numpy as np
import pytest

from fixtures.script_modules import load_benchmark

oracle = load_benchmark("visibility_oracle")

RES, F = 64, 64.0  # pixels; focal length in pixels
K = np.array([[F, 0.0, RES / 2], [0.0, F, RES / 2], [0.0, 0.0, 1.0]])
CAMERA_HEIGHT = 10.0
WORLD_FROM_CAMERA = np.eye(4)  # Blender's camera looks down -z: from (0, 0, 10) straight at the ground
WORLD_FROM_CAMERA[2, 3] = CAMERA_HEIGHT
BOX_HALF, BOX_HEIGHT = 0.5, 2.0
LIGHT = np.array([5.0, 0.0, 3.0])


def _position_buffer() -> np.ndarray:
    """World position of the first hit of each pixel's ray: the box's top face or the ground (z = 0)."""
    cols, rows = np.meshgrid(np.arange(RES) + 0.5, np.arange(RES) + 0.5)
    dx, dy = (cols - K[0, 2]) / F, (K[1, 2] - rows) / F  # ray direction (dx, dy, -1) in camera = world axes
    out = np.zeros((RES, RES, 3))
    for height in (0.0, BOX_HEIGHT):
        s = CAMERA_HEIGHT - height
        x, y = dx * s, dy * s
        on_box = (np.abs(x) < BOX_HALF) & (np.abs(y) < BOX_HALF)
        where = on_box if height > 0 else ~on_box
        out[where] = np.stack([x, y, np.full_like(x, height)], -1)[where]
    return out


def _pixel_of(point) -> tuple[int, int]:
    u, v, _ = oracle.project(np.asarray(point, dtype=float), K, WORLD_FROM_CAMERA)
    return int(v), int(u)


def test_projection_puts_each_surface_point_back_on_its_pixel():
    pos = _position_buffer()
    u, v, depth = oracle.project(pos, K, WORLD_FROM_CAMERA)
    cols, rows = np.meshgrid(np.arange(RES) + 0.5, np.arange(RES) + 0.5)
    assert np.abs(u - cols).max() < 1e-9 and np.abs(v - rows).max() < 1e-9
    assert depth.min() == pytest.approx(CAMERA_HEIGHT - BOX_HEIGHT) and depth.max() == pytest.approx(CAMERA_HEIGHT)
    # y is up in the camera, rows go down the image
    assert oracle.project(np.array([0.0, 1.0, 0.0]), K, WORLD_FROM_CAMERA)[1] < RES / 2


@pytest.mark.parametrize("directional", [False, True])
def test_ground_behind_the_box_is_hidden_from_the_light_and_the_rest_is_not(directional):
    pos = _position_buffer()
    ground = {"behind": (-1.0, 0.0, 0.0), "toward_light": (2.0, 0.0, 0.0), "beside": (-1.0, 2.5, 0.0)}
    pixels = np.array([_pixel_of(p) for p in ground.values()])
    x = pos[pixels[:, 0], pixels[:, 1]]
    if directional:
        targets = np.broadcast_to(LIGHT / np.linalg.norm(LIGHT), x.shape)
    else:
        targets = np.broadcast_to(LIGHT, x.shape)
    up = np.broadcast_to([0.0, 0.0, 1.0], x.shape)
    vis = oracle.march_visibility(
        pos, up, pixels, targets, K, WORLD_FROM_CAMERA, thickness=3.0, directional=directional
    )
    assert dict(zip(ground, vis.tolist())) == {"behind": 0.0, "toward_light": 1.0, "beside": 1.0}
    # the box is 2 m tall and the ray passes 1.1-1.75 m below its top: a surface 0.5 m thick hides nothing
    thin = oracle.march_visibility(
        pos, up, pixels, targets, K, WORLD_FROM_CAMERA, thickness=0.5, directional=directional
    )
    assert thin.tolist() == [1.0, 1.0, 1.0]


def test_point_irradiance_is_power_cos_over_four_pi_r_squared():
    x = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    n = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])  # the second faces away: nothing arrives
    e = oracle.point_irradiance([{"location": [0.0, 0.0, 2.0], "power": 100.0}], x, n)
    assert e[:, 0] == pytest.approx([100.0 / (4 * np.pi * 4.0), 0.0])


def _synthetic_renders(root, positions, alpha: float, beta: float) -> None:
    """One view of the box scene under two point lights (from +x and from -x), written as the render stage
    writes it, with true diffuse gains that follow g = alpha + beta vis exactly on a uniform gray ball's anchor."""
    import json

    import torch

    from pilight.data import layout
    from pilight.data.exr import write_exr
    from pilight.physics.calculated import diffuse_calculated
    from pilight.physics.envmap import light_level
    from pilight.relight import physics_first as pf

    sid, lights = "test_0000", [np.array([5.0, 0.0, 3.0]), np.array([-5.0, 0.0, 3.0])]
    pos = _position_buffer()
    positions.mkdir()
    np.save(positions / f"{sid}_v00.npy", pos.astype(np.float32))
    (root / sid).mkdir(parents=True)
    (root / "manifest.json").write_text(json.dumps({"scenes": [{"id": sid, "split": "test", "views": 1, "lights": 2}]}))
    (root / sid / "scene.json").write_text(
        json.dumps(
            {
                "cameras": [{"K": K.tolist(), "world_from_camera": WORLD_FROM_CAMERA.tolist()}],
                "lights": [[{"points": [{"location": loc.tolist(), "power": 1000.0}]} for loc in lights]],
                "spec": {"target": [0.0, 0.0, 0.0]},
            }
        )
    )
    ones = np.ones((RES, RES, 1), dtype=np.float32)
    maps = {"albedo": 0.5 * np.ones((RES, RES, 3)), "normal": np.tile([0.0, 0.0, 1.0], (RES, RES, 1))}
    maps |= {"roughness": 0.5 * ones, "metallic": 0 * ones, "mask": ones}
    for name, arr in maps.items():
        write_exr(layout.map_path(root, sid, 0, name), arr.astype(np.float32), half=name not in layout.FLOAT32_MAPS)
    ball = 0.5 * np.ones((32, 32, 3), dtype=np.float32)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).permute(2, 0, 1)[None]  # noqa: E731
    d_calc = diffuse_calculated(t(ball), t(maps["normal"]), t(ones), t(maps["metallic"]))
    eps = pf.EPS_LEVEL * light_level(t(ball)).view(1, 1, 1, 1)
    pixels = np.argwhere(np.ones((RES, RES), dtype=bool))
    up = np.broadcast_to([0.0, 0.0, 1.0], (len(pixels), 3))
    for li, loc in enumerate(lights):
        targets = np.broadcast_to(loc, (len(pixels), 3))
        vis = oracle.march_visibility(pos, up, pixels, targets, K, WORLD_FROM_CAMERA, thickness=3.0, directional=False)
        g = torch.from_numpy(alpha + beta * vis.reshape(RES, RES))[None, None].float()
        diffuse = pf.apply_gain(g, d_calc, eps)[0].permute(1, 2, 0).numpy()
        specular = 0.01 * np.ones((RES, RES, 3), dtype=np.float32)
        image = (maps["albedo"] * diffuse + specular).astype(np.float32)
        got = {"image": image, "diffuse": diffuse, "specular": specular, "ball": ball}
        for name, arr in got.items():
            write_exr(layout.map_path(root, sid, 0, name, li), arr, half=name not in layout.FLOAT32_MAPS)


def test_a_gain_that_follows_visibility_is_explained_by_the_visibility_law_and_not_by_the_level(tmp_path):
    renders, positions = tmp_path / "renders", tmp_path / "positions"
    _synthetic_renders(renders, positions, alpha=-0.8, beta=0.7)
    r = oracle.study(renders, positions, "test", "point", 3.0)
    assert r["pairs"] == 2 and 0.0 < r["shadowed_share"] < 0.5
    assert r["gain_explained_truth"] == pytest.approx(1.0) and r["change_r2_truth"] == pytest.approx(1.0, abs=1e-6)
    assert r["gain_explained_anchor"] == 0.0
    assert r["gain_explained_vis_law"] > 0.95 and r["gain_explained_level_plus_vis"] > 0.95
    assert r["gain_explained_level"] < r["gain_explained_vis_law"] - 0.05
    assert r["change_r2_vis_law"] > r["change_r2_level"] > r["change_r2_anchor"]


def test_the_effective_albedo_target_forms_the_true_image(tmp_path):
    """The stage's ratio form: A_x from input a, D_target = (I_b - S_b) / A_x, so A_x D_target + S_b = I_b."""
    renders, positions = tmp_path / "renders", tmp_path / "positions"
    _synthetic_renders(renders, positions, alpha=-0.8, beta=0.7)
    r = oracle.study(renders, positions, "test", "point", 3.0, albedo="effective")
    assert r["albedo"] == "effective" and r["pairs"] == 2
    assert r["change_r2_truth"] == pytest.approx(1.0, abs=1e-5) and r["change_r2_anchor"] < 0.99
