"""The light a photo was taken under, estimated from the photo and its intrinsics: a Lambertian ball.

Physics-first relighting with the effective albedo (pilight.relight.physics_first) needs the input's
own light. Rendered data carry its ball; a photo does not. On diffuse pixels a photo is I = A D(n),
and the diffuse shading of any distant light is, to within a few percent, a second-order spherical
harmonic expansion of the normal (Ramamoorthi & Hanrahan 2001, "An efficient representation for
irradiance environment maps"):

    D(n) = sum_k c_k Y_k(n),   Y = (1, x, y, z, xy, yz, xz, x^2 - y^2, 3 z^2 - 1)

so the nine c_k per channel follow from a least-squares fit of I to A Y(n) over the mask's dielectric
pixels. The estimate is returned as the gray ball of that light, BALL_ALBEDO max(D(n), 0) at each
ball normal, so it enters the same lookups as a rendered ball. It knows nothing of highlights (its
Lambertian twin is itself) or of light from behind the visible hemisphere.

Two uses, two fits. The SHADING at the image's own normals (the effective albedo,
pilight.relight.physics_first) is an interpolation, and the nine terms serve it best. The LEVEL of
the light (the ball's mean, which sets a relative light's strength, pilight.relight.intensity) is an
extrapolation over the whole ball, and there the nine terms mislead: a photo's normals face the
camera and cover a narrow cone, where the second-order terms are nearly collinear with the first, and
fitted they bend the ball outside the cone. ``estimate_source_balls(level=True)`` fits first order (the
four before the bar, ~88 % of a distant light's diffuse shading) with a ridge for the level. On the
test pairs of three splits the physics anchor's relative-tier change_r2 on the mask rose from -0.13 /
-0.10 / -0.34 to +0.13 / +0.15 / about +0.1 with stage-1 maps, the absolute and scale-invariant tiers
unchanged (they do not use the level); docs/pipeline/stage2.md, "The source light's level".
"""

from __future__ import annotations

import torch

from .envmap import BALL_ALBEDO, ball_normals
from .precision import in_full_precision

MIN_PIXELS = 32  # fewer usable pixels than this cannot pin nine coefficients down
RIDGE = 1e-6  # Tikhonov weight, relative to the normal matrix's mean diagonal (front-facing normals
# leave the basis nearly collinear)
LEVEL_TERMS = 4  # the level's fit: first order, 1, x, y, z (module docstring)
LEVEL_RIDGE = 1e-2  # its ridge: even four terms are nearly collinear on a narrow cone (it shrinks a clean
# light's level by ~3 %; 1e-6 let it drift)
METALLIC_MAX = 0.5  # pixels more metallic than this have no diffuse lobe to fit
ALBEDO_MIN = 0.02  # black pixels carry no shading


class SourceLightError(ValueError):
    """The photo has too few usable pixels to estimate its light."""


def sh_basis(normal: torch.Tensor) -> torch.Tensor:
    """(B, 9, H, W): the nine real SH polynomials (unnormalised) of unit normals (B, 3, H, W)."""
    x, y, z = normal[:, 0], normal[:, 1], normal[:, 2]
    return torch.stack([torch.ones_like(x), x, y, z, x * y, y * z, x * z, x * x - y * y, 3 * z * z - 1], 1)


def fit_diffuse_sh_found(
    image: torch.Tensor,
    albedo: torch.Tensor,
    normal: torch.Tensor,
    mask: torch.Tensor,
    metallic: torch.Tensor | None = None,
    *,
    terms: int = 9,
    ridge: float = RIDGE,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, 3, 9) coefficients c with image ~ albedo * sum_k c_k Y_k(normal) on usable pixels (masked,
    albedo above ALBEDO_MIN, and dielectric (metallic < METALLIC_MAX) unless fewer than MIN_PIXELS
    are), and (B,) usable-pixel counts; an image with fewer than MIN_PIXELS keeps c = 0. Only the
    first ``terms`` are fitted (4: first order, for the level); the rest stay 0."""
    usable = (mask[:, 0] > 0.5) & (albedo.float().mean(1) > ALBEDO_MIN)
    dielectric = usable & (metallic[:, 0] < METALLIC_MAX) if metallic is not None else usable
    basis = sh_basis(normal.float())[:, :terms]
    out = torch.zeros(image.shape[0], 3, 9)
    counts = torch.zeros(image.shape[0], dtype=torch.long)
    for i in range(image.shape[0]):
        # Dielectric pixels when there are enough; an all-metal image is fitted on every usable pixel
        # (its highlights then stand in for the light: the best this image says about it).
        sel = dielectric[i] if int(dielectric[i].sum()) >= MIN_PIXELS else usable[i]
        counts[i] = int(sel.sum())
        if counts[i] < MIN_PIXELS:
            continue
        y_k = basis[i][:, sel].T.double()  # (P, terms)
        for c in range(3):
            x = albedo[i, c][sel].double()[:, None] * y_k
            gram = x.T @ x
            gram = gram + ridge * gram.diagonal().mean() * torch.eye(terms, dtype=gram.dtype)
            out[i, c, :terms] = torch.linalg.solve(gram, x.T @ image[i, c][sel].double()).float()
    return out, counts


def fit_diffuse_sh(
    image: torch.Tensor,
    albedo: torch.Tensor,
    normal: torch.Tensor,
    mask: torch.Tensor,
    metallic: torch.Tensor | None = None,
) -> torch.Tensor:
    """fit_diffuse_sh_found's coefficients; SourceLightError naming the first image with too few pixels."""
    coeffs, counts = fit_diffuse_sh_found(image, albedo, normal, mask, metallic)
    short = (counts < MIN_PIXELS).nonzero().flatten().tolist()
    if short:
        i = short[0]
        raise SourceLightError(
            f"image {i}: {int(counts[i])} usable pixels (masked, dielectric, albedo > "
            f"{ALBEDO_MIN}); at least {MIN_PIXELS} are needed to estimate its light"
        )
    return coeffs


def sh_ball(coeffs: torch.Tensor, size: int) -> torch.Tensor:
    """(B, 3, size, size): the gray ball that a light of diffuse shading sum_k c_k Y_k shows."""
    n, inside = ball_normals(size, size)
    d = torch.einsum("bck,khw->bchw", coeffs, sh_basis(n)[0]).clamp_min(0.0)
    return BALL_ALBEDO * d * inside


def estimate_source_ball(
    image: torch.Tensor,
    albedo: torch.Tensor,
    normal: torch.Tensor,
    mask: torch.Tensor,
    size: int,
    metallic: torch.Tensor | None = None,
) -> torch.Tensor:
    """The Lambertian ball of the light ``image`` was lit by (module docstring), (B, 3, size, size).
    SourceLightError when an image has too few usable pixels."""
    return sh_ball(fit_diffuse_sh(image, albedo, normal, mask, metallic), size)


@in_full_precision
def estimate_source_balls(
    image: torch.Tensor,
    albedo: torch.Tensor,
    normal: torch.Tensor,
    mask: torch.Tensor,
    size: int,
    metallic: torch.Tensor | None = None,
    *,
    level: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per image: (balls (B, 3, size, size), found (B,) bool); an image with too few usable pixels
    gets a black ball and found = False, for the caller to handle (none is guessed). ``level``: the
    LEVEL's fit (first order, LEVEL_RIDGE; module docstring), the ball whose light_level is the input
    light's level for relative intensity; else the shading's (nine terms)."""
    fit = {"terms": LEVEL_TERMS, "ridge": LEVEL_RIDGE} if level else {}
    coeffs, counts = fit_diffuse_sh_found(image, albedo, normal, mask, metallic, **fit)
    # one image at a time: a batched einsum sums in another order, and the relit outputs' bytes would move
    return torch.cat([sh_ball(c[None], size) for c in coeffs]), counts >= MIN_PIXELS
