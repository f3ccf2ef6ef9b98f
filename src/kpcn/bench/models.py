"""Which model a denoising benchmark times: a config (random-init weights: the time does not depend on the values),
a ``registry:key=value,...`` spec, or shipped weights (``model:tag``, or a bare model name for its default).

Shared by ``python -m kpcn.bench denoise`` (:mod:`kpcn.bench.denoise`) and its ``--skip`` mode
(:mod:`kpcn.bench.skip`).
"""
from __future__ import annotations

_DENOISE_FALLBACK_MODELS = {  # used when configs/<name>.yaml cannot be found
    "small": {"name": "kpcn", "layers": 5, "width": 32, "conv_size": 5, "kernel_size": 11},
    "paper": {"name": "kpcn", "layers": 9, "width": 100, "conv_size": 5, "kernel_size": 21},
}


def _denoise_model_spec(name: str) -> tuple[str, dict | None, str]:
    """``(registry name, model kwargs, origin)`` for a config name (``small``), a YAML path, or
    ``registry:key=value,...`` (e.g. ``kpcn:layers=5,width=32,conv_size=5,kernel_size=11``); for shipped
    weights ``model:tag`` (``unet_kpcn:wide``), or a bare model name without a config of that name (``unet_kpcn``:
    its default weights): ``(name, None, origin)``, timed with those weights."""
    from pathlib import Path

    if ":" in name and "=" not in name:
        from kpcn.models import list_weights, weights_entry

        reg, _, tag = name.partition(":")
        if tag in list_weights(reg):
            return name, None, f"shipped weights {weights_entry(reg, tag).path.name}"
        raise ValueError(f"model spec {name!r}: no shipped weights {tag!r} for {reg!r} (shipped: "
                         f"{', '.join(list_weights(reg)) or 'none'}); a config is registry:key=value,...")
    if ":" in name:
        import yaml

        reg, _, rest = name.partition(":")
        kw = {}
        for item in filter(None, rest.split(",")):
            key, sep, value = item.partition("=")
            if not sep:
                raise ValueError(f"model spec {name!r}: expected key=value, got {item!r}")
            kw[key.strip()] = yaml.safe_load(value)
        return reg, kw, "command line"
    if name.endswith((".yaml", ".yml")):
        candidates = [Path(name)]
    else:
        root = Path(__file__).resolve().parents[3]  # the checkout's root (<root>/src/kpcn/bench/models.py)
        candidates = [Path("configs") / f"{name}.yaml", root / "configs" / f"{name}.yaml"]
    for path in candidates:
        if path.is_file():
            from ..config import load_config
            from ..train_config import RunConfig

            model = dict(load_config(RunConfig, path).model)
            return model.pop("name"), model, str(path)
    from kpcn.models import is_model, list_weights, weights_entry

    if is_model(name) and list_weights(name):  # a bare model name: its default shipped weights, as denoise takes it
        entry = weights_entry(name)
        return name, None, f"shipped weights {entry.path.name} ({name}:{entry.tag}, its default)"
    if name in _DENOISE_FALLBACK_MODELS:
        spec = dict(_DENOISE_FALLBACK_MODELS[name])
        return spec.pop("name"), spec, "built-in fallback"
    raise ValueError(f"unknown model config {name!r}: no configs/{name}.yaml and not one of {sorted(_DENOISE_FALLBACK_MODELS)}")


def _bench_model(model_name: str, model_kw: dict | None):
    """The model a :func:`_denoise_model_spec` names: shipped weights (``model_kw`` None), else the config with
    random-init weights (seed 0)."""
    import torch

    if model_kw is None:
        from kpcn.inference import load_model

        return load_model(model_name, "cpu")
    from kpcn.models import create_model

    torch.manual_seed(0)
    return create_model(model_name, **model_kw).eval()
