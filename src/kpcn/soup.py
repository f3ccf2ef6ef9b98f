"""Weight-space blends of runs of one network (a "model soup", Wortsman et al. 2022).

Two runs of the same network that start from the same weights (a fine-tune and
the file it started from, say) can be averaged tensor by tensor; the blend often
keeps most of what the fine-tune gained and less of what it lost. The shipped
default ``unet_kpcn:wide64h`` is such a blend (``configs/unet_wide64h.yaml``)::

    python -m kpcn.soup results/g/model.safetensors unet_kpcn:wide64c --alpha 0.7 \\
        --out src/kpcn/weights/unet_wide64h.safetensors

Each source is a ``.safetensors`` weights file or a shipped ``model:tag``. The
files must hold the same model with the same hyper-parameters and the same
tensor names and shapes (:class:`~kpcn.checkpoint.CheckpointError` otherwise),
but for the detail stage's settings (``detail_*``, no parameters), which the
blend takes from the first source.
Floating-point tensors are blended in float64 and stored in their own dtype;
any other tensor (an integer counter) must be equal in every file. The output's
metadata records its sources (with their SHA-256) and coefficients, so that the
recipe is in the file.
"""
from __future__ import annotations

import argparse
import hashlib
import os
import sys
from pathlib import Path
from typing import Sequence

import torch

from .checkpoint import CheckpointError, model_from_record, read_weights, save_weights
from .inference.paths import check_not_input, check_output_path
from .models.base import NO_WEIGHT_SETTINGS

__all__ = ["blend_state", "blend_files", "resolve_sources", "main"]


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _coefficients(n: int, alphas: Sequence[float] | None) -> list[float]:
    if n < 2:
        raise ValueError(f"soup: blend at least two weights files, got {n}")
    if alphas is None:
        return [1.0 / n] * n
    alphas = [float(a) for a in alphas]
    if len(alphas) == n - 1:  # the last source takes what is left
        alphas.append(round(1.0 - sum(alphas), 12))
    if len(alphas) != n:
        raise ValueError(f"soup: {n} sources need {n} coefficients (or {n - 1}, the last taking the rest), "
                         f"got {len(alphas)}")
    if any(not 0.0 <= a <= 1.0 for a in alphas) or abs(sum(alphas) - 1.0) > 1e-6:
        raise ValueError(f"soup: coefficients must lie in [0, 1] and sum to 1, got {alphas}")
    return alphas


def blend_state(states: Sequence[dict[str, torch.Tensor]], alphas: Sequence[float],
                names: Sequence[str] | None = None) -> dict[str, torch.Tensor]:
    """``sum_i alphas[i] * states[i]`` tensor by tensor (float64 accumulation, each tensor's own dtype).

    Every state must have the same keys and shapes; a non-floating tensor must be equal in all of them.
    ``names`` (one per state) only label the errors.
    """
    names = list(names) if names is not None else [f"state {i}" for i in range(len(states))]
    first = states[0]
    for name, s in zip(names[1:], states[1:]):
        if s.keys() != first.keys():
            diff = sorted(set(s) ^ set(first))
            raise CheckpointError(f"soup: {name} and {names[0]} hold different tensors ({len(diff)} differ, e.g. "
                                  f"{diff[:3]}): not the same network")
    out = {}
    for k, t0 in first.items():
        ts = [s[k] for s in states]
        for name, t in zip(names[1:], ts[1:]):
            if t.shape != t0.shape or t.dtype != t0.dtype:
                raise CheckpointError(f"soup: tensor {k!r} is {tuple(t.shape)} {t.dtype} in {name} but "
                                      f"{tuple(t0.shape)} {t0.dtype} in {names[0]}: not the same network")
        if t0.is_floating_point():
            acc = sum(a * t.double() for a, t in zip(alphas, ts))
            out[k] = acc.to(t0.dtype).contiguous()
        else:
            for name, t in zip(names[1:], ts[1:]):
                if not torch.equal(t, t0):
                    raise CheckpointError(f"soup: integer tensor {k!r} differs between {name} and {names[0]}")
            out[k] = t0.clone()
    return out


def resolve_sources(sources: Sequence[str | os.PathLike]) -> list[Path]:
    """Each source's weights file: an existing path as it is, else a shipped ``model:tag`` resolved."""
    from .inference.weights import resolve_weights

    return [Path(s) if Path(s).exists() else Path(resolve_weights(str(s))) for s in sources]


def blend_files(sources: Sequence[str | os.PathLike], alphas: Sequence[float] | None = None):
    """The model whose weights are the blend of ``sources`` (files or shipped ``model:tag`` names).

    Returns ``(model, record)``: the model as :func:`kpcn.checkpoint.model_from_record` builds it, and
    ``{"sources": [{"name", "sha256", "alpha"}, ...]}`` for the output's metadata.
    """
    alphas = _coefficients(len(sources), alphas)
    paths = resolve_sources(sources)
    records, states = zip(*(read_weights(p) for p in paths))
    # compared as built (a file written before a hyper-parameter existed holds its default)
    built = [model_from_record(r["model"], r["hparams"], st, str(p)) for r, st, p in zip(records, states, paths)]
    # settings that add no parameter (NO_WEIGHT_SETTINGS): the blend takes the first source's
    h0 = {k: v for k, v in built[0].hparams().items() if k not in NO_WEIGHT_SETTINGS}
    for p, r, m in zip(paths[1:], records[1:], built[1:]):
        h = {k: v for k, v in m.hparams().items() if k not in NO_WEIGHT_SETTINGS}
        if r["model"] != records[0]["model"] or h != h0:
            diff = sorted(k for k in set(h) | set(h0) if h.get(k) != h0.get(k))
            raise CheckpointError(f"soup: {p} is {r['model']} and {paths[0]} is {records[0]['model']}, "
                                  f"hyper-parameters differing: {diff or 'none'}: not the same network")
    # blend what the built models hold, into the first of them (no further model to build)
    model = built[0]
    model.load_state_dict(blend_state([m.state_dict() for m in built], alphas, [str(p) for p in paths]))
    meta = {"sources": [{"name": str(s), "sha256": _sha256(p), "alpha": a}
                        for s, p, a in zip(sources, paths, alphas)]}
    return model, meta


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m kpcn.soup", description=__doc__.split("\n\n")[0])
    p.add_argument("sources", nargs="+", help="weights files (.safetensors) or shipped model:tag names")
    p.add_argument("--alpha", type=float, nargs="+", default=None,
                   help="one coefficient per source, or one fewer (the last source takes the rest); "
                        "default: the plain mean")
    p.add_argument("--out", required=True, help="the blended weights file (.safetensors; never one of the sources)")
    args = p.parse_args(argv)
    try:
        check_output_path(args.out)
        for src in resolve_sources(args.sources):
            check_not_input(args.out, src)
        model, meta = blend_files(args.sources, args.alpha)
        save_weights(args.out, model, soup=meta)
    except (ValueError, OSError) as exc:
        print(f"kpcn.soup: {exc}", file=sys.stderr)
        return 2
    print(f"kpcn.soup: wrote {args.out} = " + " + ".join(f"{s['alpha']:g} × {s['name']}" for s in meta["sources"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
