"""The paper's physics terms of stage 2, on decoded outputs (paper, final loss):

    L = L_vpred + (1/max(t, t_min)) (lambda_ds L_DS + lambda_ps L_PS + lambda_rec L_rec)

* L_DS = MSE(D_calc, D_pred) on the mask, D_calc = diffuse_shading(unfold(target ball), N_gt, m).
  ADAPTATION: our render contract defines D = k * L_diffuse with k = (1 - metallic)(1 - specular
  layer albedo) so that A*D + S is exact, while D_calc is Lambertian shading (k = 1). We use
  D_calc * (1 - metallic): metals (D = 0 in our ground truth) are not pulled toward Lambertian
  shading. The dielectric specular-layer factor (a few %) is not modelled.
* L_PS = MSE(I_relit, A * D_pred + S_pred), with the GROUND-TRUTH albedo (the targets satisfy the
  identity exactly with it, so L_PS never fights L_vpred even when the model is conditioned on
  stage-1 predicted albedo).
* L_rec = ||phi(I_relit) - phi(I_in)||^2 with `make_feature_extractor(rec_features)` (its name is
  logged; "pooled-rgb" is NOT DINO).

Space (PHYSICS_SPACE, default "tonemapped"): the relations are formed in LINEAR HDR, then both sides
are compared after the schema's tone map (pilight.relight.encoding): raw-HDR MSEs are unbounded, and
decoded x0 at high noise maps to HDR values in the thousands. When decomposition is false there are
no D/S branches: L_DS and L_PS are 0 (logged as such, with `ds_ps_defined = 0`).
"""

from __future__ import annotations

import torch

from pilight.physics import diffuse_shading_loss, physical_shading_loss, reconstruction_loss
from pilight.relight.encoding import to_linear, tonemap

PHYSICS_SPACE = "tonemapped"


def physics_terms(
    y: torch.Tensor,
    *,
    albedo: torch.Tensor,
    d_calc: torch.Tensor | None,
    mask: torch.Tensor,
    image_a: torch.Tensor,
    extractor,
    space: str = PHYSICS_SPACE,
    ps_on_mask: bool = False,
) -> dict[str, torch.Tensor]:
    """Per-sample (B,) L_DS, L_PS, L_rec from decoded outputs y (B, V, 3, H, W) in model space.

    V = 3 (relit, diffuse, specular) or V = 1 (relit only: L_DS = L_PS = 0). `space`: "tonemapped"
    (default) or "linear" (raw HDR, for comparison; see the module docstring). ``ps_on_mask``: L_PS
    only where the relit image is formed as A * D + S (physics_first; off the mask it is not)."""
    if space not in ("tonemapped", "linear"):
        raise ValueError(f"physics space must be 'tonemapped' or 'linear', got {space!r}")
    y = y.float()
    B = y.shape[0]
    relit_lin = to_linear(y[:, 0])
    relit_tm = tonemap(relit_lin)
    rec = reconstruction_loss((relit_tm + 1) / 2, (tonemap(image_a.float()) + 1) / 2, extractor, reduction="none")
    if y.shape[1] == 1:
        zero = torch.zeros(B, device=y.device)
        return {"ds": zero, "ps": zero, "rec": rec}
    d_lin, s_lin = to_linear(y[:, 1]), to_linear(y[:, 2])
    into = tonemap if space == "tonemapped" else (lambda x: x)
    ds = diffuse_shading_loss(d_calc, d_lin, mask, reduction="none", space=into)
    ps = physical_shading_loss(
        relit_lin, albedo.float(), d_lin, s_lin, mask if ps_on_mask else None, reduction="none", space=into
    )
    return {"ds": ds, "ps": ps, "rec": rec}
