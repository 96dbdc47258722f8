"""The light-following measures: what copying and the truth score, and the conventions they rest on."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from pilight.eval.light_following import (
    PROBE_LIGHTS,
    ChangeR2,
    cross_light,
    direction_from_angles,
    direction_score,
    linearity,
    lr_asymmetry,
    probe_balls,
    probe_batch,
    probe_key,
    probe_scores,
    select_probes,
    sides_visible,
)
from pilight.physics.calculated import diffuse_calculated, specular_calculated
from pilight.physics.shading import ball_from_direction


def _sphere_normals(size=32):
    y, x = torch.meshgrid(
        1 - (torch.arange(size) + 0.5) * 2 / size, (torch.arange(size) + 0.5) * 2 / size - 1, indexing="ij"
    )
    r2 = x * x + y * y
    inside = (r2 < 0.8).float()
    n = torch.stack([x, y, (1 - r2).clamp_min(0).sqrt()]) * inside
    return n[None], inside[None, None]


def test_change_r2_is_zero_for_copying_one_for_the_truth_and_negative_for_the_wrong_way():
    g = torch.Generator().manual_seed(0)
    u_in, u_gt = torch.rand(2, 3, 8, 8, generator=g), torch.rand(2, 3, 8, 8, generator=g)
    mask = (torch.rand(2, 1, 8, 8, generator=g) > 0.5).float()
    for pred, expected in ((u_in, 0.0), (u_gt, 1.0), (2 * u_in - u_gt, -3.0)):
        r = ChangeR2()
        r.update(pred[:1], u_gt[:1], u_in[:1], mask[:1])
        r.update(pred[1:], u_gt[1:], u_in[1:], mask[1:])  # pooled over batches
        got = r.compute()
        assert got["full"] == pytest.approx(expected, abs=1e-6) and got["mask"] == pytest.approx(expected, abs=1e-6)
    half = ChangeR2()
    half.update(0.5 * (u_in + u_gt), u_gt, u_in, mask)
    assert half.compute()["full"] == pytest.approx(0.75)  # half the change: 1 - 1/4


def test_the_pair_median_is_the_typical_pair_where_one_pair_decides_the_pooled_figure():
    """Three pairs relit perfectly but for one whose true change is large and predicted the wrong way:
    pooled, that pair sinks the figure; the median over pairs is a perfect pair's 1.0. A pair whose
    mask does not change is left out of the median (its own change_r2 is undefined)."""
    g = torch.Generator().manual_seed(1)
    u_in = torch.rand(5, 3, 8, 8, generator=g) * 0.5
    u_gt = u_in + torch.tensor([0.01, 0.01, 0.01, 0.4, 0.0])[:, None, None, None]
    pred = u_gt.clone()
    pred[3] = u_in[3] - 0.4  # the big change, the wrong way: that pair's change_r2 is 1 - 4 = -3
    r = ChangeR2()
    r.update(pred[:2], u_gt[:2], u_in[:2], torch.ones(2, 1, 8, 8))
    r.update(pred[2:], u_gt[2:], u_in[2:], torch.ones(3, 1, 8, 8))
    got = r.compute()
    assert got["mask"] == pytest.approx(1 - 4 * 0.16 / (3 * 1e-4 + 0.16), abs=1e-6)
    assert got["mask_pair_median"] == pytest.approx(1.0)
    assert len(r.pairs) == 4 and min(r.pairs) == pytest.approx(-3.0)
    assert ChangeR2().compute()["mask_pair_median"] is None


def test_directions_follow_the_camera_convention_and_light_the_facing_side():
    np.testing.assert_allclose(direction_from_angles(0, 0), [0, 0, 1], atol=1e-7)
    np.testing.assert_allclose(direction_from_angles(90, 0), [1, 0, 0], atol=1e-7)
    np.testing.assert_allclose(direction_from_angles(0, 90), [0, 1, 0], atol=1e-7)
    n, mask = _sphere_normals()
    right = ball_from_direction(direction_from_angles(60, 30), size=32)
    left = ball_from_direction(direction_from_angles(-60, 30), size=32)
    d_r = diffuse_calculated(right, n, mask, torch.zeros_like(mask))
    d_l = diffuse_calculated(left, n, mask, torch.zeros_like(mask))
    a_r, a_l = lr_asymmetry(d_r, n, mask), lr_asymmetry(d_l, n, mask)
    assert a_r > 0.3 and a_l < -0.3
    assert direction_score(torch.cat([a_r, a_l]), torch.cat([a_l, a_r])) == 0.5


def test_linearity_is_the_median_ratio_and_ignores_dark_pixels():
    x = torch.rand(1, 3, 8, 8) + 0.1
    mask = torch.ones(1, 1, 8, 8)
    assert linearity(x, 2 * x, mask) == pytest.approx(2.0)
    y = 2 * x
    y[..., :2] = 100.0  # a quarter of the pixels: the median does not move
    assert linearity(x, y, mask) == pytest.approx(2.0)
    assert linearity(torch.zeros_like(x), x, mask) is None


def test_probe_balls_keep_the_target_exposure_and_double_it():
    target = ball_from_direction([0.3, 0.5, 0.8], intensity=3.0, size=16)
    balls = probe_balls(target)
    assert balls["left"].mean() == pytest.approx(float(target.mean()), rel=1e-5)
    torch.testing.assert_close(balls["target_x2"], 2 * target)
    assert balls["right"][..., :8].sum() < balls["right"][..., 8:].sum()  # lit from camera-right


def test_probes_are_distinct_input_images_of_cross_light_pairs_with_both_sides_visible():
    n, mask = _sphere_normals(8)
    flat = torch.zeros_like(n)
    flat[:, 2] = 1
    meta = lambda light: json.dumps({"scene": "s", "view": 0, "light": light})
    batch = {
        "key": ["a", "b", "c", "d"],
        "meta_a": [meta(0), meta(0), meta(1), meta(1)],
        "meta_b": [meta(0), meta(1), meta(0), meta(0)],
        "normal": torch.cat([n, n, flat, n]),
        "mask": mask.expand(4, -1, -1, -1),
    }
    assert sides_visible(batch["normal"], batch["mask"]).tolist() == [True, True, False, True]
    probes = select_probes([batch], 5)
    assert [p["key"] for p in probes] == [["b"], ["d"]]  # a: identity pair; c: faces the camera only


def test_specular_lookup_is_zero_for_a_lambertian_ball_and_scaled_by_metal_fresnel():
    n, mask = _sphere_normals()
    lamb = ball_from_direction([0, 0, 1], size=32)
    zeros = torch.zeros_like(mask)
    assert specular_calculated(lamb, lamb, n, mask, torch.full_like(n, 0.5), zeros).abs().max() == 0
    gray = lamb + 0.1 * lamb**4  # a highlight where the ball faces the light
    s_diel = specular_calculated(gray, lamb, n, mask, torch.full_like(n, 0.5), zeros)
    s_metal = specular_calculated(gray, lamb, n, mask, torch.full_like(n, 0.5), torch.ones_like(mask))
    assert s_diel.max() > 0
    torch.testing.assert_close(s_metal, s_diel * 0.5 / 0.04 * 0.5)


def _probe(scene: str = "s", light: int = 0, size: int = 16) -> dict:
    n, mask = _sphere_normals(size)
    meta = json.dumps({"scene": scene, "view": 0, "light": light})
    return {
        "key": [f"{scene}_v00_l{light:02d}_to_l01"],
        "meta_a": [meta],
        "meta_b": [meta],
        "normal": n,
        "mask": mask,
        "albedo": torch.full((1, 3, size, size), 0.5) * mask,
        "metallic": torch.zeros(1, 1, size, size),
        "image_a": torch.rand(1, 3, size, size),
        "ball_b": ball_from_direction([0.2, 0.6, 0.7], intensity=2.0, size=8),
        "ball_lambertian_b": ball_from_direction([0.2, 0.6, 0.7], intensity=1.5, size=8),
    }


def test_probe_batch_holds_the_image_under_each_probe_light_with_matching_twins():
    probe = _probe()
    batch = probe_batch(probe)
    assert batch["ball_b"].shape[0] == len(PROBE_LIGHTS) and batch["key"] == probe["key"] * len(PROBE_LIGHTS)
    i = {n: k for k, n in enumerate(PROBE_LIGHTS)}
    torch.testing.assert_close(batch["ball_b"][i["target_x2"]], 2 * probe["ball_b"][0])
    torch.testing.assert_close(batch["ball_lambertian_b"][i["target_x2"]], 2 * probe["ball_lambertian_b"][0])
    torch.testing.assert_close(
        batch["ball_lambertian_b"][i["left"]], batch["ball_b"][i["left"]]
    )  # analytic: no highlight
    torch.testing.assert_close(batch["image_a"][3], probe["image_a"][0])


def _relit_by(shade, probes):
    """Probe outputs (probe_key -> {"relit": H x W x 3}) of a model whose relit image is shade(batch)."""
    out = {}
    for p in probes:
        b = probe_batch(p)
        relit = shade(b)
        for k, light in enumerate(PROBE_LIGHTS):
            out[probe_key(p, light)] = {"relit": relit[k].permute(1, 2, 0).numpy()}
    return out


def test_probe_scores_physics_follows_the_light_and_copying_does_not():
    probes = [_probe("s1"), _probe("s2")]
    physics = _relit_by(
        lambda b: b["albedo"] * diffuse_calculated(b["ball_b"], b["normal"], b["mask"], b["metallic"]), probes
    )
    scores = probe_scores(physics, probes)
    assert scores["probes"] == 2 and scores["direction"] == 1.0
    assert scores["linearity"] == pytest.approx(2.0, rel=1e-5)
    copying = probe_scores(_relit_by(lambda b: b["image_a"].clone(), probes), probes)
    assert copying["direction"] == 0.0 and copying["linearity"] == pytest.approx(1.0)
    assert probe_scores({}, [])["direction"] is None


def test_cross_light_keeps_only_pairs_whose_lights_differ():
    meta = lambda light: json.dumps({"scene": "s", "view": 0, "light": light})
    batch = {"key": ["aa", "ab"], "meta_a": [meta(0), meta(0)], "meta_b": [meta(0), meta(1)], "x": torch.arange(2)}
    out = cross_light(batch)
    assert out["key"] == ["ab"] and out["x"].tolist() == [1]
    assert cross_light({"key": ["aa"], "meta_a": [meta(0)], "meta_b": [meta(0)], "x": torch.arange(1)}) is None
