"""One method against another on the same frames: ``python -m kpcn.report.compare``.

Reads the ``results.csv`` of finished reports (no rendering, no denoising) and prints, per spp, each method's mean
PSNR / relMSE / SSIM over the (scene, spp) frames both were run on, how many of those figures the candidate wins, and
the scenes that move each mean most. It is how a candidate is chosen on validation scenes: a mean can hide one scene
that loses several dB while the others gain a little, and this names that scene.

The two reports must have measured the same frames against the same references (their ``ref_spp`` and ``ref_floor``
per scene): otherwise the comparison is refused, naming the scenes that differ.

A side may pool several reports, ``DIR[:METHOD]+DIR[:METHOD]...`` (each its own method): the means are then over
all their scenes. A candidate chosen on one validation set is the best of several on those scenes, so its lead there
is biased upwards; a second set of scenes, pooled with the first, is how a later candidate is judged against it.

Example (the default against a fine-tune, on two reports of the same cached renders)::

    python -m kpcn.report.compare results/rep/val3:unet_kpcn results/rep/val11:rN
    python -m kpcn.report.compare results/rep/v1_sf:sf+results/rep/v2:unet_kpcn \
        results/rep/v1_g3:g3+results/rep/v2_g3:g3
"""
from __future__ import annotations

import argparse
import csv
import sys
from dataclasses import dataclass, field
from pathlib import Path

from .config import MC

__all__ = ["Side", "Comparison", "load_side", "compare", "markdown", "main"]

#: the figures compared, each with True where higher is better
FIGURES = (("psnr", True), ("relmse", False), ("ssim", True))
#: the columns that must agree between two reports' rows of one (scene, spp) for them to be the same frame
_SAME_FRAME = ("ref_spp", "ref_floor", "width", "height")


@dataclass
class Side:
    """The rows of one method in one report: ``rows[(scene, spp)]`` is that frame's CSV row."""

    label: str
    rows: dict[tuple[str, int], dict] = field(default_factory=dict)
    #: the report's folder name: added to the label where both sides have the same method
    report: str = ""


@dataclass
class Comparison:
    """``means[label][spp][figure]`` over the shared frames; ``wins`` / ``losses``: (spp, figure) pairs where the
    candidate's mean is better / worse than the base's; ``moves[spp][figure]``: (scene, candidate - base, base)
    sorted from the candidate's worst scene to its best (the difference signed so that negative is worse for every
    figure: what moves the mean most comes first)."""

    base: str
    candidate: str
    spps: list[int]
    means: dict[str, dict[int, dict[str, float]]]
    wins: list[tuple[int, str]]
    losses: list[tuple[int, str]]
    moves: dict[int, dict[str, list[tuple[str, float, float]]]]


def load_side(spec: str) -> Side:
    """``DIR[:METHOD]``: the rows of ``METHOD`` in ``DIR/results.csv`` (a report's folder). Without ``METHOD``, the
    report's one method besides raw Monte Carlo; a report with several must name one. ``SPEC+SPEC...``: the rows of
    several reports pooled (no frame in two of them)."""
    if "+" in spec:
        return _pooled([load_side(part) for part in spec.split("+")], spec)
    path, _, method = spec.partition(":")
    csv_path = Path(path) / "results.csv"
    if not csv_path.is_file():
        raise FileNotFoundError(f"{spec}: no results.csv in {path} (a finished report's folder)")
    with open(csv_path, newline="") as f:
        rows = list(csv.DictReader(f))
    methods = sorted({r["method"] for r in rows if r["method"] != MC})
    if not method:
        if len(methods) != 1:
            have = ", ".join(methods) or "none"
            raise ValueError(f"{spec}: name one method as {path}:METHOD (the report has {have})")
        method = methods[0]
    if method not in methods and method != MC:
        raise ValueError(f"{spec}: no method {method!r} in {csv_path} (it has {', '.join(methods)})")
    side = Side(label=method, report=Path(path).name)
    for r in rows:
        if r["method"] == method:
            side.rows[(r["scene"], int(r["spp"]))] = r
    return side


def _pooled(sides: list[Side], spec: str) -> Side:
    """One side of the rows of ``sides`` (each from its own report), labelled by their methods and reports."""
    rows: dict[tuple[str, int], dict] = {}
    for side in sides:
        twice = sorted(f"{s} at {spp} spp" for s, spp in set(rows) & set(side.rows))
        if twice:
            raise ValueError(f"{spec}: {', '.join(twice[:3])} in more than one of the pooled reports")
        rows.update(side.rows)
    label = "+".join(dict.fromkeys(s.label for s in sides))
    return Side(label=label, rows=rows, report="+".join(s.report for s in sides))


def _same_frames(base: Side, cand: Side) -> list[tuple[str, int]]:
    shared = sorted(set(base.rows) & set(cand.rows))
    if not shared:
        raise ValueError(f"{base.label} and {cand.label} share no (scene, spp) frame")
    differ = sorted({s for s, spp in shared
                     if any(base.rows[(s, spp)].get(k) != cand.rows[(s, spp)].get(k) for k in _SAME_FRAME)})
    if differ:
        raise ValueError(f"{base.label} and {cand.label} were measured against different references or sizes "
                         f"({', '.join(_SAME_FRAME)}) on {', '.join(differ)}: not the same frames")
    return shared


def compare(base: Side, cand: Side) -> Comparison:
    """``cand`` against ``base`` on the frames both have (see :class:`Comparison`)."""
    shared = _same_frames(base, cand)
    if base.label == cand.label:  # one method in two reports: name each by its report
        base = Side(f"{base.label} ({base.report})", base.rows, base.report)
        cand = Side(f"{cand.label} ({cand.report})", cand.rows, cand.report)
        if base.label == cand.label:
            raise ValueError(f"{base.label} against itself: name two reports or two methods")
    spps = sorted({spp for _, spp in shared})
    means: dict[str, dict[int, dict[str, float]]] = {base.label: {}, cand.label: {}}
    wins, losses, moves = [], [], {}
    for spp in spps:
        scenes = [s for s, p in shared if p == spp]
        moves[spp] = {}
        for side in (base, cand):
            means[side.label][spp] = {k: sum(float(side.rows[(s, spp)][k]) for s in scenes) / len(scenes)
                                      for k, _ in FIGURES}
        for k, higher in FIGURES:
            sign = 1.0 if higher else -1.0
            d = sign * (means[cand.label][spp][k] - means[base.label][spp][k])
            (wins if d > 0 else losses if d < 0 else []).append((spp, k))
            per = [(s, sign * (float(cand.rows[(s, spp)][k]) - float(base.rows[(s, spp)][k])),
                    float(base.rows[(s, spp)][k])) for s in scenes]
            moves[spp][k] = sorted(per, key=lambda t: t[1])
    return Comparison(base.label, cand.label, spps, means, wins, losses, moves)


def _fig(k: str, v: float) -> str:
    return f"{v:.2f}" if k == "psnr" else f"{v:.6f}" if k == "relmse" else f"{v:.5f}"


def markdown(c: Comparison, worst: int = 2) -> str:
    """The means table, the count of figures won, and each spp's ``worst`` scenes per figure for the candidate."""
    lines = [f"## {c.candidate} against {c.base}", "",
             f"| spp | {c.base} (PSNR / relMSE / SSIM) | {c.candidate} | candidate better on |", "|---|---|---|---|"]
    for spp in c.spps:
        cells = [" / ".join(_fig(k, c.means[m][spp][k]) for k, _ in FIGURES) for m in (c.base, c.candidate)]
        better = ", ".join(k for s, k in c.wins if s == spp) or "none"
        lines.append(f"| {spp} | {cells[0]} | {cells[1]} | {better} |")
    n = len(c.spps) * len(FIGURES)
    lines += ["", f"{c.candidate} wins {len(c.wins)} of {n} figures and loses {len(c.losses)}.", ""]
    if worst > 0:
        lines += ["The scenes that cost the candidate most, per spp (PSNR and SSIM: candidate − base; relMSE: its "
                  "rise as a fraction of the base's on that scene):", ""]
        for spp in c.spps:
            parts = []
            for k, _ in FIGURES:
                picks = [(s, -d / max(b, 1e-12) if k == "relmse" else d) for s, d, b in c.moves[spp][k][:worst]
                         if d < 0]
                parts.append(f"{k}: " + (", ".join(f"{s} {d:+.3g}" for s, d in picks) or "none worse"))
            lines.append(f"- {spp} spp: " + "; ".join(parts))
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m kpcn.report.compare", description=__doc__.split("\n\n")[0])
    p.add_argument("base", help="REPORT_DIR[:METHOD]: the method compared against (REPORT_DIR[:METHOD]+...: "
                                "several reports pooled)")
    p.add_argument("candidates", nargs="+", help="REPORT_DIR[:METHOD] each (or several pooled with +)")
    p.add_argument("--worst", type=int, default=2, help="scenes listed per spp and figure (default: 2; 0: none)")
    a = p.parse_args(argv)
    try:
        base = load_side(a.base)
        out = [markdown(compare(base, load_side(spec)), a.worst) for spec in a.candidates]
    except (FileNotFoundError, ValueError) as e:
        print(f"kpcn.report.compare: {e}", file=sys.stderr)
        return 2
    print("\n".join(out), end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
