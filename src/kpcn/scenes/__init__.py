"""Procedural training scenes and small named test scenes for Mitsuba 3.

Every function here returns a Mitsuba scene *dict* (as accepted by
``mi.load_dict``) containing only plain Python values, nested dicts,
``mi.Bitmap`` and ``mi.ScalarTransform4f`` objects.  The dict holds:

* ``"type": "scene"``
* ``"integrator"``: a plain ``path`` integrator (callers such as
  :mod:`kpcn.render` replace it),
* ``"sensor"``: a ``perspective`` camera with a ``look_at`` ``to_world``, an
  ``hdrfilm`` (box reconstruction filter) and an ``independent`` sampler,
* shapes with BSDFs and emitters (area, environment, point/spot lights).

Public API
----------
``random_scene(seed, resolution=(128, 128)) -> dict``
``random_scene_with_meta(seed, resolution=(128, 128)) -> (dict, dict)``
``describe_scene(seed) -> str``
``test_scene(name, resolution=(32, 32)) -> dict``
``test_scene_with_meta(name, resolution=(32, 32)) -> (dict, dict)``
``list_test_scenes() -> list[str]``
``copy_scene_dict(scene) -> dict``
``list_scene_files() -> list[str]``, ``scene_file(name) -> Path``: the Mitsuba XML
scene files shipped for evaluation (``files/*.xml``, see :mod:`kpcn.scenes.files`)

``resolution`` is ``(width, height)`` like Mitsuba's film.

Mitsuba variant: the scene builders need a variant to create ``mi.Bitmap`` /
transform objects.  If no variant is set, ``llvm_ad_rgb`` is selected (and
the LLVM version is checked); if the caller already set a variant it is kept.
The dicts are written for RGB variants (``llvm_ad_rgb``, ``scalar_rgb``,
``cuda_ad_rgb``).

Mitsuba's ``Bitmap`` and transform objects cannot be deep-copied or pickled;
use :func:`copy_scene_dict` (copies the nested dicts, shares the leaves)
before editing a scene dict, or rebuild it from its seed / name.

Layouts of random scenes: ``open`` (ground plane, sky map / constant
environment, optional area and delta lights), ``corner`` (ground plus one or
two backdrop walls), ``closed`` (room with lamps: ceiling panels, sphere
lamps, wall panels, hidden lights facing the ceiling, point/spot), ``window``
(closed room lit by a sky seen through a hole in a wall, sun aimed in) and
``cornell`` (box with an open front, camera outside).  3-10 objects
(sphere, cube, capped cylinder, disk, rectangle; stacked, floating or
intersecting now and then), sometimes a cluster of small clutter objects.

Brightness: no render in the loop.  Open scenes set each light from a target
radiance T (log-uniform 0.2-1) of a grey (albedo 0.5) surface facing it
(solid angle / inverse square / sky irradiance); rooms use an energy balance
(emitted flux ~ T * pi * area * (1 - rho) / rho, rho = mean wall albedo).
Measured (Mitsuba ``path``, 120 seeds): image mean radiance 0.013-8.5,
median 0.37, 5-95 % range 0.07-1.5; the high end comes from large emitters
seen directly.

Known Mitsuba 3.9 issue avoided here: ``bumpmap`` around ``roughplastic``
gives NaNs on some axis-aligned rectangles, so bump maps never wrap
``roughplastic``.

Modules
-------
``base`` (Mitsuba access, :func:`copy_scene_dict`), ``geometry``
(rotations, frames, shape matrices, solid angles), ``colours`` (albedos,
black-body tints), ``materials`` (procedural textures, BSDF dicts),
``sky`` (procedural sky maps), ``builder`` (the scene-dict builder),
``objects`` (object and clutter placement, camera framing), ``lights``
(light intensities and placement), ``layouts`` (random scenes),
``named`` (named test scenes) and ``files`` (the shipped XML scene files).
"""

from __future__ import annotations

from .base import _mi, copy_scene_dict  # noqa: F401  (_mi: used by tests to select the variant)
from .files import list_scene_files, scene_file
from .layouts import describe_scene, random_scene, random_scene_with_meta
from .lights import LIGHT_CLASSES
from .materials import MATERIAL_CLASSES
from .named import list_test_scenes, test_scene, test_scene_with_meta

__all__ = [
    "random_scene",
    "random_scene_with_meta",
    "describe_scene",
    "test_scene",
    "test_scene_with_meta",
    "list_test_scenes",
    "copy_scene_dict",
    "list_scene_files",
    "scene_file",
    "MATERIAL_CLASSES",
    "LIGHT_CLASSES",
]
