"""Numpy brute-force references for the physics tests (independent of pilight.physics).

D(n) = 1/pi * integral over the sphere of L(w) max(0, n.w) dw, integrated on a
fine lat-long grid with exact cell solid angles.
"""

import numpy as np


def sphere_grid(h=64, w=128):
    """Directions (K x 3) and solid angles (K,) of a lat-long grid (any frame, y = pole)."""
    edges = np.linspace(0.0, np.pi, h + 1)
    th = 0.5 * (edges[1:] + edges[:-1])
    ph = (np.arange(w) + 0.5) * 2 * np.pi / w - np.pi
    T, P = np.meshgrid(th, ph, indexing="ij")
    d = np.stack([np.sin(T) * np.sin(P), np.cos(T), np.sin(T) * np.cos(P)], -1).reshape(-1, 3)
    dw = np.repeat((np.cos(edges[:-1]) - np.cos(edges[1:])) * 2 * np.pi / w, w)
    return d, dw


def irradiance(normals, radiance_fn, h=64, w=128, chunk=4096):
    """Brute-force D for normals (P x 3); radiance_fn(dirs K x 3) -> K x C radiance."""
    d, dw = sphere_grid(h, w)
    L = radiance_fn(d) * dw[:, None]
    out = []
    for s in range(0, len(normals), chunk):
        c = np.clip(normals[s : s + chunk] @ d.T, 0.0, None)
        out.append(c @ L / np.pi)
    return np.concatenate(out, 0)


def ball_pixel_normals(size):
    """Ball-layout normals (size x size x 3) and disk mask, per the documented convention."""
    x = (np.arange(size) + 0.5) * 2 / size - 1
    y = 1 - (np.arange(size) + 0.5) * 2 / size
    Y, X = np.meshgrid(y, x, indexing="ij")
    r2 = X**2 + Y**2
    inside = r2 < 1
    n = np.stack([X, Y, np.sqrt(np.clip(1 - r2, 0, None))], -1) * inside[..., None]
    return n, inside


def ball_from_radiance(radiance_fn, size=256, albedo=0.5):
    """A gray ball image (C x size x size) under radiance_fn, by brute force."""
    n, inside = ball_pixel_normals(size)
    D = np.zeros((size * size, 3))
    flat = inside.reshape(-1)
    D[flat] = irradiance(n.reshape(-1, 3)[flat], radiance_fn)
    return (albedo * D).T.reshape(3, size, size)


def smooth_env(seed, lobes=3):
    """Random smooth positive RGB environment: constant + von-Mises-Fisher-like lobes."""
    rng = np.random.default_rng(seed)
    mu = rng.normal(size=(lobes, 3))
    mu /= np.linalg.norm(mu, axis=1, keepdims=True)
    kappa = rng.uniform(1.0, 4.0, lobes)
    amp = rng.uniform(0.2, 2.0, (lobes, 3))
    base = rng.uniform(0.05, 0.3, 3)

    def fn(d):
        return base + np.exp(kappa * (d @ mu.T - 1.0)) @ amp

    return fn
