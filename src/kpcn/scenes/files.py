"""Mitsuba 3 XML scene files shipped with kpcn (``src/kpcn/scenes/files/*.xml``), for evaluation.

They use Mitsuba's built-in shapes (rectangle, cube, sphere, disk, cylinder),
BSDFs and emitters only: no meshes or textures to download, no participating
media. None of them is used for training. The report names them
``file:<name>`` (:func:`scene_file` turns a name into its path):

* ``cbox_glossy``: a closed Cornell-style room, ceiling light, a rough
  aluminium block, a glass ball (caustics) and a glossy plastic ball;
* ``material_test``: five spheres (diffuse, plastic, rough plastic, rough
  gold, rough glass) on a checkered floor, a large disk light and a rim light;
* ``sun_yard``: an open yard lit by a constant sky and a directional sun
  (principled, rough copper and thin-glass surfaces);
* ``lamp_room``: an interior lit only indirectly (a spot light aimed at the
  ceiling, a small lamp hidden behind a screen): fireflies at low spp.

Each file declares ``<default name="res" value="256"/>`` for its film size;
kpcn's renderer replaces the film anyway (:func:`kpcn.render.load_scene`).
"""
from __future__ import annotations

from pathlib import Path

FILES_DIR = Path(__file__).resolve().parent / "files"
PREFIX = "file:"


def list_scene_files() -> list[str]:
    """Names of the shipped scene files (without ``.xml``), sorted."""
    return sorted(p.stem for p in FILES_DIR.glob("*.xml"))


def scene_file(name: str) -> Path:
    """The path of the shipped scene file ``name`` (``"cbox_glossy"`` or ``"file:cbox_glossy"``).

    Raises:
        ValueError: no shipped scene file has that name (the message lists them).
    """
    stem = name[len(PREFIX):] if name.startswith(PREFIX) else name
    path = FILES_DIR / f"{stem}.xml"
    if not stem or "/" in stem or "\\" in stem or not path.is_file():
        raise ValueError(f"unknown scene file {name!r}; shipped: "
                         f"{', '.join(PREFIX + n for n in list_scene_files())}")
    return path
