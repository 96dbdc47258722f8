"""Does the relit image follow the chosen light? Three measures, each beside what copying scores.

All three are about the CHANGE a relighting makes, which PSNR/SSIM against the target hide: most of
a relit image repeats its input, so "copy the input" already scores well on them.

* ``change_r2`` (display space u = tonemap01 of the evaluation): with dt = u(I_b) - u(I_a) the true
  change and dp = u(I_hat_b) - u(I_a) the predicted one, pooled over every pixel of every
  cross-light pair (optionally only the mask):

      change_r2 = 1 - sum (dp - dt)^2 / sum dt^2

  Copying scores exactly 0, the ground truth 1; a prediction that moves the wrong way is negative.
  Pooled, a pair weighs by how much it changes, so one pair can decide it (a dark close-up once
  moved a base split's figure by 0.03 of 0.04); ``mask_pair_median`` is the median over pairs of each
  pair's own change_r2 on the mask: the typical pair, beside the pooled figure.
* ``direction``: probe images relit under an analytic light from camera-left and camera-right
  (``PROBE_AZIMUTH_DEG``, ``PROBE_ELEVATION_DEG``); the share whose left/right luminance asymmetry
  (``lr_asymmetry``, ground-truth normals, mask) is larger under the right light. Chance is 0.5.
* ``linearity``: probe images relit under their target ball and under that ball x 2; the median
  ratio of the relit radiances (linear HDR luminance, mask). Light transport is linear: 2.

Probe images (``select_probes``): inputs of cross-light test pairs, each image once, with at least
``PROBE_SIDE_SHARE`` of their mask facing right (n_x > 0.2) and as much facing left, so an
asymmetry can show at all.
"""

from __future__ import annotations

import json

import torch

from pilight.data.schema import sample_key
from pilight.lights import direction as direction_from_angles  # azimuth 0 = from the camera, +90 = camera-right
from pilight.physics.shading import ball_from_direction

PROBE_AZIMUTH_DEG = 60.0  # from the view axis toward camera-right (+) or camera-left (-)
PROBE_ELEVATION_DEG = 30.0  # above the camera's horizon
PROBE_SIDE_SHARE = 0.05  # of the mask, facing each side
PROBE_LIGHTS = ("left", "right", "target", "target_x2")
SIDE_NORMAL_X = 0.2  # n_x beyond which a pixel faces right (or left, negated)


def lr_asymmetry(
    d: torch.Tensor, normal: torch.Tensor, mask: torch.Tensor, thr: float = SIDE_NORMAL_X, eps: float = 1e-6
) -> torch.Tensor:
    """(R - L) / (R + L) per image (B,): R, L = mean luminance of `d` over masked pixels whose
    (original, unflipped) normal faces right (n_x > thr) or left (n_x < -thr).

    Classifying by the normal, not by image halves, makes the measure independent of where the
    objects sit in the frame: if shading follows N, flipping N_x swaps R and L, so the sign flips."""
    lum = d.float().mean(1, keepdim=True)
    m = mask.float() > 0.5
    right, left = m & (normal[:, :1] > thr), m & (normal[:, :1] < -thr)
    mean = lambda sel: (lum * sel).flatten(1).sum(1) / sel.flatten(1).sum(1).clamp_min(1)
    r, l = mean(right), mean(left)
    return (r - l) / (r + l + eps)


class ChangeR2:
    """Pooled change_r2 over batches, on the full image and on the mask (module docstring)."""

    def __init__(self):
        self.err = {"full": 0.0, "mask": 0.0}
        self.tot = {"full": 0.0, "mask": 0.0}
        self.pairs: list[float] = []  # each pair's change_r2 on the mask (pairs whose mask changes at all)

    def update(self, pred_u: torch.Tensor, target_u: torch.Tensor, input_u: torch.Tensor, mask: torch.Tensor) -> None:
        """Display values in [0, 1], (B, 3, H, W); mask (B, 1, H, W)."""
        dp, dt = (pred_u - input_u).double(), (target_u - input_u).double()
        m = (mask.double() > 0.5).expand_as(dt)
        for name, sel in (("full", torch.ones_like(m)), ("mask", m)):
            self.err[name] += float(((dp - dt) ** 2 * sel).sum())
            self.tot[name] += float((dt**2 * sel).sum())
        err, tot = (((x**2) * m).flatten(1).sum(1) for x in (dp - dt, dt))
        self.pairs += [1.0 - float(e / t) for e, t in zip(err, tot) if t > 0]

    def compute(self) -> dict[str, float | None]:
        out = {k: (1.0 - self.err[k] / self.tot[k]) if self.tot[k] > 0 else None for k in self.err}
        # the lower median of an even count: a value some pair scored, as torch.median gives
        out["mask_pair_median"] = float(torch.tensor(self.pairs).median()) if self.pairs else None
        return out


def sides_visible(normal: torch.Tensor, mask: torch.Tensor, share: float = PROBE_SIDE_SHARE) -> torch.Tensor:
    """(B,) bool: at least ``share`` of the mask faces right and as much faces left."""
    m = mask.float() > 0.5
    n = m.flatten(1).sum(1).clamp_min(1)
    right = (m & (normal[:, :1] > SIDE_NORMAL_X)).flatten(1).sum(1) / n
    left = (m & (normal[:, :1] < -SIDE_NORMAL_X)).flatten(1).sum(1) / n
    return (right >= share) & (left >= share) & (m.flatten(1).sum(1) > 0)


def select_probes(batches, count: int) -> list[dict]:
    """The first ``count`` probe images (module docstring) of an iterable of pair batches, each as
    a one-sample batch (the pair's input image, its intrinsics, mask and target ball)."""
    out: list[dict] = []
    seen: set[str] = set()
    for b in batches:
        ok = sides_visible(b["normal"], b["mask"])
        for i, _key in enumerate(b["key"]):
            ma, mb = json.loads(b["meta_a"][i]), json.loads(b["meta_b"][i])
            image = sample_key(ma["scene"], ma["view"], ma["light"])
            if ma["light"] == mb["light"] or image in seen or not ok[i]:
                continue
            seen.add(image)
            out.append({k: (v[i : i + 1] if torch.is_tensor(v) else [v[i]]) for k, v in b.items()})
            if len(out) == count:
                return out
    return out


def probe_balls(target_ball: torch.Tensor) -> dict[str, torch.Tensor]:
    """The four probe lights for one image (``PROBE_LIGHTS``), each a ball like ``target_ball``
    (1, 3, h, w). The analytic left/right balls get the target ball's mean radiance, so the probe
    is exposed like the data."""
    size = target_ball.shape[-1]
    out = {}
    for name, sign in (("left", -1.0), ("right", 1.0)):
        unit = ball_from_direction(direction_from_angles(sign * PROBE_AZIMUTH_DEG, PROBE_ELEVATION_DEG), size=size)
        scale = target_ball.float().mean() / unit.mean().clamp_min(1e-12)
        out[name] = unit * scale
    out["target"] = target_ball.float()
    out["target_x2"] = 2.0 * target_ball.float()
    return out


def direction_score(asym_right: torch.Tensor, asym_left: torch.Tensor) -> float | None:
    """Share of probe images whose asymmetry is larger under the right light than the left."""
    return float((asym_right > asym_left).float().mean()) if len(asym_right) else None


def linearity(relit_1x: torch.Tensor, relit_2x: torch.Tensor, mask: torch.Tensor, floor: float = 1e-3) -> float | None:
    """Median over masked pixels (pooled over images) of lum(relit_2x) / lum(relit_1x), linear HDR;
    pixels darker than ``floor`` under 1x are left out (their ratio is noise)."""
    l1, l2 = relit_1x.float().mean(1), relit_2x.float().mean(1)
    sel = (mask[:, 0].float() > 0.5) & (l1 > floor)
    return float((l2[sel] / l1[sel]).median()) if sel.any() else None


PROBE_SPLIT = "probes"  # the relit folder's split that holds the probe images' relit outputs


def probe_key(probe: dict, light: str) -> str:
    """`<scene>_vNN_lNN_probe_<light>` of a probe image (a one-sample batch of select_probes)."""
    ma = json.loads(probe["meta_a"][0])
    return f"{sample_key(ma['scene'], ma['view'], ma['light'])}_probe_{light}"


def probe_batch(probe: dict) -> dict:
    """The probe image under the four PROBE_LIGHTS as one batch of 4 (the target ball's Lambertian
    twin scaled alike; the analytic balls are their own twin: they have no highlight)."""
    balls = probe_balls(probe["ball_b"])
    lamb = probe.get("ball_lambertian_b")
    twins = {"left": balls["left"], "right": balls["right"]}
    if lamb is not None:
        twins |= {"target": lamb.float(), "target_x2": 2.0 * lamb.float()}
    else:
        twins |= {"target": balls["target"], "target_x2": balls["target_x2"]}
    out = {
        k: (v.expand(len(PROBE_LIGHTS), *v.shape[1:]) if torch.is_tensor(v) else v * len(PROBE_LIGHTS))
        for k, v in probe.items()
    }
    out["ball_b"] = torch.cat([balls[n] for n in PROBE_LIGHTS])
    out["ball_lambertian_b"] = torch.cat([twins[n] for n in PROBE_LIGHTS])
    return out


def probe_scores(relit: dict[str, dict], probes: list[dict]) -> dict:
    """direction and linearity (module docstring) from the probes' relit outputs (linear HDR,
    H x W x 3 arrays keyed by probe_key), with the probes' ground-truth normals and masks."""
    if not probes:
        return {"probes": 0, "direction": None, "linearity": None, "note": "no test image shows both sides"}
    get = lambda p, n: torch.from_numpy(relit[probe_key(p, n)]["relit"]).permute(2, 0, 1)[None].float()
    normal = torch.cat([p["normal"] for p in probes])
    mask = torch.cat([p["mask"] for p in probes])
    right, left = (torch.cat([get(p, n) for p in probes]) for n in ("right", "left"))
    one, two = (torch.cat([get(p, n) for p in probes]) for n in ("target", "target_x2"))
    return {
        "probes": len(probes),
        "direction": direction_score(lr_asymmetry(right, normal, mask), lr_asymmetry(left, normal, mask)),
        "linearity": linearity(one, two, mask),
        "what": f"direction: share of {len(probes)} probe images whose relit left/right asymmetry (ground-truth "
        f"normals, mask) is larger under an analytic light from camera-right than from camera-left "
        f"(azimuth +-{PROBE_AZIMUTH_DEG:g}, elevation {PROBE_ELEVATION_DEG:g} deg; chance 0.5); "
        "linearity: median relit radiance ratio under the target ball x 2 and x 1 (mask; truth 2)",
    }


def cross_light(batch: dict) -> dict | None:
    """The cross-light pairs (light a != light b) of a pairs batch, or None when it has none."""
    keep = [json.loads(a)["light"] != json.loads(b)["light"] for a, b in zip(batch["meta_a"], batch["meta_b"])]
    if not any(keep):
        return None
    sel = torch.tensor(keep)
    return {k: (v[sel] if torch.is_tensor(v) else [x for x, k_ in zip(v, keep) if k_]) for k, v in batch.items()}
