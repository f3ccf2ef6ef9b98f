"""Distributed training plumbing: the process's rank and device, and cross-rank agreement on errors.

Under ``torchrun`` :func:`setup_distributed` joins the process group (gloo on
CPU, nccl on GPU); :func:`_agree` runs a step on every rank and makes every
rank raise when any rank failed, so that a mistake never leaves some ranks
waiting.
"""
from __future__ import annotations

import os
import pickle
from dataclasses import dataclass
from typing import Any, Callable

import torch
import torch.distributed as dist

__all__ = ["Dist", "setup_distributed"]


@dataclass
class Dist:
    rank: int = 0
    world: int = 1
    device: torch.device = torch.device("cpu")

    @property
    def main(self) -> bool:
        return self.rank == 0


def setup_distributed(device: str = "auto") -> Dist:
    """Initialise ``torch.distributed`` when launched by torchrun; pick the device."""
    use_cuda = torch.cuda.is_available() if device == "auto" else device.startswith("cuda")
    if "RANK" in os.environ and "WORLD_SIZE" in os.environ and int(os.environ["WORLD_SIZE"]) > 1:
        if not dist.is_initialized():
            dist.init_process_group("nccl" if use_cuda else "gloo")
        rank, world = dist.get_rank(), dist.get_world_size()
        local = int(os.environ.get("LOCAL_RANK", rank))
        dev = torch.device(f"cuda:{local}") if use_cuda else torch.device("cpu")
        if use_cuda:
            torch.cuda.set_device(dev)
        return Dist(rank, world, dev)
    return Dist(0, 1, torch.device("cuda" if use_cuda else "cpu"))


def _rank_of_world() -> int:
    return dist.get_rank() if dist.is_available() and dist.is_initialized() else 0


def _portable(exc: BaseException) -> BaseException:
    """``exc`` if it survives pickling (to send it to the other ranks), else a RuntimeError with its text."""
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:
        return RuntimeError(f"{type(exc).__name__}: {exc}")


def _agree(fn: Callable[[], Any]) -> Any:
    """``fn()`` on every rank; when it fails on any rank, every rank raises (nobody is left waiting).

    Rank 0 raises its own error when it has one, else the first failing rank's;
    the other ranks raise rank 0's error when rank 0 failed (marked with
    ``kpcn_echo`` so that only rank 0 prints it), else their own.
    """
    err: BaseException | None = None
    out = None
    try:
        out = fn()
    except Exception as exc:
        err = exc
    if dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1:
        errs: list = [None] * dist.get_world_size()
        dist.all_gather_object(errs, None if err is None else _portable(err))
        rank = dist.get_rank()
        if rank != 0 and errs[0] is not None:
            echo = errs[0]
            echo.kpcn_echo = True
            raise echo
        if err is None:
            other = next((e for e in errs if e is not None), None)
            if other is not None:
                other.kpcn_echo = rank != 0
                raise other
    if err is not None:
        raise err
    return out
