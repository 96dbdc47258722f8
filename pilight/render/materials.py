"""Materials and the shader AOVs that give exact per-pixel intrinsics (runs inside bpy only).

Every Principled BSDF also writes what feeds its Base Color, Roughness and Metallic inputs to
shader AOVs ("albedo", "roughness", "metallic") and 1.0 to "principled". Cycles evaluates AOVs
at the camera ray's first hit in the same render as the beauty pass: no extra render, and the
values are the material's own (no compositor reconstruction that drifts with the light, the
problem the paper reports with BlenderProc). Glass and emission write no AOV, so "principled"
stays 0 there and the mask excludes them.
"""

from __future__ import annotations

import bpy

AOVS = (("albedo", "COLOR"), ("roughness", "VALUE"), ("metallic", "VALUE"), ("principled", "VALUE"))
_TEXTURE_NODES = {
    "noise": "ShaderNodeTexNoise",
    "voronoi": "ShaderNodeTexVoronoi",
    "checker": "ShaderNodeTexChecker",
    "wave": "ShaderNodeTexWave",
    "brick": "ShaderNodeTexBrick",
    "magic": "ShaderNodeTexMagic",
    "gradient": "ShaderNodeTexGradient",
    "gabor": "ShaderNodeTexGabor",  # Blender 4.3+
}


def add_aov_layers(view_layer) -> None:
    existing = {a.name for a in view_layer.aovs}
    for name, kind in AOVS:
        if name not in existing:
            aov = view_layer.aovs.add()
            aov.name, aov.type = name, kind


def _aov_node(nt, name: str):
    node = nt.nodes.new("ShaderNodeOutputAOV")
    node.aov_name = name
    return node


def _texture_fac(nt, texture: str, scale: float):
    """A texture's scalar output, about [0, 1] around 0.5, on the object's Generated coordinates
    (Blender's default for an unlinked Vector: the mesh's bounding box as [0, 1]^3, so a pattern
    sticks to its object and stretches with it)."""
    tex = nt.nodes.new(_TEXTURE_NODES[texture])
    if texture == "gradient":
        return _gradient_fac(nt, tex, scale)
    tex.inputs["Scale"].default_value = scale
    if texture == "gabor":
        # 3D: a solid object's surface cuts the noise everywhere alike (2D would smear it along z).
        # Its Value has Fac's range (median 0.49, 98% within [-0.1, 0.94] on a sphere; measured).
        tex.gabor_type = "3D"
        return tex.outputs["Value"]
    return tex.outputs["Fac"] if "Fac" in tex.outputs else tex.outputs[0]


def _gradient_fac(nt, tex, scale: float):
    """A linear ramp across the object (Generated x), steepened about its middle by ``scale``: it
    rises from 0 to 1 over 2 / scale of the bounding box (scale 2: the whole object). The low
    frequency that the other textures lack: slow albedo changes that shading also makes."""
    coord, mapping = nt.nodes.new("ShaderNodeTexCoord"), nt.nodes.new("ShaderNodeMapping")
    k = scale / 2.0
    mapping.inputs["Scale"].default_value = (k, k, k)
    mapping.inputs["Location"].default_value = (0.5 - 0.5 * k,) * 3  # x' = k (x - 0.5) + 0.5
    nt.links.new(coord.outputs["Generated"], mapping.inputs["Vector"])
    nt.links.new(mapping.outputs["Vector"], tex.inputs["Vector"])
    tex.gradient_type = "LINEAR"  # x itself: beyond [0, 1] the Mix and Map Range that read it clamp
    return tex.outputs["Fac"]


def _pattern_mask(nt, pattern: dict):
    """A shared pattern's mask in [0, 1]: the texture's Fac ramped across 0.5 +- edge."""
    mask = nt.nodes.new("ShaderNodeMapRange")
    mask.clamp = True
    nt.links.new(_texture_fac(nt, pattern["texture"], pattern["scale"]), mask.inputs["Value"])
    mask.inputs["From Min"].default_value = 0.5 - pattern["edge"]
    mask.inputs["From Max"].default_value = 0.5 + pattern["edge"]
    return mask.outputs["Result"]


def _driven(nt, spec: dict, colour: bool, mask=None):
    """A socket carrying a constant, or a procedural factor mapped between two values: the
    channel's own texture ("texture" in spec) or the material's shared ``mask``."""
    if "const" in spec:
        return None, spec["const"]
    fac = _texture_fac(nt, spec["texture"], spec["scale"]) if "texture" in spec else mask
    if fac is None:
        raise ValueError(f"a channel with values {spec['values']} needs its own texture or the material's pattern")
    a, b = spec["values"]
    if colour:
        mix = nt.nodes.new("ShaderNodeMix")
        mix.data_type = "RGBA"
        mix.clamp_factor = True
        nt.links.new(fac, mix.inputs["Factor"])
        mix.inputs["A"].default_value = (*a, 1.0)
        mix.inputs["B"].default_value = (*b, 1.0)
        return mix.outputs["Result"], None
    rng = nt.nodes.new("ShaderNodeMapRange")
    rng.clamp = True
    nt.links.new(fac, rng.inputs["Value"])
    rng.inputs["To Min"].default_value, rng.inputs["To Max"].default_value = a, b
    return rng.outputs["Result"], None


def wire_principled_aovs(nt, bsdf) -> None:
    """Send whatever feeds the BSDF's inputs to the AOVs too (also used for imported assets)."""
    for aov, socket_name, out_socket in (
        ("albedo", "Base Color", "Color"),
        ("roughness", "Roughness", "Value"),
        ("metallic", "Metallic", "Value"),
    ):
        node, src = _aov_node(nt, aov), bsdf.inputs[socket_name]
        if src.is_linked:
            nt.links.new(src.links[0].from_socket, node.inputs[out_socket])
        else:
            node.inputs[out_socket].default_value = src.default_value
    _aov_node(nt, "principled").inputs["Value"].default_value = 1.0


def make_material(name: str, spec: dict):
    mat = bpy.data.materials.new(name)
    nt = mat.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    kind = spec["type"]
    if kind == "principled":
        bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
        mask = _pattern_mask(nt, spec["pattern"]) if "pattern" in spec else None
        for socket_name, key, colour in (
            ("Base Color", "base_color", True),
            ("Roughness", "roughness", False),
            ("Metallic", "metallic", False),
        ):
            socket, const = _driven(nt, spec[key], colour, mask)
            if socket is not None:
                nt.links.new(socket, bsdf.inputs[socket_name])
            else:
                bsdf.inputs[socket_name].default_value = (*const, 1.0) if colour else const
        nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
        wire_principled_aovs(nt, bsdf)
    elif kind == "glass":
        glass = nt.nodes.new("ShaderNodeBsdfGlass")
        glass.inputs["Color"].default_value = (*spec["color"], 1.0)
        glass.inputs["Roughness"].default_value = spec["roughness"]
        glass.inputs["IOR"].default_value = spec["ior"]
        nt.links.new(glass.outputs["BSDF"], out.inputs["Surface"])
    elif kind == "emission":
        em = nt.nodes.new("ShaderNodeEmission")
        em.inputs["Color"].default_value = (*spec["color"], 1.0)
        em.inputs["Strength"].default_value = spec["strength"]
        nt.links.new(em.outputs["Emission"], out.inputs["Surface"])
    else:
        raise ValueError(f"material {name!r}: unknown type {kind!r}")
    return mat


def gray_ball_material():
    """The paper's light ball: Principled, base colour 0.5, roughness 0.5, metallic 0."""
    mat = bpy.data.materials.new("pilight_gray_ball")
    bsdf = next(n for n in mat.node_tree.nodes if n.type == "BSDF_PRINCIPLED")
    bsdf.inputs["Base Color"].default_value = (0.5, 0.5, 0.5, 1.0)
    bsdf.inputs["Roughness"].default_value = 0.5
    bsdf.inputs["Metallic"].default_value = 0.0
    return mat
