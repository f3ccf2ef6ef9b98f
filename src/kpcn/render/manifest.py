"""Data set manifests: their format, whether a data set is complete, and :class:`DatasetError`.

``<root>/manifest.json`` is written by :func:`kpcn.render.render_dataset` (format 2)::

    {
      "format": 2,
      "complete": false,            # true only once every scene is rendered and checked
      "procedural": true,           # scenes are random:<first_seed> ... random:<first_seed + n_scenes - 1>
      "n_scenes": 24, "first_seed": 0, "spp": [2, 4, 8, 16, 32], "ref_spp": 1024,
      "resolution": [128, 128], "max_depth": 8, "pass_spp": 256,
      "scenes": [                   # the scenes finished so far, in order
        {"name": "random_0", "source": "random:0", "seed": 0, "fingerprint": "sha256:...",
         "inputs": {"2": "random_0/input_2spp.exr", ...}, "reference": "random_0/reference.exr",
         "frames": {"random_0/input_2spp.exr": {<the frame's render record>}, ...}}
      ]
    }

The manifest is rewritten (atomically) before the first frame of a run is
changed, with ``"complete": false``, and after every scene; ``"complete": true``
is written only after the last scene. Each frame's render record (see
:mod:`kpcn.render.record`) is also stored in the frame's own EXR header.

Manifests written before kpcn recorded completeness (no ``"format"`` key:
``spp``, ``ref_spp``, ``resolution`` and ``scenes`` only) are *legacy*: they
were rewritten after every scene, so a data set whose render was interrupted
cannot be told from a smaller complete one. They are still read — with a
warning, and only when every file they list exists — so data sets rendered
before are not lost; running ``python -m kpcn.render dataset`` on such a folder
renders its frames again, as they carry no render record.

This module imports nothing heavy (no Mitsuba, no torch).
"""
from __future__ import annotations

import json
import shlex
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

MANIFEST = "manifest.json"
FORMAT = 2
#: the settings ensure_dataset compares, in the order its messages list them
SETTING_KEYS = ("n_scenes", "first_seed", "spp", "ref_spp", "resolution", "ref_floor_target", "ref_spp_max")
#: the settings of references refined to a noise floor; a manifest without them refines none
REFINE_KEYS = ("ref_floor_target", "ref_spp_max")


class DatasetError(ValueError):
    """A data set folder that cannot be used as asked: incomplete, other settings, missing or broken files.

    The message names the folder, what is wrong and the command that fixes it.
    """


def settings(n_scenes: int, spp: Sequence[int], ref_spp: int, resolution: Sequence[int], first_seed: int,
             ref_floor_target: float | None = None, ref_spp_max: int | None = None) -> dict:
    """The settings of a procedural data set, as the manifest stores them (``ref_floor_target`` and
    ``ref_spp_max`` only when references are refined: :func:`kpcn.render.refine.refined_spp`)."""
    s = {"n_scenes": int(n_scenes), "first_seed": int(first_seed), "spp": [int(s) for s in dict.fromkeys(spp)],
         "ref_spp": int(ref_spp), "resolution": [int(v) for v in resolution]}
    if ref_floor_target is not None:
        s.update(ref_floor_target=float(ref_floor_target), ref_spp_max=int(ref_spp_max or ref_spp))
    return s


def render_command(root: str | Path, s: dict) -> str:
    """The ``python -m kpcn.render dataset`` command that renders (or resumes) the data set ``s``."""
    w, h = s["resolution"]
    return (f"python -m kpcn.render dataset --out {shlex.quote(str(root))} --scenes {s['n_scenes']} "
            f"--first-seed {s['first_seed']} --spp {' '.join(map(str, s['spp']))} --ref-spp {s['ref_spp']} "
            f"--resolution {w} {h}" + _refine_flags(s))


def _refine_flags(s: dict) -> str:
    if s.get("ref_floor_target") is None:
        return ""
    return f" --ref-floor-target {s['ref_floor_target']:g} --ref-spp-max {s['ref_spp_max']}"


def _refine_text(s: dict) -> str:
    if s.get("ref_floor_target") is None:
        return ""
    return f" (refined to a floor of relMSE {s['ref_floor_target']:g}, at most {s['ref_spp_max']} spp)"


def _text(key: str, value: Any) -> str:
    if key == "resolution":
        return f"{value[0]}x{value[1]}"
    if key == "spp":
        return " ".join(map(str, value))
    if key == "procedural":
        return "procedural scenes" if value else "a custom scene list"
    return str(value)


def describe(s: dict) -> str:
    """One line: ``24 scenes from seed 0, spp 2 4 8, ref_spp 1024, 128x128``."""
    if not s.get("procedural", True):
        return f"{s['n_scenes']} scenes from a custom scene list, spp {_text('spp', s['spp'])}, " \
               f"ref_spp {s['ref_spp']}{_refine_text(s)}, {_text('resolution', s['resolution'])}"
    return (f"{s['n_scenes']} scenes from seed {s['first_seed']}, spp {_text('spp', s['spp'])}, "
            f"ref_spp {s['ref_spp']}{_refine_text(s)}, {_text('resolution', s['resolution'])}")


def differences(have: dict, want: dict) -> list[str]:
    """``["resolution 8x8 (requested 12x12)", ...]``: the settings in which ``have`` differs from ``want``."""
    out = []
    hp, wp = have.get("procedural", True), want.get("procedural", True)
    if hp != wp:
        out.append(f"scenes: {_text('procedural', hp)} (requested {_text('procedural', wp)})")
    for k in SETTING_KEYS:
        a, b = have.get(k), want.get(k)
        if k == "spp":
            a, b = sorted(a or []), sorted(b or [])
        if a != b:
            name = {"n_scenes": "scenes", "first_seed": "first seed"}.get(k, k)
            if k in REFINE_KEYS:
                out.append(f"{k} {'none' if a is None else a} (requested {'none' if b is None else b})")
                continue
            out.append(f"{name} {_text(k, a) if a is not None else '?'} (requested {_text(k, b)})")
    return out


def load_manifest(root: str | Path) -> dict | None:
    """The manifest of ``root`` as a dict, or None when there is none; :class:`DatasetError` when unreadable."""
    path = Path(root) / MANIFEST
    if not path.exists():
        return None
    try:
        m = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{root}: cannot read {MANIFEST} ({exc}); render the data set again "
                           f"with `python -m kpcn.render dataset --out {shlex.quote(str(root))} ...`") from exc
    if not isinstance(m, dict) or not isinstance(m.get("scenes"), list):
        raise DatasetError(f"{root}: {MANIFEST} is not a kpcn data set manifest (no list of scenes)")
    return m


def manifest_settings(m: dict) -> dict:
    """The settings a manifest records (inferred from the scene list for legacy manifests)."""
    scenes = m["scenes"]
    first = int(m.get("first_seed", scenes[0]["seed"] if scenes else 0))
    if "format" in m:
        procedural = bool(m.get("procedural", True))
        n = int(m["n_scenes"])
    else:  # legacy: n_scenes is what it lists; procedural when the sources are random:<seed> in order
        n = len(scenes)
        procedural = all(sc.get("source") == f"random:{first + i}" for i, sc in enumerate(scenes))
    return {"n_scenes": n, "first_seed": first, "spp": [int(s) for s in m.get("spp", [])],
            "ref_spp": int(m.get("ref_spp", 0)), "resolution": [int(v) for v in m.get("resolution", [0, 0])],
            "procedural": procedural, **{k: m[k] for k in REFINE_KEYS if m.get(k) is not None}}


def listed_files(m: dict) -> list[str]:
    """Every frame the manifest lists (paths relative to the data set folder)."""
    out = []
    for sc in m["scenes"]:
        out += list(sc["inputs"].values()) + [sc["reference"]]
    return out


@dataclass
class DatasetStatus:
    """What a data set folder holds (:func:`dataset_status`)."""

    root: Path
    manifest: dict | None  #: None: no manifest.json
    complete: bool | None = None  #: None for a legacy manifest (completeness was not recorded)
    settings: dict = field(default_factory=dict)
    rendered: int = 0  #: scenes finished
    missing: list[str] = field(default_factory=list)  #: listed frames that are not on disk

    @property
    def legacy(self) -> bool:
        return self.manifest is not None and "format" not in self.manifest

    def command(self) -> str:
        """The command that renders or resumes this data set (its own settings)."""
        if not self.settings.get("procedural", True):
            return "the render_dataset(..., scenes=[...]) call that made it (a custom scene list)"
        return render_command(self.root, self.settings)


def dataset_status(root: str | Path) -> DatasetStatus:
    """Read ``root``'s manifest and check that the frames it lists exist (no pixel is read)."""
    root = Path(root)
    m = load_manifest(root)
    if m is None:
        return DatasetStatus(root, None)
    try:
        s = manifest_settings(m)
        files = listed_files(m)
        complete = bool(m["complete"]) if "format" in m else None
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise DatasetError(f"{root}: {MANIFEST} is damaged ({type(exc).__name__}: {exc}); render the data set "
                           f"again with `python -m kpcn.render dataset --out {shlex.quote(str(root))} ...`") from exc
    missing = [f for f in files if not (root / f).is_file()]
    return DatasetStatus(root, m, complete, s, len(m["scenes"]), missing)


def missing_text(missing: list[str]) -> str:
    shown = ", ".join(missing[:3]) + (f" and {len(missing) - 3} more" if len(missing) > 3 else "")
    return f"{len(missing)} listed frame(s) missing: {shown}"


def check_usable(status: DatasetStatus) -> None:
    """Raise :class:`DatasetError` unless ``status`` is a complete data set whose files all exist.

    Legacy manifests pass (with a ``UserWarning``) when every file they list exists.
    """
    import warnings

    root = status.root
    if status.manifest is None:
        raise DatasetError(f"{root}: no {MANIFEST}: not a data set")
    if status.complete is False:
        raise DatasetError(f"{root}: incomplete data set: {status.rendered} of {status.settings['n_scenes']} scenes "
                           f"rendered (its render was interrupted); finish it with `{status.command()}` (it resumes "
                           f"and keeps the finished frames)")
    if status.missing:
        raise DatasetError(f"{root}: {missing_text(status.missing)}; render them with `{status.command()}`")
    if status.complete is None:
        warnings.warn(f"{root}: {MANIFEST} was written before kpcn recorded whether a data set is complete; its "
                      f"{status.rendered} scene(s) are used as they are (run `{status.command()}` to check it and "
                      f"record it as complete: it renders frames without a render record again)",
                      UserWarning, stacklevel=3)
