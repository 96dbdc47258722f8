"""Material classes with real-world correlations (render.scene.material_model: classes). Pure numpy.

The uniform model draws colour, roughness and metalness independently, so a rough, pure-red metal
is as likely as a polished one. Real objects are made of a few kinds of stuff whose properties go
together: metals are coloured only by their own reflectance (silver, gold, copper) and are often
polished; plastics are saturated and semi-glossy; rubber is dark and rough; wood is brown, grained
and never metallic; stone is gray and rough; glazed ceramic is light and glossy. A base model that
learns these correlations reads material from appearance the way photos allow.

Each class is a Principled (sub-)material, and a shared pattern (two sub-materials along one
procedural mask, as in spec.py) stays available inside a class: painted metal, two-tone plastic,
wood grain, mottled stone, tiles. Every base colour is linear RGB in [0.03, 0.9]: no real surface is
perfectly black or white, and D = diffuse radiance / albedo needs albedo away from 0.
"""

from __future__ import annotations

import numpy as np

ALBEDO_RANGE = (0.03, 0.9)

# Half-width of the Fac band that a shared pattern's mask ramps across: narrow, so the two
# sub-materials meet along a soft edge (anti-aliased, as in a baked material mask) instead of
# blending over the whole of a noise texture, whose Fac stays mostly between 0.3 and 0.7.
PATTERN_EDGE = 0.05

# Linear RGB reflectance at normal incidence (F0) of pure metals: Real-Time Rendering, 4th ed.,
# Table 9.2 (after Hoffman's "Physics and Math of Shading"). A metal's base colour IS its F0.
METAL_F0 = {
    "silver": (0.972, 0.960, 0.915),
    "aluminium": (0.913, 0.922, 0.924),
    "gold": (1.000, 0.782, 0.344),
    "copper": (0.955, 0.638, 0.538),
    "brass": (0.910, 0.778, 0.423),
    "iron": (0.562, 0.565, 0.578),
    "chromium": (0.549, 0.556, 0.554),
    "nickel": (0.660, 0.609, 0.526),
    "titanium": (0.542, 0.497, 0.449),
}

Sub = tuple[list[float], float, float]  # (base colour, roughness, metallic) of one sub-material
CHANNELS = ("base_color", "roughness", "metallic")  # a Sub's entries as a material spec's keys


def hsv_linear(h: float, s: float, v: float) -> list[float]:
    """An HSV colour read as display (sRGB-like) values, in linear RGB within ALBEDO_RANGE."""
    k = (np.array([5.0, 3.0, 1.0]) + h * 6.0) % 6.0
    rgb = v - v * s * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)
    return np.clip(rgb**2.2, *ALBEDO_RANGE).round(4).tolist()


def _u(rng, lo: float, hi: float) -> float:
    return round(float(rng.uniform(lo, hi)), 4)


def _metal(rng) -> Sub:
    f0 = np.asarray(METAL_F0[str(rng.choice(sorted(METAL_F0)))])
    f0 = f0 * rng.uniform(0.85, 1.0) * rng.uniform(0.97, 1.03, 3)  # alloy, oxide, measurement spread
    f0 = f0 * min(1.0, ALBEDO_RANGE[1] / f0.max())  # silver and gold exceed 0.9: scale, keep the hue
    return np.clip(f0, *ALBEDO_RANGE).round(4).tolist(), _u(rng, 0.05, 0.6), 1.0


def _paint(rng) -> Sub:  # the coat of painted metal
    return hsv_linear(rng.uniform(), rng.uniform(0.3, 0.9), rng.uniform(0.3, 0.95)), _u(rng, 0.3, 0.7), 0.0


def _plastic(rng) -> Sub:
    return hsv_linear(rng.uniform(), rng.uniform(0.5, 0.95), rng.uniform(0.35, 0.95)), _u(rng, 0.2, 0.6), 0.0


def _rubber(rng) -> Sub:
    return hsv_linear(rng.uniform(), rng.uniform(0.0, 0.6), rng.uniform(0.15, 0.6)), _u(rng, 0.7, 1.0), 0.0


def _wood(rng) -> Sub:
    return hsv_linear(rng.uniform(0.05, 0.11), rng.uniform(0.45, 0.8), rng.uniform(0.3, 0.8)), _u(rng, 0.4, 0.8), 0.0


def _stone(rng) -> Sub:
    return hsv_linear(rng.uniform(0.05, 0.15), rng.uniform(0.0, 0.15), rng.uniform(0.3, 0.85)), _u(rng, 0.6, 0.95), 0.0


def _ceramic(rng) -> Sub:
    return hsv_linear(rng.uniform(), rng.uniform(0.0, 0.3), rng.uniform(0.75, 0.95)), _u(rng, 0.05, 0.3), 0.0


def _grain(rng, wood: Sub) -> Sub:
    """Wood's darker grain: the same hue, darker, a little rougher or smoother."""
    colour = np.asarray(wood[0]) * rng.uniform(0.35, 0.65)
    roughness = float(np.clip(wood[1] + rng.uniform(-0.1, 0.1), 0.3, 0.9))
    return np.clip(colour, *ALBEDO_RANGE).round(4).tolist(), round(roughness, 4), 0.0


def _glaze(rng) -> Sub:  # a ceramic's painted or glazed motif
    return hsv_linear(rng.uniform(), rng.uniform(0.2, 0.8), rng.uniform(0.35, 0.9)), _u(rng, 0.05, 0.3), 0.0


# class: (first sub-material, second sub-material given the first, share patterned, pattern textures)
# The textures are those that look like the class's pattern (worn paint, moulded stripes, grain,
# mottling, tiles); only those also listed in render.scene.textures are used.
CLASSES = {
    "metal": (_metal, lambda rng, first: _paint(rng), 0.3, ("noise", "voronoi", "gabor")),
    "plastic": (_plastic, lambda rng, first: _plastic(rng), 0.3, ("checker", "wave", "gradient", "brick", "magic")),
    "rubber": (_rubber, lambda rng, first: _rubber(rng), 0.15, ("noise", "voronoi", "gradient")),
    "wood": (_wood, _grain, 0.85, ("wave", "gabor", "noise")),
    "stone": (_stone, lambda rng, first: _stone(rng), 0.8, ("voronoi", "noise", "gabor", "magic")),
    "ceramic": (_ceramic, lambda rng, first: _glaze(rng), 0.4, ("checker", "brick", "wave")),
}


def pattern_material(first: Sub, second: Sub, pattern: dict, **extra) -> dict:
    """Two sub-materials meeting along one pattern: a channel where they agree stays constant."""
    channels = {k: {"const": a} if a == b else {"values": [a, b]} for k, a, b in zip(CHANNELS, first, second)}
    return {"type": "principled", **extra, "pattern": pattern, **channels}


def class_material(rng: np.random.Generator, weights: dict[str, float], textures: tuple[str, ...]) -> dict:
    """A Principled material of a class drawn by ``weights``; patterned with the class's textures
    that are among ``textures`` (none: always plain)."""
    names = sorted(weights)
    w = np.array([weights[n] for n in names], dtype=np.float64)
    name = str(rng.choice(names, p=w / w.sum()))
    first_of, second_of, patterned, class_textures = CLASSES[name]
    first = first_of(rng)
    usable = [t for t in class_textures if t in textures]
    if not usable or rng.uniform() >= patterned:
        return {"type": "principled", "class": name, **{k: {"const": v} for k, v in zip(CHANNELS, first)}}
    second = second_of(rng, first)
    pattern = {"texture": str(rng.choice(usable)), "scale": _u(rng, 2.0, 8.0), "edge": PATTERN_EDGE}
    return pattern_material(first, second, pattern, **{"class": name})
