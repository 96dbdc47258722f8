"""benchmarks/flip_average.py's mirror: an averaged prediction of a mirror-equivariant model is the
model's own (so the averaging measures the model, not a slip in the mirror), and a model that is not
equivariant gets symmetrised."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from fixtures.script_modules import load_benchmark

flip_average = load_benchmark("flip_average")


def central_dx(x: torch.Tensor) -> torch.Tensor:
    """Circular central difference along x: exactly negated (and mirrored) when x is mirrored."""
    return (x.roll(-1, -1) - x.roll(1, -1)) / 2


def equivariant_intrinsics(self, image, domains, sp, generator=None):
    """Normals tilt with the image's horizontal gradient, roughness is the image's brightness."""
    dx = central_dx(image[:, :1])
    normal = F.normalize(torch.cat([dx, torch.full_like(dx, 0.3), torch.ones_like(dx)], 1), dim=1)
    return {"normal": normal, "roughness": image[:, :1]}


def leaning_intrinsics(self, image, domains, sp, generator=None):
    """Every normal leans to +x and roughness ramps left to right, whatever the image."""
    B, _, H, W = image.shape
    ramp = torch.linspace(0, 1, W).expand(B, 1, H, W)
    return {
        "normal": F.normalize(torch.tensor([1.0, 0.0, 1.0]).view(1, 3, 1, 1).expand(B, 3, H, W), dim=1),
        "roughness": ramp,
    }


def test_an_equivariant_stage_one_is_unchanged():
    image = torch.rand(2, 3, 8, 12, generator=torch.Generator().manual_seed(0))
    plain = equivariant_intrinsics(None, image, ("normal", "roughness"), None)
    averaged = flip_average.averaged_intrinsics(equivariant_intrinsics)(None, image, ("normal", "roughness"), None)
    for d in plain:
        torch.testing.assert_close(averaged[d], plain[d], rtol=0, atol=1e-6)


def test_a_leaning_stage_one_is_symmetrised():
    image = torch.rand(1, 3, 4, 6)
    averaged = flip_average.averaged_intrinsics(leaning_intrinsics)(None, image, ("normal", "roughness"), None)
    torch.testing.assert_close(averaged["normal"][:, 0], torch.zeros(1, 4, 6))  # the x lean cancels
    torch.testing.assert_close(averaged["roughness"], torch.full((1, 1, 4, 6), 0.5))


def equivariant_relight(self, batch, sp, generator=None, intr=None, **kw):
    """The relit image: the input lit from the side the ball is brighter on, along the normals' x."""
    ball = batch["ball_b"]
    side = ball[..., : ball.shape[-1] // 2].mean((1, 2, 3)) - ball[..., ball.shape[-1] // 2 :].mean((1, 2, 3))
    relit = batch["image_a"] * (1 + side.view(-1, 1, 1, 1) * (intr or batch)["normal"][:, :1])
    return {"relit": relit, "diffuse": relit / 2}


def test_an_equivariant_stage_two_is_unchanged_and_the_anchor_untouched():
    g = torch.Generator().manual_seed(1)
    normal = F.normalize(torch.randn(2, 3, 8, 8, generator=g), dim=1)
    batch = {"image_a": torch.rand(2, 3, 8, 8, generator=g), "ball_b": torch.rand(2, 3, 4, 4, generator=g)}
    batch["normal"], batch["meta_a"] = normal, ["{}", "{}"]
    plain = equivariant_relight(None, batch, None)
    averaged = flip_average.averaged_relight(equivariant_relight)(None, batch, None)
    for k in plain:
        torch.testing.assert_close(averaged[k], plain[k], rtol=0, atol=1e-6)
    calls = []
    flip_average.averaged_relight(lambda *a, **kw: calls.append(kw) or plain)(None, batch, None, zero_gains=True)
    assert len(calls) == 1  # the physics anchor is graded as it is, never averaged
