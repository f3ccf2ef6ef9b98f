"""The small scene ``python -m kpcn.render cycles --generated`` builds inside Blender.

Runs in Blender's process (``bpy`` is passed in): a textured diffuse plane, a
glossy and a glass sphere, an area light, a world light and a camera.
"""
from __future__ import annotations

import math

#: size of the generated scene when no resolution is given
GENERATED_RESOLUTION = (128, 128)


def build_scene(bpy, scene) -> None:
    """kpcn's generated scene: textured diffuse plane, glossy and glass spheres, an area light, a world light."""
    data = bpy.data

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
        checker.inputs["Scale"].default_value = 4.0
        checker.inputs["Color1"].default_value = (0.8, 0.8, 0.8, 1.0)
        checker.inputs["Color2"].default_value = (0.2, 0.3, 0.6, 1.0)
        nt.links.new(checker.outputs["Color"], bsdf.inputs["Color"])
        return bsdf

    def glossy(nt):
        bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
        bsdf.inputs["Base Color"].default_value = (0.9, 0.6, 0.3, 1.0)
        bsdf.inputs["Metallic"].default_value = 1.0
        bsdf.inputs["Roughness"].default_value = 0.25
        return bsdf

    def glass(nt):
        bsdf = nt.nodes.new("ShaderNodeBsdfGlass")
        bsdf.inputs["IOR"].default_value = 1.45
        bsdf.inputs["Roughness"].default_value = 0.0
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
    for name, loc, radius, mat in (("glossy", (-1.1, 0.3, 1.0), 1.0, material("glossy", glossy)),
                                   ("glass", (1.2, -0.4, 0.8), 0.8, material("glass", glass))):
        add(data.objects.new(name, _sphere(data, name, radius)), mat).location = loc
    light = data.lights.new("area", type="AREA")
    light.energy = 400.0
    light.size = 1.5
    add(data.objects.new("area", light)).location = (1.5, -1.0, 4.0)
    world = data.worlds.new("world")
    scene.world = world
    bg = world.node_tree.nodes["Background"]
    bg.inputs["Color"].default_value = (0.3, 0.4, 0.6, 1.0)
    bg.inputs["Strength"].default_value = 0.8
    cam = data.cameras.new("camera")
    cam.lens = 35.0
    camera = add(data.objects.new("camera", cam))
    camera.location = (0.0, -7.0, 3.2)
    camera.rotation_euler = (math.radians(72.0), 0.0, 0.0)
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
