"""Build a Blender scene from a spec (runs inside bpy only).

Two bpy scenes share one world and one collection of lights:
- the main scene (objects, backdrop, perspective camera);
- the ball scene: the paper's gray ball, centred on the scene's target point, seen by an
  orthographic camera with the main camera's orientation and tangent to the image borders, so
  the ball is lit by exactly the same lights and environment as the scene centre.
Changing the light or the view only moves objects and edits the world, so Cycles' persistent
data keeps the scene's geometry (BVH) between the renders of one view.
"""

from __future__ import annotations

import math
from pathlib import Path

import bpy
import numpy as np
from mathutils import Euler, Matrix, Vector

from pilight.params import RenderParams
from pilight.render.holed_shapes import HOLED, add_holed_shape
from pilight.render.materials import add_aov_layers, gray_ball_material, make_material, wire_principled_aovs
from pilight.render.spec import half_height

BALL_RADIUS = 0.05  # small, so the ball samples the light field at the scene centre
LIGHTS_COLLECTION = "pilight_lights"


class RenderError(RuntimeError):
    """Bad render input (asset, HDRI) or a broken render; the message names the file or scene."""


def reset_blender() -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    # Untrusted .blend assets must never run their embedded Python.
    bpy.context.preferences.filepaths.use_scripts_auto_execute = False


def configure_cycles(scene, p: RenderParams, seed: int) -> None:
    r, c = scene.render, scene.cycles
    r.engine = "CYCLES"
    r.resolution_x = r.resolution_y = p.resolution
    r.resolution_percentage = 100
    r.use_persistent_data = True
    r.use_compositing = False
    r.use_sequencer = False
    r.dither_intensity = 0.0
    if p.cycles.threads:
        r.threads_mode, r.threads = "FIXED", p.cycles.threads
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure, scene.view_settings.gamma = 0.0, 1.0
    c.device = p.cycles.device
    c.samples = p.cycles.samples
    c.use_adaptive_sampling = p.cycles.adaptive_threshold > 0
    c.adaptive_threshold = p.cycles.adaptive_threshold
    c.adaptive_min_samples = p.cycles.adaptive_min_samples
    c.use_denoising = False
    c.seed, c.use_animated_seed = seed, False
    c.max_bounces = p.cycles.max_bounces
    c.diffuse_bounces, c.glossy_bounces = p.cycles.diffuse_bounces, p.cycles.glossy_bounces
    c.transmission_bounces = p.cycles.transmission_bounces
    c.transparent_max_bounces = p.cycles.transparent_max_bounces
    # Clamping would break Combined = sum of light passes, on which the A*D+S contract rests.
    c.sample_clamp_direct = c.sample_clamp_indirect = 0.0
    imf = r.image_settings
    imf.media_type = "MULTI_LAYER_IMAGE"
    imf.file_format = "OPEN_EXR_MULTILAYER"
    imf.color_depth = "32"
    imf.exr_codec = "ZIP"


def _shape(name: str):
    if name in HOLED:  # built from their vertices: all smooth, split at every crease (holed_shapes.py)
        obj = add_holed_shape(name)
        obj.data.shade_smooth()
        return obj
    add = bpy.ops.mesh
    {
        "sphere": lambda: add.primitive_uv_sphere_add(segments=48, ring_count=24),
        "icosphere": lambda: add.primitive_ico_sphere_add(subdivisions=3),
        "cube": lambda: add.primitive_cube_add(),
        "cylinder": lambda: add.primitive_cylinder_add(vertices=48),
        "cone": lambda: add.primitive_cone_add(vertices=48),
        "torus": lambda: add.primitive_torus_add(major_segments=48, minor_segments=16),
        "monkey": lambda: add.primitive_monkey_add(),
    }[name]()
    obj = bpy.context.object
    if name != "cube":
        obj.data.shade_smooth()
    return obj


def _modifier(obj, kind: str) -> None:
    if kind == "bevel":
        m = obj.modifiers.new("bevel", "BEVEL")
        m.width, m.segments = 0.08, 3
        obj.data.shade_smooth()  # bevel needs smooth normals to look rounded
    elif kind == "subdivision":
        obj.modifiers.new("subdivision", "SUBSURF").render_levels = 2
    elif kind == "displace":
        # Not Blender's Displace modifier: it moves vertices along Blender's own vertex normals,
        # which are not deterministic (see deterministic_normals), so the displaced positions
        # changed between runs.  deterministic_normals displaces along our normals instead.
        obj.modifiers.new("subdivision", "SUBSURF").render_levels = 2
        tex = bpy.data.textures.new(f"{obj.name}_clouds", "CLOUDS")
        tex.noise_scale = 0.6
        obj["pilight_displace"] = {"texture": tex.name, "strength": 0.12, "midlevel": 0.5}
    else:
        raise ValueError(f"unknown modifier {kind!r}")


POSITION_GRID = 2.0**16  # baked vertex positions are multiples of 1 / POSITION_GRID metres


def _vertex_normals(me) -> tuple[np.ndarray, np.ndarray]:
    """(positions, unit area-weighted vertex normals), float64, summed in a fixed order."""
    n_loops = len(me.loops)
    co = np.zeros(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3).astype(np.float64)
    vi = np.zeros(n_loops, np.int64)
    me.loops.foreach_get("vertex_index", vi)
    start, total = np.zeros(len(me.polygons), np.int64), np.zeros(len(me.polygons), np.int64)
    me.polygons.foreach_get("loop_start", start)
    me.polygons.foreach_get("loop_total", total)
    face = np.repeat(np.arange(len(total)), total)
    nxt = np.arange(n_loops) + 1
    last = start + total - 1
    nxt[last] = start
    face_n = np.zeros((len(total), 3))
    np.add.at(face_n, face, np.cross(co[vi], co[vi[nxt]]))  # Newell: twice the area vector
    vert_n = np.zeros_like(co)
    np.add.at(vert_n, vi, face_n[face])  # area-weighted, in loop order
    vert_n /= np.maximum(np.linalg.norm(vert_n, axis=1, keepdims=True), 1e-12)
    return co, vert_n


def _set_snapped_positions(me, co: np.ndarray) -> None:
    """Write vertex positions rounded to the POSITION_GRID (see deterministic_normals)."""
    me.vertices.foreach_set("co", (np.round(co * POSITION_GRID) / POSITION_GRID).astype(np.float32).ravel())
    me.update()


def deterministic_normals(obj) -> None:
    """Bake modifiers and give the mesh smooth normals computed in a fixed order.

    Blender sums face normals into vertex normals in a thread-dependent order, so the last bit
    of a smooth normal changes from run to run (measured: 1.2e-7 on a UV sphere), and with it
    the render. A float3 `custom_normal` attribute on the point domain replaces Blender's
    computation exactly, so the same seed gives the same bytes.

    The same normals moved Blender's Displace modifier's vertices differently from run to run
    (all light renders of a displaced scene changed, up to 4e-6), so displacement is done here,
    along our normals (``_modifier`` only records it).  Baked positions are also snapped to a grid
    of 2^-16 m (15 um, far below a pixel), so no last-bit difference of the remaining modifiers
    (subdivision, bevel) reaches the renderer unless it straddles a grid line.
    """
    if obj.modifiers:
        mesh = bpy.data.meshes.new_from_object(obj.evaluated_get(bpy.context.evaluated_depsgraph_get()))
        obj.modifiers.clear()
        obj.data = mesh
        baked = np.zeros(len(mesh.vertices) * 3, np.float32)
        mesh.vertices.foreach_get("co", baked)
        _set_snapped_positions(mesh, baked)
    me = obj.data
    displace = obj.get("pilight_displace")
    if displace is not None:  # Displace, texture coordinates LOCAL: p += (value - midlevel) * strength * n
        co, n = _vertex_normals(me)
        tex = bpy.data.textures[displace["texture"]]
        value = np.array([tex.evaluate(tuple(c))[3] for c in co])
        co = co + ((value - displace["midlevel"]) * displace["strength"])[:, None] * n
        _set_snapped_positions(me, co)
        del obj["pilight_displace"]
    if not any(poly.use_smooth for poly in me.polygons):
        return  # flat faces use face normals, which are deterministic
    _, vert_n = _vertex_normals(me)
    attr = me.attributes.get("custom_normal") or me.attributes.new("custom_normal", "FLOAT_VECTOR", "POINT")
    attr.data.foreach_set("vector", vert_n.astype(np.float32).ravel())
    me.update()


def _plane(name: str, size: float, location, rotation, material):
    bpy.ops.mesh.primitive_plane_add(size=size, location=location, rotation=rotation)
    obj = bpy.context.object
    obj.name = name
    obj.data.materials.append(material)
    return obj


def _backdrop(spec: dict | None, ground_z: float) -> None:
    if spec is None:
        return
    if spec["type"] == "wall":  # close-up scenes: a wall behind the subject, placed by the spec, no floor
        wall = make_material("backdrop_wall", spec["material"])
        _plane("wall", 12.0, spec["location"], [math.radians(a) for a in spec["rotation_deg"]], wall)
        return
    floor = make_material("backdrop_floor", spec["material"])
    _plane("floor", 12.0 if spec["type"] == "ground" else 7.0, (0, 0, ground_z), (0, 0, 0), floor)
    if spec["type"] == "room":  # an open room corner: back and left walls, no ceiling
        wall = make_material("backdrop_wall", spec["wall_material"])
        _plane("wall_back", 7.0, (0, 2.5, 3.5), (math.pi / 2, 0, 0), wall)
        _plane("wall_left", 7.0, (-3.0, 0, 3.5), (0, math.pi / 2, 0), wall)


def import_asset(path: str, name: str):
    """Import one user asset with Blender's own importers; returns its root (an empty)."""
    p = Path(path)
    if not p.is_file():
        raise RenderError(f"asset {path}: file not found")
    before = set(bpy.data.objects)
    try:
        suffix = p.suffix.lower()
        if suffix in (".glb", ".gltf"):
            bpy.ops.import_scene.gltf(filepath=str(p))
        elif suffix == ".obj":
            bpy.ops.wm.obj_import(filepath=str(p))
        elif suffix == ".blend":
            # Loading data blocks never runs the file's scripts (and auto-exec is off anyway).
            with bpy.data.libraries.load(str(p), link=False) as (src, dst):
                dst.objects = list(src.objects)
            for obj in dst.objects:
                if obj is not None and obj.type == "MESH":
                    bpy.context.scene.collection.objects.link(obj)
        else:
            raise RenderError(f"asset {path}: unsupported type {suffix!r}")
    except RenderError:
        raise
    except Exception as exc:  # importers raise RuntimeError with Blender's report text
        raise RenderError(f"asset {path}: import failed ({exc})") from exc
    meshes = [o for o in set(bpy.data.objects) - before if o.type == "MESH" and o.name in bpy.context.scene.objects]
    if not meshes:
        raise RenderError(f"asset {path}: contains no mesh object")
    root = bpy.data.objects.new(name, None)
    bpy.context.scene.collection.objects.link(root)
    for obj in meshes:
        if obj.parent is None or obj.parent not in meshes:
            obj.parent = root
        for slot in obj.material_slots:
            _wire_asset_material(slot.material)
        deterministic_normals(obj)
    return root, meshes


def _wire_asset_material(mat) -> None:
    """AOVs for an imported material whose surface is exactly one Principled BSDF."""
    if mat is None or not mat.node_tree or any(n.type == "OUTPUT_AOV" for n in mat.node_tree.nodes):
        return
    out = next((n for n in mat.node_tree.nodes if n.type == "OUTPUT_MATERIAL" and n.is_active_output), None)
    if out and out.inputs["Surface"].is_linked:
        src = out.inputs["Surface"].links[0].from_node
        if src.type == "BSDF_PRINCIPLED":
            wire_principled_aovs(mat.node_tree, src)


def _fit_asset(root, meshes, size: float, location, rotation_deg) -> None:
    bpy.context.view_layer.update()
    corners = [obj.matrix_world @ Vector(c) for obj in meshes for c in obj.bound_box]
    lo = Vector(tuple(min(c[i] for c in corners) for i in range(3)))
    hi = Vector(tuple(max(c[i] for c in corners) for i in range(3)))
    scale = size / max(max(hi - lo), 1e-6)
    centre = (lo + hi) / 2
    root.scale = (scale, scale, scale)
    root.rotation_euler = Euler([math.radians(a) for a in rotation_deg])
    root.location = (
        Vector(location)
        - scale * (root.rotation_euler.to_matrix() @ centre)
        + Vector((0, 0, scale * (centre.z - lo.z)))
    )


def _world(hdri_dir: Path, map_resolution: int, camera_backdrop: float | None = None, sky: bool = False):
    """The world: HDRI + ambient (+ procedural sky with ``sky``), set per light by set_world. With
    ``camera_backdrop`` (linear gray radiance; render.camera_backdrop), rays leaving the CAMERA see
    that constant instead, so the background behind the scene is the same for every light of a view,
    while every other ray (diffuse, glossy, shadow) still sees the lighting world: the scene stays lit
    by it. The sky's nodes exist only in scenes with a sky light, so every other scene keeps the world
    (and so the bytes) it had before skies existed."""
    world = bpy.data.worlds.new("pilight_world")
    nt = world.node_tree
    nt.nodes.clear()
    coord, mapping = nt.nodes.new("ShaderNodeTexCoord"), nt.nodes.new("ShaderNodeMapping")
    env, bg_env, bg_amb = (
        nt.nodes.new("ShaderNodeTexEnvironment"),
        nt.nodes.new("ShaderNodeBackground"),
        nt.nodes.new("ShaderNodeBackground"),
    )
    add, out = nt.nodes.new("ShaderNodeAddShader"), nt.nodes.new("ShaderNodeOutputWorld")
    nt.links.new(coord.outputs["Generated"], mapping.inputs["Vector"])
    nt.links.new(mapping.outputs["Vector"], env.inputs["Vector"])
    nt.links.new(env.outputs["Color"], bg_env.inputs["Color"])
    nt.links.new(bg_env.outputs["Background"], add.inputs[0])
    nt.links.new(bg_amb.outputs["Background"], add.inputs[1])
    lighting = add.outputs["Shader"]
    if sky:
        tex, bg_sky, add_sky = (
            nt.nodes.new("ShaderNodeTexSky"),
            nt.nodes.new("ShaderNodeBackground"),
            nt.nodes.new("ShaderNodeAddShader"),
        )
        tex.name, bg_sky.name = "sky", "sky_background"
        # Its Vector stays unlinked: Cycles then samples the sun disc directly (scene/light.cpp, sun
        # guiding of a sky with a sun disc), which a 256 x 128 importance map could not (0.5 degrees).
        nt.links.new(tex.outputs["Color"], bg_sky.inputs["Color"])
        nt.links.new(lighting, add_sky.inputs[0])
        nt.links.new(bg_sky.outputs["Background"], add_sky.inputs[1])
        lighting = add_sky.outputs["Shader"]
    if camera_backdrop is None:
        nt.links.new(lighting, out.inputs["Surface"])
    else:
        path, backdrop = nt.nodes.new("ShaderNodeLightPath"), nt.nodes.new("ShaderNodeBackground")
        backdrop.name = "camera_backdrop"
        backdrop.inputs["Color"].default_value = (camera_backdrop, camera_backdrop, camera_backdrop, 1.0)
        backdrop.inputs["Strength"].default_value = 1.0
        mix = nt.nodes.new("ShaderNodeMixShader")
        nt.links.new(path.outputs["Is Camera Ray"], mix.inputs["Fac"])
        nt.links.new(lighting, mix.inputs[1])
        nt.links.new(backdrop.outputs["Background"], mix.inputs[2])
        nt.links.new(mix.outputs["Shader"], out.inputs["Surface"])
    world["hdri_dir"] = str(hdri_dir)
    # AUTOMATIC ignores sample_map_resolution and builds the map at the HDRI's size on every
    # world edit: 0.8 s per HDRI-lit render at 128^2 (measured); MANUAL at 256 costs 0.06 s.
    world.cycles.sampling_method = "MANUAL"
    world.cycles.sample_map_resolution = map_resolution
    return world


def set_world(world, light: dict) -> None:
    nt = world.node_tree
    env, bg_env = nt.nodes["Environment Texture"], nt.nodes["Background"]
    bg_amb, mapping = nt.nodes["Background.001"], nt.nodes["Mapping"]
    a = light["ambient"]
    bg_amb.inputs["Color"].default_value = (a, a, a, 1.0)
    hdri = light["hdri"]
    bg_env.inputs["Strength"].default_value = 0.0 if hdri is None else hdri["strength"]
    if hdri is not None:
        env.image = load_hdri(Path(world["hdri_dir"]), hdri["name"])
        mapping.inputs["Rotation"].default_value = (0.0, 0.0, math.radians(hdri["rotation_deg"]))
    sky = light.get("sky")
    if "sky" in nt.nodes:
        nt.nodes["sky_background"].inputs["Strength"].default_value = 0.0 if sky is None else sky["strength"]
        if sky is not None:
            set_sky(nt.nodes["sky"], sky)
    elif sky is not None:
        raise RenderError("a sky light in a world built without the sky's nodes (build() decides from the spec)")


def set_sky(node, sky: dict) -> None:
    """Blender's sky node from a sky light's spec (pilight/render/spec.py, _sky)."""
    node.sky_type = sky["model"]
    x, y, z = sky["sun_direction"]
    node.sun_elevation = math.asin(max(-1.0, min(1.0, z)))
    # Blender's sun direction is (sin r cos e, cos r cos e, sin e): rotation 0 puts the sun toward +y
    # (measured on equirectangular renders; tests/render/test_render_variety.py checks it on the ball).
    node.sun_rotation = math.atan2(x, y)
    node.sun_disc, node.sun_intensity = True, sky["sun_intensity"]
    node.air_density, node.aerosol_density, node.ozone_density = sky["air"], sky["aerosol"], 1.0
    node.altitude = 100.0  # metres above sea level: a scene on the ground


def hdri_path(hdri_dir: Path, name: str) -> Path:
    for suffix in (".exr", ".hdr"):
        if (hdri_dir / f"{name}{suffix}").is_file():
            return hdri_dir / f"{name}{suffix}"
    raise RenderError(f"HDRI {name!r}: no {name}.exr or {name}.hdr in {hdri_dir}")


def load_hdri(hdri_dir: Path, name: str):
    path = hdri_path(hdri_dir, name)
    img = bpy.data.images.load(str(path), check_existing=True)
    if img.size[0] == 0 or img.size[1] == 0:
        raise RenderError(f"HDRI {path}: unreadable image")
    return img


def set_lights(light: dict) -> None:
    coll = bpy.data.collections[LIGHTS_COLLECTION]
    for i, obj in enumerate(sorted(coll.objects, key=lambda o: o.name)):
        if i < len(light["points"]):
            pt = light["points"][i]
            obj.location, obj.data.energy, obj.data.shadow_soft_size = pt["location"], pt["power"], pt["radius"]
            obj.hide_render = False
        else:
            obj.hide_render = True


def look_at(obj, location, target) -> None:
    obj.location = Vector(location)
    direction = Vector(target) - Vector(location)
    obj.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()


def set_view(handles: dict, view: dict) -> None:
    cam, ball_cam = handles["camera"], handles["ball_camera"]
    look_at(cam, view["location"], view["target"])
    cam.data.lens = view["lens_mm"]
    # Orthographic ball camera: same orientation, looking at the ball from 10 radii away.
    rot = cam.rotation_euler.to_matrix()
    ball_cam.rotation_euler = cam.rotation_euler
    ball_cam.location = Vector(handles["target"]) + rot @ Vector((0, 0, 10 * BALL_RADIUS))
    bpy.context.view_layer.update()


def camera_json(cam, scene) -> dict:
    """Intrinsics K (pixels) and world_from_camera (Blender camera: -z forward, y up)."""
    res = scene.render.resolution_x
    f_px = cam.data.lens / cam.data.sensor_width * res
    K = [[f_px, 0.0, res / 2], [0.0, f_px, res / 2], [0.0, 0.0, 1.0]]
    return {
        "K": K,
        "world_from_camera": [list(row) for row in cam.matrix_world],
        "lens_mm": cam.data.lens,
        "sensor_width_mm": cam.data.sensor_width,
    }


def build(spec: dict, p: RenderParams, hdri_dir: Path) -> dict:
    """Create both scenes for `spec`; return handles used while rendering."""
    reset_blender()
    scene = bpy.context.scene
    scene.name = "pilight_main"
    configure_cycles(scene, p, spec["cycles_seed"])
    add_aov_layers(scene.view_layers[0])
    materials = []
    lowest = 0.0
    for i, o in enumerate(spec["objects"]):
        obj = _shape(o["shape"])
        obj.name = f"obj_{i:02d}_{o['shape']}"
        obj.location = o["location"]
        obj.rotation_euler = [math.radians(a) for a in o["rotation_deg"]]
        # Per-axis stretch (render.scene.stretch): Cycles moves normals by the inverse transpose of
        # the object's matrix, so the normal pass stays that of the stretched surface.
        obj.scale = [o["scale"] * s for s in o.get("stretch", (1.0, 1.0, 1.0))]
        for m in o["modifiers"]:
            _modifier(obj, m)
        mat = make_material(f"mat_{i:02d}", o["material"])
        obj.data.materials.append(mat)
        deterministic_normals(obj)
        materials.append({"object": obj.name, **o["material"]})
        lowest = min(lowest, o["location"][2] - half_height(o))
    for j, a in enumerate(spec["assets"]):
        root, meshes = import_asset(a["asset"], f"asset_{j:02d}")
        _fit_asset(root, meshes, a["size"], a["location"], a["rotation_deg"])
    _backdrop(spec["backdrop"], 0.0 if spec["kind"] == "room" else lowest)

    cam = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    scene.collection.objects.link(cam)
    scene.camera = cam
    has_sky = any(l.get("sky") for view_lights in spec["lights"] for l in view_lights)
    world = _world(hdri_dir, p.cycles.world_map_resolution, p.camera_backdrop, sky=has_sky)
    scene.world = world

    lights = bpy.data.collections.new(LIGHTS_COLLECTION)
    scene.collection.children.link(lights)
    for k in range(max(len(l["points"]) for view_lights in spec["lights"] for l in view_lights)):
        lamp = bpy.data.objects.new(f"light_{k}", bpy.data.lights.new(f"light_{k}", "POINT"))
        lights.objects.link(lamp)

    ball_scene = bpy.data.scenes.new("pilight_ball")
    configure_cycles(ball_scene, p, spec["cycles_seed"])
    ball_scene.render.film_transparent = True  # ball image is 0 outside the disk
    ball_scene.render.resolution_x = ball_scene.render.resolution_y = p.ball_resolution
    ball_scene.cycles.samples = p.ball_samples
    ball_scene.cycles.adaptive_min_samples = p.ball_min_samples
    ball_scene.world = world
    ball_scene.collection.children.link(lights)
    ball_mesh = bpy.data.meshes.new("ball")
    ball = bpy.data.objects.new("ball", ball_mesh)
    ball_scene.collection.objects.link(ball)
    import bmesh

    bm = bmesh.new()
    bmesh.ops.create_uvsphere(bm, u_segments=96, v_segments=48, radius=BALL_RADIUS)
    bm.to_mesh(ball_mesh)
    bm.free()
    ball_mesh.shade_smooth()
    ball_mesh.materials.append(gray_ball_material())
    deterministic_normals(ball)
    ball.location = spec["target"]
    ball_cam = bpy.data.objects.new("ball_camera", bpy.data.cameras.new("ball_camera"))
    ball_cam.data.type, ball_cam.data.ortho_scale = "ORTHO", 2 * BALL_RADIUS
    ball_cam.data.clip_start, ball_cam.data.clip_end = BALL_RADIUS, 40 * BALL_RADIUS
    ball_scene.collection.objects.link(ball_cam)
    ball_scene.camera = ball_cam
    return {
        "scene": scene,
        "ball_scene": ball_scene,
        "camera": cam,
        "ball_camera": ball_cam,
        "world": world,
        "target": spec["target"],
        "materials": materials,
    }


def camera_rotation(handles: dict) -> Matrix:
    return handles["camera"].matrix_world.to_3x3()
