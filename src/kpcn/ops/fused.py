"""Inference steps of the U-Net's row bands fused into one native pass each (:mod:`kpcn.ops.native`).

Each returns None (:func:`feed_native`: False) where the library or its inputs do not fit (no compiler,
``KPCN_NATIVE=0``, autograd, not float32 on the CPU, ...), and the caller runs its PyTorch path: the same function
to float rounding. Each splits its rows between ``torch.get_num_threads()`` threads (torch's own OpenMP pool).

:func:`softmax_apply_native`: bounded-softmax kernels applied; :func:`upsample_guide_native`: the guided head's
full-resolution output; :func:`guided_blend_native`: the full-resolution level's coarse-to-fine blend with the
normal-guided upsampling; :func:`feed_native`: the guide and the pooled features of a band of feature rows;
:func:`residual_regression_native`: the detail stage's regression with one fit per 2×2 block;
:func:`branch_features_native`: the diffuse/specular features of a band.
"""
from __future__ import annotations

import ctypes

import torch

from ..constants import BRANCH_LAYERS
from . import native

__all__ = ["softmax_apply_native", "upsample_guide_native", "guided_softmax_native", "guided_blend_native",
           "feed_native", "residual_regression_native", "branch_features_native", "MAX_NATIVE_SCALE",
           "MAX_NATIVE_KERNEL", "MAX_FEED_CHANNELS"]

#: above this logit bound the PyTorch path subtracts the maximum before exp (2^(s log2 e) would overflow float32)
MAX_NATIVE_SCALE = 80.0
#: the most feature channels :func:`feed_native` takes (a band's transformed features live on a thread's stack)
MAX_FEED_CHANNELS = 64
#: the input transforms :func:`feed_native` computes (:func:`kpcn.models.layers.transform_input`)
_FEED_TRANSFORMS = {"none": 0, "log": 1}
#: the largest kernel the native path takes (its per-row weights, k² × 64 floats, live on a thread's stack)
MAX_NATIVE_KERNEL = 31


def _plain(*ts: torch.Tensor, dtypes=(torch.float32,), rows: bool = False) -> bool:
    """Whether every tensor can go to the C library as it is: 4-D on the CPU in one of ``dtypes``, asking for no
    gradient, and with ``rows`` each row contiguous. The one check every wrapper here makes first."""
    return all(t.dim() == 4 and t.device.type == "cpu" and t.dtype in dtypes
               and not (torch.is_grad_enabled() and t.requires_grad) and (not rows or t.stride(-1) == 1) for t in ts)


def _threads(rows: int) -> int:
    """Threads for a call over ``rows`` rows (or row pairs, blocks of rows): torch's, no more than there are rows."""
    return max(1, min(torch.get_num_threads(), rows))


def _usable(logits: torch.Tensor, padded: torch.Tensor, k: int, s: float) -> bool:
    return (_plain(logits, padded, rows=True) and 0 < s <= MAX_NATIVE_SCALE and k % 2 == 1 and k <= MAX_NATIVE_KERNEL
            and logits.shape[1] == k * k)


def softmax_apply_native(logits: torch.Tensor, padded: torch.Tensor, kernel_size: int,
                         logit_scale: float) -> torch.Tensor | None:
    """The bounded-softmax kernels of ``logits`` ``(B, k², H, W)`` applied to ``padded`` ``(B, C, H + 2r, W + 2r)``
    (``r = k // 2``, already padded): ``(B, C, H, W)`` float32, or None where the native path does not apply.

    ``out[b, c, y, x] = sum_t w_t · padded[b, c, y + i_t, x + j_t] / sum_t w_t``, ``w_t = exp(s tanh(z_t / s))``
    (``z = logits[b, :, y, x]``, tap ``t = i k + j`` in :func:`~kpcn.ops.kernel_apply` order): what
    :func:`kpcn.models.kernel_heads._softmax_weights` and :func:`~kpcn.ops.kernel_apply.kernel_apply_padded` do, in
    one loop; ``s`` at most :data:`MAX_NATIVE_SCALE`.

    ``logits`` may be a slice of a larger tensor (its rows and taps strided), each row contiguous."""
    k, s = int(kernel_size), float(logit_scale)
    if not _usable(logits, padded, k, s):
        return None
    b, _, h, w = logits.shape
    if padded.shape[0] != b or padded.shape[-2] != h + k - 1 or padded.shape[-1] != w + k - 1:
        raise ValueError(f"softmax_apply_native: padded {tuple(padded.shape)} does not fit logits "
                         f"{tuple(logits.shape)} with kernel size {k}")
    lib = native.library()
    if lib is None:
        return None
    c = padded.shape[1]
    out = torch.empty(b, c, h, w, dtype=torch.float32)
    threads = _threads(h)
    for i in range(b):
        z, img, o = logits[i], padded[i], out[i]
        lib.softmax_apply_rows(z.data_ptr(), z.stride(0), z.stride(1), k, s, img.data_ptr(), img.stride(0),
                               img.stride(1), c, o.data_ptr(), o.stride(0), o.stride(1), h, w, threads)
    return out


def _guided_band(low: torch.Tensor, guide: torch.Tensor, weight: torch.Tensor, caller: str) -> bool:
    """The checks both guided-head wrappers make of a band (:func:`upsample_guide_native`,
    :func:`guided_softmax_native`): False where the native path does not take these tensors (dtype, device, a
    gradient, a batch); a ValueError naming ``caller`` where ``low`` ``(1, O, n + 2, w)``, ``guide`` ``(1, G, 2n, 2w)``
    and ``weight`` ``(O, G)`` do not fit each other."""
    if not (_plain(low, rows=True) and _plain(guide, dtypes=(torch.float32, torch.bfloat16), rows=True)) or \
            (torch.is_grad_enabled() and weight.requires_grad) or low.shape[0] != 1 or guide.shape[0] != 1:
        return False
    _, o, lr, lw = low.shape
    if lr < 3 or guide.shape[-2:] != (2 * lr - 4, 2 * lw) or tuple(weight.shape) != (o, guide.shape[1]):
        raise ValueError(f"{caller}: low {tuple(low.shape)} (1, O, n + 2, w), guide {tuple(guide.shape)} "
                         f"and weight {tuple(weight.shape)} do not fit: want guide (1, G, 2n, 2w), weight (O, G)")
    return True


def upsample_guide_native(low: torch.Tensor, guide: torch.Tensor, weight: torch.Tensor) -> torch.Tensor | None:
    """The guided head's full-resolution output for a band: ``upsample2(low, context_rows=True) + W_g · guide``
    (:func:`kpcn.models.layers.upsample2`, :meth:`kpcn.models.kernel_heads.GuidedHead.add_guide_part_`).

    Args:
        low: ``(1, O, n + 2, w)`` float32, the head's half-resolution product with its bias, over the band's
            half-resolution rows and one row of context each side.
        guide: ``(1, G, 2n, 2w)`` float32 or bfloat16, the band's guide rows (each row contiguous).
        weight: ``(O, G)`` float32, the head's guide weights.

    Returns:
        ``(1, O, 2n, 2w)`` float32 contiguous, or None where the native path does not apply.
    """
    if not _guided_band(low, guide, weight, "upsample_guide_native"):
        return None
    lib = native.library()
    if lib is None:
        return None
    _, o, lr, lw = low.shape
    g, rows = guide.shape[1], 2 * lr - 4
    out = torch.empty(1, o, rows, 2 * lw, dtype=torch.float32)
    wg = weight.detach().to(torch.float32).contiguous()
    threads = _threads(rows)
    scratch = torch.empty(threads * (g + 1) * 2 * lw, dtype=torch.float32)
    lib.upsample_guide_rows(low.data_ptr(), low.stride(1), low.stride(2), lr, lw, guide.data_ptr(), guide.stride(1),
                            guide.stride(2), g, int(guide.dtype == torch.bfloat16), wg.data_ptr(), o, out.data_ptr(),
                            out.stride(1), out.stride(2), scratch.data_ptr(), threads)
    return out


def guided_softmax_native(low: torch.Tensor, guide: torch.Tensor, weight: torch.Tensor, padded: torch.Tensor,
                          kernel_size: int, logit_scale: float) -> torch.Tensor | None:
    """The guided head's kernels for a band, made and applied at once: :func:`softmax_apply_native` of the first
    ``k²`` channels of :func:`upsample_guide_native`'s output, without writing those logits to memory.

    Args:
        low: ``(1, O, n + 2, w)`` float32, ``O >= k²``, the head's half-resolution product with its bias (only its
            first ``k²`` channels are read), over the band's half-resolution rows and one row of context each side.
        guide: ``(1, G, 2n, 2w)`` float32 or bfloat16, the band's guide rows (each row contiguous).
        weight: ``(O, G)`` float32, the head's guide weights (its first ``k²`` rows are read).
        padded: ``(1, C, 2n + k - 1, 2w + k - 1)`` float32, the colour the kernels apply to, padded by ``k // 2``.

    Returns:
        ``(1, C, 2n, 2w)`` float32, or None where the native path does not apply.
    """
    k, s = int(kernel_size), float(logit_scale)
    kk = k * k
    if not (_plain(padded, rows=True) and padded.shape[0] == 1 and 0 < s <= MAX_NATIVE_SCALE and k % 2 == 1
            and k <= MAX_NATIVE_KERNEL) or not _guided_band(low, guide, weight, "guided_softmax_native"):
        return None
    _, o, lr, lw = low.shape
    g, rows, width = guide.shape[1], 2 * lr - 4, 2 * lw
    if o < kk or padded.shape[-2:] != (rows + k - 1, width + k - 1):
        raise ValueError(f"guided_softmax_native: low {tuple(low.shape)} (1, O >= {kk}, n + 2, w) and padded "
                         f"{tuple(padded.shape)} do not fit: want padded (1, C, 2n + {k - 1}, 2w + {k - 1})")
    lib = native.library()
    if lib is None:
        return None
    c = padded.shape[1]
    out = torch.empty(1, c, rows, width, dtype=torch.float32)
    wg = weight[:kk].detach().to(torch.float32).contiguous()
    threads = _threads(rows)
    scratch = torch.empty(threads * (kk + g + 1) * width, dtype=torch.float32)
    lib.guided_softmax_rows(low.data_ptr(), low.stride(1), low.stride(2), lr, lw, guide.data_ptr(), guide.stride(1),
                            guide.stride(2), g, int(guide.dtype == torch.bfloat16), wg.data_ptr(), k, s,
                            padded.data_ptr(), padded.stride(1), padded.stride(2), c, out.data_ptr(), out.stride(1),
                            out.stride(2), scratch.data_ptr(), threads)
    return out


def guided_blend_native(f: torch.Tensor, coarse: torch.Tensor, guide_fine: torch.Tensor, guide_coarse: torch.Tensor,
                        sigma: float, alpha: torch.Tensor, beta: torch.Tensor, r0: int, n: int) -> torch.Tensor | None:
    """Rows ``[r0, r0 + n)`` of a band's blended full-resolution level, ``lerp(U D f, f, β) + α · U(coarse - D f)``,
    ``D`` the 2×2 average and ``U`` :func:`~kpcn.models.guided.upsample2_guided` by the guide pair (each of the band's
    maps replicate-padded at its edges, as :func:`~kpcn.models.guided.apply_guided` pads them): what
    :meth:`kpcn.models.unet_rows.RowStream.rows` does with ``edge_upsample`` and ``band_gain``, in one loop.

    Args:
        f: ``(1, C, R, W)`` float32, the level's filtered colour over the band's rows (``R``, ``W`` even).
        coarse: ``(1, C, R / 2, W / 2)`` float32, the coarser levels' result over them.
        guide_fine: ``(1, G, R, W)`` float32; guide_coarse: ``(1, G, R / 2, W / 2)`` float32.
        sigma: > 0. alpha, beta: ``(1, 1, R, W)`` float32, the blend weight and the high band's gain.

    Returns:
        ``(1, C, n, W)`` float32 contiguous, or None where the native path does not apply.
    """
    if not (_plain(f, coarse, guide_fine, guide_coarse, alpha, beta, rows=True) and sigma > 0) or f.shape[0] != 1:
        return None
    _, c, rows, width = f.shape
    g = guide_fine.shape[1]
    if rows % 2 or width % 2 or coarse.shape != (1, c, rows // 2, width // 2) \
            or guide_fine.shape[-2:] != (rows, width) or guide_coarse.shape != (1, g, rows // 2, width // 2) \
            or alpha.shape != (1, 1, rows, width) or beta.shape != (1, 1, rows, width) or not 0 <= r0 <= r0 + n <= rows:
        raise ValueError(f"guided_blend_native: f {tuple(f.shape)} (1, C, R, W), coarse {tuple(coarse.shape)}, guides "
                         f"{tuple(guide_fine.shape)} and {tuple(guide_coarse.shape)}, alpha {tuple(alpha.shape)}, "
                         f"beta {tuple(beta.shape)} and rows [{r0}, {r0 + n}) do not fit")
    lib = native.library()
    if lib is None:
        return None
    out = torch.empty(1, c, n, width, dtype=torch.float32)
    threads = _threads(n)
    scratch = torch.empty(2 * c * (rows // 2) * (width // 2) + threads * 4 * width, dtype=torch.float32)
    lib.guided_blend_rows(f.data_ptr(), f.stride(1), f.stride(2), rows, width, c,
                          coarse.data_ptr(), coarse.stride(1), coarse.stride(2),
                          guide_fine.data_ptr(), guide_fine.stride(1), guide_fine.stride(2),
                          guide_coarse.data_ptr(), guide_coarse.stride(1), guide_coarse.stride(2), g, float(sigma),
                          alpha.data_ptr(), alpha.stride(2), beta.data_ptr(), beta.stride(2), int(r0), int(n),
                          out.data_ptr(), out.stride(1), out.stride(2), scratch.data_ptr(), threads)
    return out


def feed_native(x: torch.Tensor, transform: str, guide_weight: torch.Tensor | None, guide_bias: torch.Tensor | None,
                guide: torch.Tensor | None, pooled: torch.Tensor) -> bool:
    """A band of feature rows made into what a row stream keeps, written into the given views: ``guide`` =
    ``relu(W · T(x) + b)`` (a 1×1 guide) and ``pooled`` = ``T(pool2(x))``, ``T`` the input transform
    (:func:`kpcn.models.layers.transform_input`, ``"none"`` or ``"log"``).

    Args:
        x: ``(1, C, n, W)`` float32, ``n`` and ``W`` even, each row contiguous.
        transform: ``UNetConfig.input_transform``.
        guide_weight, guide_bias: ``(G, C)`` and ``(G,)`` (None, and ``guide`` None: no guide).
        guide: ``(1, G, n, W)`` float32 or bfloat16, each row contiguous (a band of the stream's guide).
        pooled: ``(1, C, n / 2, W / 2)`` float32 or bfloat16, any strides (the stream keeps it channels-last).

    Returns:
        True when written; False where the native path does not apply (nothing written).
    """
    if transform not in _FEED_TRANSFORMS or not _plain(x, rows=True) or x.shape[0] != 1 or \
            x.shape[1] > MAX_FEED_CHANNELS or not _plain(pooled, dtypes=(torch.float32, torch.bfloat16)) or \
            (guide is not None and not _plain(guide, dtypes=(torch.float32, torch.bfloat16), rows=True)):
        return False
    _, c, n, w = x.shape
    g = 0 if guide is None else guide.shape[1]
    if n % 2 or w % 2 or tuple(pooled.shape) != (1, c, n // 2, w // 2) or \
            (guide is not None and (tuple(guide.shape) != (1, g, n, w) or guide_weight is None
                                    or tuple(guide_weight.shape[:2]) != (g, c))):
        raise ValueError(f"feed_native: x {tuple(x.shape)} (1, C, n, W), n and W even; pooled {tuple(pooled.shape)} "
                         f"must be (1, C, n/2, W/2), guide {None if guide is None else tuple(guide.shape)} "
                         f"(1, G, n, W) with weights (G, C)")
    lib = native.library()
    if lib is None:
        return False
    gw = guide_weight.detach().reshape(g, c).to(torch.float32).contiguous() if g else torch.zeros(1)
    gb = guide_bias.detach().to(torch.float32).contiguous() if g and guide_bias is not None else torch.zeros(max(g, 1))
    threads = _threads(n // 2)
    gp = guide.data_ptr() if g else None
    lib.feed_rows(x.data_ptr(), x.stride(1), x.stride(2), c, n, w, _FEED_TRANSFORMS[transform], gw.data_ptr(),
                  gb.data_ptr(), g, gp, guide.stride(1) if g else 0, guide.stride(2) if g else 0,
                  int(g and guide.dtype == torch.bfloat16), pooled.data_ptr(), pooled.stride(1), pooled.stride(2),
                  pooled.stride(3), int(pooled.dtype == torch.bfloat16), threads)
    return True


def residual_regression_native(denoised: torch.Tensor, noisy: torch.Tensor, guide: torch.Tensor, radius: int,
                               eps: float, bound: bool, clip: float | None) -> torch.Tensor | None:
    """:func:`kpcn.ops.regression.residual_regression` with ``stride=2`` for one image: ``denoised``, ``noisy``
    ``(1, 3, H, W)`` and ``guide`` ``(1, 3, H, W)`` float32 at any strides (arguments as there, checked there);
    ``(1, 3, H, W)`` contiguous, or None where the native path does not apply."""
    ts = (denoised, noisy, guide)
    if not _plain(*ts) or any(tuple(t.shape[:2]) != (1, 3) for t in ts):
        return None
    lib = native.library()
    if lib is None:
        return None
    h, w = denoised.shape[-2:]
    hb, wb = (h + 1) // 2, (w + 1) // 2
    out = torch.empty(1, 3, h, w, dtype=torch.float32)
    scratch = torch.empty(9 * h * w + 66 * hb * wb, dtype=torch.float32)
    d, n, g = (t[0] for t in ts)
    lib.residual_regression_s2(d.data_ptr(), *d.stride(), n.data_ptr(), *n.stride(), g.data_ptr(), *g.stride(),
                               out.data_ptr(), h, w, radius // 2, float(eps), float(clip) if clip is not None else 0.0,
                               int(bool(bound)), scratch.data_ptr(), _threads(hb))
    return out


#: the layers :func:`branch_features_native` reads, in the C function's order
FEATURE_LAYERS = ("diffuse", "specular", "albedo", "normal", "depth", "diffuseVariance", "specularVariance",
                  "albedoVariance", "normalVariance", "depthVariance")


def branch_features_native(buffers, depth_scale, branches
                           ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]] | None:
    """:func:`kpcn.features.branch_features` with variances for one image: ``buffers`` ``{layer: (1, C, h, w)}``
    float32 on the CPU at any strides (C = 3, or 1 for a variance or the depth), ``depth_scale`` a number or a
    one-element tensor (> 0), ``branches`` a subset of ``("diffuse", "specular")``.

    Returns:
        ``({"albedo": (1, 3, h, w), branch: (1, 27, h, w), ...}, {variance layer: values clamped (0-dim)})``, or
        None where the native path does not apply (a missing layer is the caller's to report)."""
    # an unlisted branch's layers are not read (the albedo stands in for them)
    unused = {n for b, ls in BRANCH_LAYERS.items() if b not in branches for n in ls}
    if depth_scale is None or not branches or any(n not in buffers for n in FEATURE_LAYERS if n not in unused):
        return None
    ts = [buffers["albedo"] if n in unused else buffers[n] for n in FEATURE_LAYERS]
    h, w = ts[0].shape[-2:]
    if not _plain(*ts) or h < 1 or w < 1 or \
            any(t.shape[0] != 1 or t.shape[1] not in (1, 3) or tuple(t.shape[-2:]) != (h, w) for t in ts):
        return None
    scale = float(depth_scale.reshape(-1)[0]) if isinstance(depth_scale, torch.Tensor) else float(depth_scale)
    if isinstance(depth_scale, torch.Tensor) and depth_scale.numel() != 1 or not scale > 0:
        return None
    lib = native.library()
    if lib is None:
        return None
    ptrs = (ctypes.c_void_p * 10)(*(t.data_ptr() for t in ts))
    strides = ((ctypes.c_int64 * 3) * 10)(*((ctypes.c_int64 * 3)(*t.stride()[1:]) for t in ts))
    channels = (ctypes.c_int * 10)(*(t.shape[1] for t in ts))
    out = {"albedo": torch.empty(1, 3, h, w)}
    for b in branches:
        out[b] = torch.empty(1, 27, h, w)
    threads = _threads(h)
    tmp, rows = torch.empty(4 * h * w), torch.empty(threads * 31 * w)  # the normal and depth planes; row buffers
    clamped = torch.zeros(5, dtype=torch.int64)
    lib.branch_features_rows(ptrs, strides, channels, h, w, scale, int("diffuse" in out), int("specular" in out),
                             out["diffuse"].data_ptr() if "diffuse" in out else None,
                             out["specular"].data_ptr() if "specular" in out else None, out["albedo"].data_ptr(),
                             tmp.data_ptr(), rows.data_ptr(), clamped.data_ptr(), threads)
    n = dict(zip(("diffuseVariance", "specularVariance", "albedoVariance", "normalVariance", "depthVariance"),
                 clamped.unbind()))
    # in the order kpcn.features reads the layers (its warning names them so): the shared ones, then each branch's
    order = ("albedoVariance", "normalVariance", "depthVariance") + tuple(f"{b}Variance" for b in branches)
    return out, {k: n[k] for k in order}
