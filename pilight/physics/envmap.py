"""Light ball <-> diffuse environment map (PI-Light, "Diffuse Shading Loss").

Conventions (fixed by the render stage; every function in ``pilight.physics``
uses them):

* Camera space: x right, y up, z toward the camera.  Normal maps are
  ``B x 3 x H x W`` unit vectors in that frame; background normals are all
  zero and a mask ``B x 1 x H x W`` (1 = valid) removes them.
* Light ball image ``B x 3 x H x W``: orthographic camera with the scene
  camera's orientation, sphere tangent to the image borders.  Pixel
  (row i, col j) has centre ``x = 2(j+0.5)/W - 1``, ``y = 1 - 2(i+0.5)/H``
  (row 0 = top); inside the unit disk the sphere normal there is
  ``(x, y, sqrt(1 - x^2 - y^2))``.  These are exactly grid_sample's
  ``align_corners=False`` pixel centres with grid ``(x, -y)``.
* The gray ball has base colour ``BALL_ALBEDO = 0.5``, so the diffuse
  environment map is ``E_diff = ball / 0.5`` (paper: "unfolding [the diffuse
  ball] directly yields the energy-conserving diffuse environment map").
  Units of ``E_diff`` and of the diffuse shading ``D``: a Lambertian surface
  of albedo ``A`` has radiance ``A * D`` (Cycles: Diffuse Direct + Indirect
  light passes).  For an environment of radiance ``L(w)``,
  ``D(n) = 1/pi * integral L(w) max(0, n.w) dw``; a constant ``L`` gives ``D = L``.
* Lat-long ``E_diff``: ``ENV_H x ENV_W = 16 x 32`` (the paper's 32x16 map).
  Direction ``n`` -> ``u = atan2(n_x, n_z)/pi`` (columns, in [-1, 1]) and
  ``v = 2/pi * acos(n_y) - 1`` (rows, in [-1, 1], top row = ``n_y = +1``),
  looked up with ``grid_sample(..., align_corners=False)``.  The hemisphere
  visible on the ball (``n_z >= 0``) is ``|u| <= 0.5``, i.e. the middle 16
  columns; the other 16 columns are hidden from the ball.

Hidden-hemisphere texels (``envmap_valid = 0``): they cannot be observed, so
they are not guessed.  Each holds a copy of the nearest visible column of its
row (columns 0..7 copy column 8, columns 24..31 copy column 23).  The copy
matters only for lookups with ``0 <= |u| - 0.47 <= 0.03`` (normals within
~5 degrees of the silhouette), where bilinear interpolation then returns the
silhouette value instead of blending in zeros.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

ENV_H, ENV_W = 16, 32
BALL_ALBEDO = 0.5


def check_finite(x: torch.Tensor, what: str, where: torch.Tensor | None = None) -> None:
    """ValueError naming ``what`` and the first bad element if ``x`` holds NaN or Inf (only where
    ``where`` is true, when given).  One NaN texel or normal would otherwise spread silently
    through bilinear lookups into every shading value it touches, with the valid flag still 1."""
    bad = ~torch.isfinite(x)
    if where is not None:
        bad = bad & where
    if bool(bad.any()):
        first = [int(i) for i in bad.nonzero()[0]]
        raise ValueError(
            f"{what}: {int(bad.sum())} non-finite value(s) (NaN/Inf), the first at index {first} "
            f"of shape {tuple(x.shape)}"
        )


def _check_size(height: int, width: int, what: str) -> None:
    if height < 1 or width < 1:
        raise ValueError(f"{what}: size {height}x{width}; want at least 1x1")


def ball_normals(height: int, width: int, device=None, dtype=torch.float32):
    """Sphere normals ``1 x 3 x H x W`` and disk mask ``1 x 1 x H x W`` of a light-ball image."""
    _check_size(height, width, "light ball")
    x = (torch.arange(width, device=device, dtype=dtype) + 0.5) * (2.0 / width) - 1.0
    y = 1.0 - (torch.arange(height, device=device, dtype=dtype) + 0.5) * (2.0 / height)
    yy, xx = torch.meshgrid(y, x, indexing="ij")
    r2 = xx * xx + yy * yy
    inside = (r2 < 1.0).to(dtype)
    zz = torch.sqrt((1.0 - r2).clamp_min(0.0))
    n = torch.stack([xx, yy, zz], 0) * inside
    return n[None], inside[None, None]


def light_level(ball: torch.Tensor) -> torch.Tensor:
    """(B, 1, 1, 1): the ball's mean radiance over its disk / BALL_ALBEDO, i.e. the mean diffuse
    shading a sphere receives; the unit every map of this light is divided by. Floor 1e-6."""
    _, disk = ball_normals(*ball.shape[-2:], device=ball.device)
    mean = (ball.float() * disk[0]).sum((-1, -2)).mean(1) / disk.sum()
    return (mean / BALL_ALBEDO).clamp_min(1e-6)[:, None, None, None]


def envmap_directions(height: int = ENV_H, width: int = ENV_W, device=None, dtype=torch.float32):
    """Unit direction ``3 x h x w`` at each lat-long texel centre (inverse of ``normal_to_uv``)."""
    u = (torch.arange(width, device=device, dtype=dtype) + 0.5) * (2.0 / width) - 1.0
    v = (torch.arange(height, device=device, dtype=dtype) + 0.5) * (2.0 / height) - 1.0
    theta = (v + 1.0) * (math.pi / 2)  # polar angle from +y
    phi = u * math.pi  # azimuth from +z toward +x
    th, ph = torch.meshgrid(theta, phi, indexing="ij")
    return torch.stack([th.sin() * ph.sin(), th.cos(), th.sin() * ph.cos()], 0)


def normal_to_uv(normals: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Paper eq. UV = [1/pi atan(n_x/n_z), 2/pi acos(n_y) - 1] as a ``B x H x W x 2`` grid.

    Written so value and gradient stay finite everywhere: normals are
    normalised with 1e-6 inside the sqrt (zero normals stay zero), ``atan2``
    replaces ``atan(n_x/n_z)`` (n_z = 0 and the back hemisphere are fine) with
    ``n_z`` nudged to ``eps`` where both arguments vanish (atan2'(0,0) is 0/0),
    and ``n_y`` is clamped to ``[-1+eps, 1-eps]`` before ``acos`` (acos' is
    infinite at +-1).  Computed in >= fp32: eps=1e-6 is not representable
    next to 1 in half precision.
    """
    check_finite(normals, "normals")
    n = normals.float() if normals.dtype in (torch.float16, torch.bfloat16) else normals
    n = n * torch.rsqrt((n * n).sum(1, keepdim=True) + 1e-6)  # zero normals: grad <= 1e3, finite
    nx, ny, nz = n.unbind(1)
    nz = torch.where((nx == 0) & (nz == 0), torch.full_like(nz, eps), nz)
    u = torch.atan2(nx, nz) / math.pi
    v = torch.acos(ny.clamp(-1.0 + eps, 1.0 - eps)) * (2.0 / math.pi) - 1.0
    return torch.stack([u, v], -1)


def ball_to_envmap(
    ball: torch.Tensor, valid: torch.Tensor | None = None, height: int = ENV_H, width: int = ENV_W, eps: float = 1e-3
):
    """Unfold a gray light ball into ``(E_diff, envmap_valid)`` (``B x C x h x w``, ``B x 1 x h x w``).

    Paper: "given a gray ball ... we convert it into an environment map
    E in R^{32x16x3} ... unfolding it directly yields E_diff".  Each visible
    texel direction ``d`` is the ball normal at ball pixel ``(d_x, d_y)``, read
    with bilinear grid_sample.  ``valid`` (default: the analytic disk) is used
    as a normalised-convolution weight, so texels near the rim never average
    in the black background; sample points are also pulled half a pixel inside
    the rim, so with the default disk mask every visible texel has data.
    Visible texels with no valid ball pixel around them (user ``valid``
    holes) get value 0 and valid 0; hidden texels: see the module docstring.
    """
    b, _, h, w = ball.shape
    _check_size(h, w, "ball_to_envmap: light ball")  # (and r_max below would divide by zero)
    work = ball.float() if ball.dtype in (torch.float16, torch.bfloat16) else ball
    if valid is None:
        valid = ball_normals(h, w, ball.device, work.dtype)[1].expand(b, 1, h, w)
    valid = valid.to(work.dtype).expand(b, 1, h, w)
    check_finite(valid, "ball_to_envmap: valid mask")
    # Bad pixels outside the valid mask are what the mask is for: they are selected away below
    # (NaN * 0 is NaN, so multiplying by the mask would not remove them); inside it they are an error.
    check_finite(work, "ball_to_envmap: light ball pixels inside the valid mask", (valid > 0).expand_as(work))
    work = torch.where(valid > 0, work, torch.zeros((), dtype=work.dtype, device=work.device))
    d = envmap_directions(height, width, ball.device, work.dtype)
    xy = torch.stack([d[0], -d[1]], -1)  # grid_sample y points down the image
    r = xy.norm(dim=-1, keepdim=True)
    # half a pixel inside the rim: some bilinear neighbour is then always a disk pixel
    r_max = 1.0 - 1.0 / min(h, w)
    xy = xy * (r_max / r.clamp_min(r_max)).clamp(max=1.0)
    grid = xy[None].expand(b, height, width, 2)
    num = F.grid_sample(work * valid, grid, mode="bilinear", align_corners=False)
    den = F.grid_sample(valid, grid, mode="bilinear", align_corners=False)
    env = num / den.clamp_min(eps) / BALL_ALBEDO
    seen = (den > eps).to(work.dtype)
    # visible columns |u_c| <= 0.5, found on the host (no device sync)
    cols = [c for c in range(width) if abs((c + 0.5) * 2.0 / width - 1.0) <= 0.5]
    src = torch.arange(width, device=ball.device).clamp(cols[0], cols[-1])
    env = env.index_select(3, src)
    visible = torch.zeros(width, device=ball.device, dtype=work.dtype)
    visible[cols[0] : cols[-1] + 1] = 1
    env_valid = seen * visible
    return env.to(ball.dtype), env_valid.to(ball.dtype)
