"""The small scene ``python -m kpcn.render cycles --generated`` builds inside Blender.

Runs in Blender's process (``bpy`` is passed in): a textured diffuse plane, a
glossy and a glass sphere, an area light, a world light and a camera.
"""
from __future__ import annotations

import math
import os

#: size of the generated scene when no resolution is given
GENERATED_RESOLUTION = (128, 128)
#: the scene's name in data sets and reports; ``cycles:generated:<N>`` is its variant N
GENERATED = "cycles:generated"


def is_generated(name) -> bool:
    """Whether ``name`` is ``cycles:generated`` or ``cycles:generated:<...>``."""
    s = os.fspath(name) if isinstance(name, (str, os.PathLike)) else None
    return s is not None and (s == GENERATED or s.startswith(GENERATED + ":"))


def generated_variant(name) -> int | None:
    """N of ``cycles:generated:<N>`` (None for ``cycles:generated``); ValueError for any other name."""
    s = os.fspath(name)
    if s == GENERATED:
        return None
    tail = s[len(GENERATED) + 1:]
    if not s.startswith(GENERATED + ":") or not tail.isdigit():
        raise ValueError(f"{s}: a generated Cycles scene is cycles:generated or cycles:generated:<N> (N >= 0)")
    return int(tail)


def scene_params(variant: int | None = None) -> dict:
    """The generated scene's parameters: the fixed layout (``variant`` None), or one drawn from ``variant``
    (a seed >= 0): checker colours and scale, the metal's colour and roughness, the glass's IOR, roughness and
    tint, sphere sizes and places, the area light, the sky and the camera's azimuth all vary."""
    p = {"checker_scale": 4.0, "color1": (0.8, 0.8, 0.8), "color2": (0.2, 0.3, 0.6),
         "metal_color": (0.9, 0.6, 0.3), "metal_roughness": 0.25, "glass_ior": 1.45, "glass_roughness": 0.0,
         "glass_color": (1.0, 1.0, 1.0), "glossy": ((-1.1, 0.3), 1.0), "glass": ((1.2, -0.4), 0.8),
         "light_location": (1.5, -1.0, 4.0), "light_energy": 400.0, "light_size": 1.5,
         "sky": (0.3, 0.4, 0.6), "sky_strength": 0.8, "azimuth": 0.0}
    if variant is None:
        return p
    if isinstance(variant, bool) or not isinstance(variant, int) or variant < 0:
        raise ValueError(f"generated Cycles scene: variant must be an integer >= 0, got {variant!r}")
    import random

    r = random.Random(variant)
    rgb = lambda lo, hi: tuple(round(r.uniform(lo, hi), 3) for _ in range(3))  # noqa: E731
    p.update(checker_scale=r.uniform(2.0, 10.0), color1=rgb(0.4, 0.9), color2=rgb(0.02, 0.5),
             metal_color=rgb(0.3, 0.95), metal_roughness=r.choice([0.02, 0.1, 0.25, 0.5]),
             glass_ior=r.uniform(1.3, 1.7), glass_roughness=r.choice([0.0, 0.0, 0.05, 0.2]),
             glass_color=rgb(0.7, 1.0), glossy=((r.uniform(-2.0, -0.6), r.uniform(-0.8, 1.2)), r.uniform(0.5, 1.2)),
             glass=((r.uniform(0.6, 2.0), r.uniform(-1.2, 0.8)), r.uniform(0.4, 1.0)),
             light_location=(r.uniform(-3.0, 3.0), r.uniform(-3.0, 1.0), r.uniform(2.5, 5.0)),
             light_energy=r.uniform(100.0, 900.0), light_size=r.choice([0.2, 0.5, 1.5, 3.0]),
             sky=rgb(0.05, 0.8), sky_strength=r.choice([0.0, 0.1, 0.5, 1.0]), azimuth=r.uniform(-25.0, 25.0))
    return p


def build_scene(bpy, scene, variant: int | None = None) -> None:
    """kpcn's generated scene: textured diffuse plane, glossy and glass spheres, an area light, a world light
    (the fixed layout, or the one :func:`scene_params` draws from ``variant``)."""
    data = bpy.data
    p = scene_params(variant)

    def material(name: str, make):
        m = data.materials.new(name)
        nt = m.node_tree
        nt.nodes.clear()
        out = nt.nodes.new("ShaderNodeOutputMaterial")
        nt.links.new(make(nt).outputs[0], out.inputs["Surface"])
        return m

    def diffuse(nt):
        bsdf = nt.nodes.new("ShaderNodeBsdfDiffuse")
        checker = nt.nodes.new("ShaderNodeTexChecker")
        checker.inputs["Scale"].default_value = p["checker_scale"]
        checker.inputs["Color1"].default_value = (*p["color1"], 1.0)
        checker.inputs["Color2"].default_value = (*p["color2"], 1.0)
        nt.links.new(checker.outputs["Color"], bsdf.inputs["Color"])
        return bsdf

    def glossy(nt):
        bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
        bsdf.inputs["Base Color"].default_value = (*p["metal_color"], 1.0)
        bsdf.inputs["Metallic"].default_value = 1.0
        bsdf.inputs["Roughness"].default_value = p["metal_roughness"]
        return bsdf

    def glass(nt):
        bsdf = nt.nodes.new("ShaderNodeBsdfGlass")
        bsdf.inputs["IOR"].default_value = p["glass_ior"]
        bsdf.inputs["Roughness"].default_value = p["glass_roughness"]
        bsdf.inputs["Color"].default_value = (*p["glass_color"], 1.0)
        return bsdf

    def add(obj, mat=None):
        scene.collection.objects.link(obj)
        if mat is not None:
            obj.data.materials.append(mat)
        return obj

    plane = data.meshes.new("plane")
    s = 6.0
    plane.from_pydata([(-s, -s, 0), (s, -s, 0), (s, s, 0), (-s, s, 0)], [], [(0, 1, 2, 3)])
    plane.uv_layers.new(name="UVMap")
    add(data.objects.new("plane", plane), material("diffuse", diffuse))
    for name, make in (("glossy", glossy), ("glass", glass)):
        (x, y), radius = p[name]
        add(data.objects.new(name, _sphere(data, name, radius)), material(name, make)).location = (x, y, radius)
    light = data.lights.new("area", type="AREA")
    light.energy = p["light_energy"]
    light.size = p["light_size"]
    add(data.objects.new("area", light)).location = p["light_location"]
    world = data.worlds.new("world")
    scene.world = world
    bg = world.node_tree.nodes["Background"]
    bg.inputs["Color"].default_value = (*p["sky"], 1.0)
    bg.inputs["Strength"].default_value = p["sky_strength"]
    cam = data.cameras.new("camera")
    cam.lens = 35.0
    camera = add(data.objects.new("camera", cam))
    az = math.radians(p["azimuth"])  # the camera circles the origin; the fixed layout looks along +y
    camera.location = (7.0 * math.sin(az), -7.0 * math.cos(az), 3.2)
    camera.rotation_euler = (math.radians(72.0), 0.0, az)
    scene.camera = camera
    scene.render.resolution_x, scene.render.resolution_y = GENERATED_RESOLUTION
    scene.render.resolution_percentage = 100


def _sphere(data, name: str, radius: float, segments: int = 48, rings: int = 24):
    """A smooth-shaded UV sphere mesh (built from vertices: no operator, no context needed)."""
    verts = [(0.0, 0.0, radius)]
    for i in range(1, rings):
        theta = math.pi * i / rings
        for j in range(segments):
            phi = 2 * math.pi * j / segments
            verts.append((radius * math.sin(theta) * math.cos(phi), radius * math.sin(theta) * math.sin(phi),
                          radius * math.cos(theta)))
    verts.append((0.0, 0.0, -radius))
    bottom = len(verts) - 1
    faces = [(0, 1 + j, 1 + (j + 1) % segments) for j in range(segments)]
    for i in range(rings - 2):
        a, b = 1 + i * segments, 1 + (i + 1) * segments
        faces += [(a + j, b + j, b + (j + 1) % segments, a + (j + 1) % segments) for j in range(segments)]
    last = 1 + (rings - 2) * segments
    faces += [(last + (j + 1) % segments, last + j, bottom) for j in range(segments)]
    mesh = data.meshes.new(name)
    mesh.from_pydata(verts, [], faces)
    mesh.shade_smooth()
    return mesh
