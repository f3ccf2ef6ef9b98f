"""What a data set frame was rendered with: its *render record*, and whether a frame on disk is stale.

A record is a small dict, stored as JSON in the frame's EXR header (attribute
``kpcnRecord``; :func:`kpcn.io.write_exr` writes string attributes as they are)
and in the data set's manifest::

    {"record": 1, "role": "input", "spp": 4, "seed": 100, "noise_role": 6,
     "resolution": [48, 48], "max_depth": 8, "pass_spp": 256,
     "source": "random:100", "fingerprint": "sha256:..."}

``fingerprint`` identifies the scene itself: for ``random:<seed>`` and
``test:<name>`` scenes (and scene dicts) a SHA-256 of the generated scene dict
(its values, transforms' matrices and bitmaps' pixels — so a change of the
scene generator changes it); for XML files a SHA-256 of the file's bytes and
its ``$name`` parameters (files it includes, meshes and textures are not
hashed). A frame is reused only when its stored record equals the one that
would be rendered now and its pixel size matches; anything else — no file, an
unreadable file, no record (another tool, an older kpcn), any differing
field — makes it stale.
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np

HEADER_KEY = "kpcnRecord"
RECORD_VERSION = 1
#: the record keys of the layers a first-hit pass re-renders (:mod:`kpcn.render.albedo`)
FIRST_HIT = ("albedo", "normal")


# ----------------------------------------------------------------------------- scene fingerprints


def update_hash(h, v) -> None:
    """Feed a canonical encoding of a scene-dict value into hash ``h`` (dict keys sorted).

    Used for frame records here and for the report's render cache.
    """
    if isinstance(v, Mapping):
        h.update(b"{")
        for k in sorted(v, key=str):
            update_hash(h, str(k))
            update_hash(h, v[k])
        h.update(b"}")
    elif isinstance(v, (list, tuple)):
        h.update(b"[")
        for x in v:
            update_hash(h, x)
        h.update(b"]")
    elif isinstance(v, (bool, np.bool_)):
        h.update(b"b1;" if v else b"b0;")
    elif isinstance(v, (int, np.integer)):
        h.update(f"i{int(v)};".encode())
    elif isinstance(v, (float, np.floating)):
        h.update(f"f{float(v)!r};".encode())
    elif isinstance(v, str):
        b = v.encode()
        h.update(f"s{len(b)}:".encode() + b)
    elif v is None:
        h.update(b"n;")
    elif isinstance(v, np.ndarray):
        _feed_array(h, v)
    elif type(v).__name__ == "Bitmap":
        h.update(f"bitmap:{v.pixel_format()}:{v.component_format()}:{bool(v.srgb_gamma())}:".encode())
        _feed_array(h, np.array(v))
    elif hasattr(v, "matrix"):  # Mitsuba transforms
        h.update(f"{type(v).__name__}:".encode())
        _feed_array(h, np.array(v.matrix, dtype=np.float64))
    else:  # a ready-made Mitsuba object in a user's dict: only its type is known
        h.update(f"object:{type(v).__module__}.{type(v).__qualname__};".encode())


def _feed_array(h, a: np.ndarray) -> None:
    a = np.ascontiguousarray(a)
    h.update(f"array:{a.dtype.str}:{a.shape}:".encode())
    h.update(a.tobytes())


def dict_fingerprint(scene: Mapping) -> str:
    """SHA-256 of a scene dict; the film size is left out (a frame's record holds its resolution)."""
    def no_film_size(v):
        if isinstance(v, Mapping) and isinstance(v.get("film"), Mapping):
            return {**v, "film": {k: x for k, x in v["film"].items() if k not in ("width", "height")}}
        return v

    h = hashlib.sha256()
    update_hash(h, {k: no_film_size(v) for k, v in scene.items()})
    return "sha256:" + h.hexdigest()


def scene_identity(scene: Any, resolution: tuple[int, int]) -> tuple[str, str, Any]:
    """``(source, fingerprint, scene to render)`` of a data set scene.

    ``random:``/``test:`` scenes are generated here once — hashed, and returned
    as a dict (named by ``kpcn_name``) that renders exactly as the string would.
    """
    from . import cycles_scene
    from .scene import SceneError, generated_scene

    if cycles_scene.is_generated(scene):  # Blender Cycles: the generator's code + variant
        h = hashlib.sha256(Path(cycles_scene.__file__).read_bytes())
        h.update(scene.encode())
        return scene, "sha256:" + h.hexdigest(), scene
    if isinstance(scene, (str, os.PathLike)) and str(scene).startswith(("test:", "random:")):
        name, d = generated_scene(str(scene), resolution)
        return name, dict_fingerprint(d), {**d, "kpcn_name": name}
    if isinstance(scene, Mapping):
        return str(scene.get("kpcn_name", "dict")), dict_fingerprint(scene), scene
    path = Path(scene)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SceneError(f"scene file not found: {path}" if not path.exists() else
                         f"cannot read scene {path}: {exc.strerror}") from exc
    return str(path), "sha256:" + hashlib.sha256(data).hexdigest(), scene


# ----------------------------------------------------------------------------- frame records


def frame_record(*, role: str, spp: int, seed: int, noise_role: int, resolution, max_depth: int,
                 pass_spp: int, source: str, fingerprint: str, albedo: int | None = None,
                 normal: int | None = None) -> dict:
    """A frame's render record; ``albedo`` and ``normal``: the integrator's albedo and normal revisions
    (Mitsuba frames; a record written before albedo revision 2 has neither, one before normal revision 2
    no ``normal``)."""
    rec = {"record": RECORD_VERSION, "role": role, "spp": int(spp), "seed": int(seed), "noise_role": int(noise_role),
           "resolution": [int(v) for v in resolution], "max_depth": int(max_depth), "pass_spp": int(pass_spp),
           "source": str(source), "fingerprint": str(fingerprint)}
    if albedo is not None:
        rec["albedo"] = int(albedo)
    if normal is not None:
        rec["normal"] = int(normal)
    return rec


def read_record(path: str | os.PathLike) -> tuple[dict | None, tuple[int, int] | None]:
    """The render record in an EXR header and the frame's ``(width, height)``; raises on an unreadable file."""
    import OpenEXR

    with OpenEXR.File(os.fspath(path), header_only=True) as f:
        header = dict(f.header())
    lo, hi = header["dataWindow"]
    size = (int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1))
    text = header.get(HEADER_KEY)
    if isinstance(text, bytes):
        text = text.decode("utf-8", "replace")
    try:
        rec = json.loads(text) if text else None
    except json.JSONDecodeError:
        rec = None
    return (rec if isinstance(rec, dict) else None), size


def _show(key: str, v) -> str:
    if key == "resolution" and isinstance(v, list) and len(v) == 2:
        return f"{v[0]}x{v[1]}"
    if key == "fingerprint" and isinstance(v, str):
        return v[:15]
    return json.dumps(v)


def _differences(have: dict, size, want: dict) -> dict:
    """``{key: the record's value}`` for each key of ``want`` the record ``have`` differs in (a record before
    albedo revision 2 has no ``albedo`` key, one before normal revision 2 no ``normal``: revision 1), then
    ``"size": size`` if the frame's ``(width, height)`` is not ``want``'s resolution."""
    have = {**{k: 1 for k in FIRST_HIT if k in want}, **have}
    diff = {k: have.get(k) for k in want if have.get(k) != want[k]}
    if list(size) != list(want["resolution"]):
        diff["size"] = size
    return diff


def _record_differences(path: Path, want: dict) -> tuple[dict, dict] | None:
    """The record of the frame at ``path`` and how it differs from ``want`` (:func:`_differences`); None when the
    file is missing, unreadable or has no record."""
    if not Path(path).is_file():  # OpenEXR would print its own error for a missing file before raising
        return None
    try:
        have, size = read_record(path)
    except Exception:
        return None
    return None if have is None else (have, _differences(have, size, want))


def first_hit_differences(path: Path, want: dict) -> list[str]:
    """The first-hit layers (``"albedo"``, ``"normal"``) whose revision alone makes the frame at ``path``
    differ from the record ``want`` (it can be brought up to date by
    :func:`kpcn.render.albedo.update_first_hit` rather than rendered again); [] when anything else differs."""
    found = _record_differences(path, want)
    diff = list(found[1]) if found else []
    return diff if diff and set(diff) <= set(FIRST_HIT) else []


def _spp_alone(path: Path, want: dict) -> int | None:
    """The spp of the frame at ``path`` when its record differs from ``want`` in the spp alone; None otherwise."""
    found = _record_differences(path, want)
    if found is None:
        return None
    have, diff = found
    spp = have.get("spp")
    return spp if set(diff) == {"spp"} and isinstance(spp, int) else None


def fewer_samples(path: Path, want: dict) -> int | None:
    """The spp of the frame at ``path`` when it differs from the record ``want`` only in having fewer samples
    (the same seed, noise role and pass size: its passes are the first of ``want``'s, so
    :func:`kpcn.render.extend_frame` can add the rest); None otherwise."""
    spp = _spp_alone(path, want)
    return spp if spp is not None and 2 <= spp < int(want["spp"]) else None


def more_samples(path: Path, want: dict, most: int) -> int | None:
    """The spp of the frame at ``path`` when it differs from the record ``want`` only in having more samples, at
    most ``most`` (a reference refined to a noise floor, :mod:`kpcn.render.refine`); None otherwise."""
    spp = _spp_alone(path, want)
    return spp if spp is not None and int(want["spp"]) < spp <= most else None


def stale_reason(path: Path, want: dict) -> str | None:
    """Why the frame at ``path`` cannot be reused for the record ``want``; None when it can."""
    if not path.exists():
        return "missing"
    try:
        have, size = read_record(path)
    except Exception as exc:  # OpenEXR raises plain RuntimeErrors for truncated files
        return f"unreadable ({exc})"
    if have is None:
        return "it has no render record (written by another tool or an older kpcn)"
    differ = _differences(have, size, want)
    diffs = [f"{'scene ' if k == 'fingerprint' else ''}{k} {_show(k, v)} -> {_show(k, want[k])}"
             for k, v in differ.items() if k != "size"]
    if not diffs and "size" in differ:
        diffs.append(f"its pixels are {size[0]}x{size[1]}, not {_show('resolution', want['resolution'])}")
    return ", ".join(diffs) if diffs else None
