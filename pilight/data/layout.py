"""Where the render stage puts each file: the contract between `render` and `shard`.

```
<render_root>/
  manifest.json                  one entry per scene: id, kind, split; blender version; params digest
  <scene_id>/                    e.g. "train_0003" (split and index in the name)
    scene.json                   sidecar: seed, objects, materials, cameras, lights, blender version
    v00/                         one folder per camera view
      albedo.exr   RGB  float32  Principled Base Color, linear
      normal.exr   RGB  float16  camera space (x right, y up, z toward camera), unit; 0 off-mask
      roughness.exr Y   float16  Principled Roughness in [0, 1]
      metallic.exr  Y   float16  Principled Metallic in [0, 1]
      mask.exr      Y   float16  1 = pixel fully covered by Principled BSDF surfaces, else 0
      l00/                       one folder per light condition
        image.exr       RGB float32  linear HDR beauty render
        diffuse.exr     RGB float32  D >= 0 such that image = albedo * D + specular
        specular.exr    RGB float32  S >= 0 (glossy + transmission + emission + background)
        ball.exr        RGB float16  gray ball (base 0.5, roughness 0.5) lit like the scene,
                                     at its own size (render.ball_resolution)
        ball_lambertian.exr RGB float16  the same ball with a pure diffuse material (optional)
        preview.png     sRGB 8-bit   image | albedo | diffuse | specular | ball, for people
```

A view folder is complete when its `.done` marker exists; the render stage skips complete
views on a rerun and redoes incomplete ones, so an interrupted render resumes to the same bytes.
"""

from __future__ import annotations

from pathlib import Path

INTRINSIC_MAPS = ("albedo", "normal", "roughness", "metallic")  # what stage 1 predicts, in its one-hot order
VIEW_MAPS = (*INTRINSIC_MAPS, "mask")  # per view: the intrinsics and the mask, shared by the view's lights
LIGHT_MAPS = ("image", "diffuse", "specular", "ball")
OPTIONAL_LIGHT_MAPS = ("ball_lambertian",)
RELIT_MAPS = ("relit", "diffuse", "specular")  # stage 2's outputs, each linear in the target light
# float32 where the identity image = albedo * diffuse + specular must hold to float precision.
FLOAT32_MAPS = frozenset({"albedo", "image", "diffuse", "specular"})
CHANNELS = {
    "albedo": 3,
    "normal": 3,
    "roughness": 1,
    "metallic": 1,
    "mask": 1,
    "image": 3,
    "diffuse": 3,
    "specular": 3,
    "ball": 3,
    "ball_lambertian": 3,
}
DONE_MARKER = ".done"


def scene_id(split: str, index: int) -> str:
    return f"{split}_{index:04d}"


def view_dir(root: Path, scene: str, view: int) -> Path:
    return Path(root) / scene / f"v{view:02d}"


def light_dir(root: Path, scene: str, view: int, light: int) -> Path:
    return view_dir(root, scene, view) / f"l{light:02d}"


def map_path(root: Path, scene: str, view: int, name: str, light: int | None = None) -> Path:
    """Path of one map; `light` is required for per-light maps and refused for per-view maps."""
    if name in VIEW_MAPS:
        if light is not None:
            raise ValueError(f"{name!r} is per view; it takes no light index")
        return view_dir(root, scene, view) / f"{name}.exr"
    if name in LIGHT_MAPS or name in OPTIONAL_LIGHT_MAPS:
        if light is None:
            raise ValueError(f"{name!r} is per light; give a light index")
        return light_dir(root, scene, view, light) / f"{name}.exr"
    raise ValueError(f"unknown map {name!r}; known: {VIEW_MAPS + LIGHT_MAPS + OPTIONAL_LIGHT_MAPS}")
