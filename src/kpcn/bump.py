"""The shading normal a bump- or normal-mapped BSDF shades with, for the ``normal`` layer.

Mitsuba's ``bumpmap`` and ``normalmap`` are BSDF adapters: they tilt the shading frame inside the BSDF,
and ``SurfaceInteraction3f.sh_frame`` (what the ``normal`` layer held up to normal revision 1) never
sees it. A denoiser guided by such a normal cannot tell a bumpy glossy wall's glints from noise, and
other renderers' normal passes (Cycles, the convention OIDN asks for) carry the mapped normal. Normal
revision 2 (:data:`kpcn.integrator.NORMAL_REVISION`) writes it for ``bumpmap`` (height ``h`` from its
texture, times ``scale``): the surface displaced along the shading normal ``n`` by ``h`` has tangents
``dp/du + n (dh/du - n·dp/du)`` and the same in ``v``; their cross product, turned to the side of the
geometric normal, is the bumped normal. ``tests/test_bump.py`` checks it against the BSDF's own evaluation.

Normal revision 3 adds ``normalmap``: its texture's value ``t`` (as the texture evaluates it, so a bitmap's
own colour handling applies) gives the normal ``normalize(2 t - 1)`` in the shading frame, which Mitsuba's
adapter shades with (``tests/test_bump.py`` recovers the normal the BSDF shades with from three evaluations: it
agrees to 0.12°).

Each BSDF of the scene's shapes is searched (through ``twosided`` and other adapters) for the first bump or normal
map; the integrator asks :func:`mapped_normal` for the hits on those BSDFs.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["BumpMap", "find_bump_maps", "mapped_normal"]


@dataclass
class BumpMap:
    """One BSDF of a scene that bump- or normal-maps its shading normal.

    Attributes:
        bsdf: the BSDF the shapes hold (the pointer ``si.bsdf()`` returns for their hits).
        texture: the bump map's height texture, or the normal map's texture.
        scale: the bump map's height scale (1 for a normal map).
        kind: ``"bump"`` or ``"normal"``.
    """

    bsdf: Any
    texture: Any
    scale: float
    kind: str = "bump"


#: Mitsuba's shading-frame adapters: class name -> (kind, the parameter naming their texture)
_ADAPTERS = {"BumpMap": ("bump", "nested_texture"), "NormalMap": ("normal", "normalmap")}


def _bump_adapter(bsdf) -> tuple[Any, float, str] | None:
    """The first ``BumpMap`` or ``NormalMap`` inside ``bsdf`` (itself included): ``(texture, scale, kind)``."""
    import mitsuba as mi

    found: list = []

    class Walk(mi.TraversalCallback):
        def put(self, name, value, *rest):
            if found or not isinstance(value, mi.BSDF):
                return
            if value.class_name() in _ADAPTERS:
                found.append(value)
            else:
                value.traverse(Walk())

    if bsdf.class_name() in _ADAPTERS:
        found.append(bsdf)
    else:
        bsdf.traverse(Walk())
    if not found:
        return None
    kind, texture_name = _ADAPTERS[found[0].class_name()]
    textures: list = []

    class Textures(mi.TraversalCallback):
        def put(self, name, value, *rest):
            if isinstance(value, mi.Texture) and name == texture_name:
                textures.append(value)

    found[0].traverse(Textures())
    if len(textures) != 1:
        return None  # an adapter of a layout this module does not know: the unmapped normal stays
    scale = float(mi.traverse(found[0])["scale"]) if kind == "bump" else 1.0
    return textures[0], scale, kind


def find_bump_maps(scene) -> list[BumpMap]:
    """The distinct BSDFs of ``scene``'s shapes that bump- or normal-map their shading frame."""
    seen: dict[int, BumpMap] = {}
    for shape in scene.shapes():
        bsdf = shape.bsdf()
        if bsdf is None or id(bsdf) in seen:
            continue
        found = _bump_adapter(bsdf)
        if found is not None:
            seen[id(bsdf)] = BumpMap(bsdf, *found)
    return list(seen.values())


def mapped_normal(maps: list[BumpMap], si, bsdf_ptr, normal, active):
    """``normal`` (world space, a Dr.Jit ``Vector3f``) with the mapped normal where ``si`` hit one of ``maps``.

    Args:
        maps: :func:`find_bump_maps` of the scene ``si`` was found in.
        si: the first hits (``mi.SurfaceInteraction3f`` with ``dp_du``/``dp_dv``: ``RayFlags.All``).
        bsdf_ptr: ``si.bsdf(ray)``.
        normal: the unmapped normal (``si.sh_frame.n`` where ``active``, else 0).
        active: the lanes that hit something.
    """
    import drjit as dr
    import mitsuba as mi

    n = si.sh_frame.n
    for m in maps:
        on = active & (bsdf_ptr == mi.BSDFPtr(m.bsdf))
        if m.kind == "normal":  # the texture's normal in the shading frame, as the adapter builds its frame
            mapped = si.sh_frame.to_world(mi.Vector3f(dr.normalize(m.texture.eval_3(si, on) * 2.0 - 1.0)))
            normal = dr.select(on & dr.all(dr.isfinite(mapped)), mapped, normal)
            continue
        grad = m.texture.eval_1_grad(si, on) * m.scale
        du = si.dp_du + n * (grad.x - dr.dot(n, si.dp_du))
        dv = si.dp_dv + n * (grad.y - dr.dot(n, si.dp_dv))
        bumped = dr.normalize(dr.cross(du, dv))
        bumped = dr.select(dr.dot(si.n, bumped) < 0.0, -bumped, bumped)
        normal = dr.select(on & dr.all(dr.isfinite(bumped)), bumped, normal)
    return normal
