"""Where training runs (``train.device``): the CPU, or a CUDA GPU.

Training is the costly stage (a TIGNN-sized step with autograd is ~120 ms on 756 nodes on two
CPU cores) and never needs dolfinx, so it can run on a GPU machine. The whole run then happens
under ``torch.device(...)`` as the default device: the dataset's tensors, the mesh graph, the
model and its prior's FE operators are made there, so the training code stays the same on both.
Checkpoints always hold CPU tensors (``checkpoint.save_checkpoint``): a model trained on a GPU is
evaluated, exported and served on a CPU-only machine unchanged. The random draws (the sample
order, the training noise) come from a generator on the CPU and are moved to the device, so a
run draws the same numbers on either and an interrupted run resumes on the other.
"""

from __future__ import annotations

import os

import torch
from torch import Tensor

from thermognn.core.errors import ConfigError


def cpu_randn(shape, generator: torch.Generator, like: Tensor) -> Tensor:
    """Standard normal draws of ``shape`` from the CPU ``generator``, on ``like``'s device and in
    its dtype: the same numbers whatever ``train.device``."""
    return torch.randn(shape, generator=generator, dtype=like.dtype, device="cpu").to(like.device)


def training_device(setting) -> torch.device:
    """``train.device``: cpu | cuda | cuda:N | auto (the GPU when torch sees one, else the CPU).
    A GPU that torch cannot see is refused in one line; so is a GPU under ``torchrun`` (its
    processes average gradients over gloo on the CPU)."""
    name = str(setting if setting is not None else "cpu").strip().lower()
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ConfigError(f"train.device = {setting!r}, expected cpu, cuda, cuda:N or auto") from None
    if device.type not in ("cpu", "cuda"):
        raise ConfigError(f"train.device = {setting!r}, expected cpu, cuda, cuda:N or auto")
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(f"train.device = {setting!r}, but torch sees no CUDA GPU here (torch "
                              f"{torch.__version__}); use train.device=cpu or auto")
        count = torch.cuda.device_count()
        if device.index is not None and device.index >= count:
            raise ConfigError(f"train.device = {setting!r}, but torch sees {count} CUDA GPU(s) (cuda:0..cuda:{count - 1})")
        if int(os.environ.get("WORLD_SIZE", "1")) > 1:
            raise ConfigError(f"train.device = {setting!r} under torchrun: data-parallel training runs on "
                              f"CPUs only (train.device=cpu); one GPU trains in one process")
        if device.index is None:
            device = torch.device("cuda", torch.cuda.current_device())
    return device
