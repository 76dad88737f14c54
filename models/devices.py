"""Where and how training computes: the device (the CPU or a CUDA GPU), the arithmetic (bf16 autocast where
the hardware has it, else fp32), whether the training forward pass goes through ``torch.compile``, the memory
layout of the networks' tensors (channels-last unless a network trips a oneDNN defect), and the seeds of the
random generators. Why and when compiling pays: models/train.py's docstring (``python -m models.train --help``).
"""

from __future__ import annotations

import random
import shutil

import numpy as np
import torch

from pipeline.errors import InputError

CPU = torch.device("cpu")
COMPILE_MIN_STEPS = 200  # below this, compiling (about a minute per network) costs more than it saves
COMPILED_TASKS = ("depth", "detector")  # joint's per-frame soft BEV has no fixed shapes to compile for


def resolve_device(device: str) -> torch.device:
    """``auto`` → the first CUDA GPU when this torch build sees one, else the CPU."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        resolved = torch.device(device)
    except RuntimeError:
        raise InputError(f"--device: {device!r} is not a torch device (auto, cpu, cuda, cuda:N)") from None
    if resolved.type == "cuda" and not torch.cuda.is_available():
        raise InputError(f"--device: {device} asked for, but this torch build sees no CUDA GPU "
                         f"(torch {torch.__version__}; install a CUDA build of torch)")
    if resolved.type not in ("cpu", "cuda"):
        raise InputError(f"--device: {device!r}: only cpu and cuda are supported")
    return resolved


def resolve_precision(precision: str, device: torch.device | None = None) -> str:
    """``auto`` → bf16 where the hardware has native bf16 arithmetic (a CPU with AVX-512 BF16, the one
    CPU feature checked: AMX is not looked at; a GPU that supports it), else fp32.

    Measured here (2-core AMD EPYC with AVX-512 BF16), one training step: bf16 autocast with channels-last
    tensors took PIXOR (edge, batch 8) from 1.42 s to 0.41 s and the depth net (edge, batch 4) from 0.33 s
    to 0.17 s; weights, optimizer state and losses stay fp32.
    """
    if precision not in ("auto", "bf16", "fp32"):
        raise InputError(f"--precision: {precision!r} is not one of auto, bf16, fp32")
    if precision == "auto":
        if device is not None and device.type == "cuda":
            supported = torch.cuda.is_bf16_supported()
        else:
            supported = torch.backends.mkldnn.is_available() and torch.cpu._is_avx512_bf16_supported()
        return "bf16" if supported else "fp32"
    return precision


def resolve_compile(mode: str, task: str, steps: int, device: torch.device = CPU) -> bool:
    """Whether to ``torch.compile`` the training forward pass (models/train.py's docstring).

    ``auto`` → yes for the depth and detector tasks when the run has at least :data:`COMPILE_MIN_STEPS`
    steps and the device can compile: a CUDA GPU, or a CPU with a C++ compiler on the PATH (Inductor
    builds its CPU kernels with it). ``on`` insists (an InputError where it cannot), ``off`` never.
    """
    if mode not in ("auto", "on", "off"):
        raise InputError(f"--compile: {mode!r} is not one of auto, on, off")
    if mode == "off" or task not in COMPILED_TASKS:
        return False
    can = device.type == "cuda" or any(shutil.which(c) for c in ("c++", "g++", "clang++"))
    if mode == "on" and not can:
        raise InputError("--compile on: torch.compile on the CPU needs a C++ compiler (c++, g++ or clang++) on "
                         "the PATH; install one or pass --compile off")
    return can and (mode == "on" or steps >= COMPILE_MIN_STEPS)


def channels_last_safe(networks: dict[str, torch.nn.Module]) -> bool:
    """False when a network has a convolution oneDNN's channels-last path mishandles.

    Found here (torch 2.13.0, oneDNN 3.12): the backward pass of a 1×1 stride-2 convolution with 8 input
    channels in channels-last layout corrupts the heap ("double free or corruption"), in fp32 and bf16.
    Such thin strided shortcuts exist only in the ``tiny`` test preset (the 3×3 strided stems of ``edge``
    with 1 and 3 input channels were checked and are fine).
    """
    return not any(m.kernel_size == (1, 1) and m.stride != (1, 1) and m.in_channels < 16
                   for net in networks.values() for m in net.modules() if isinstance(m, torch.nn.Conv2d))


def autocast(precision: str, device: torch.device | None = None):
    """Mixed-precision context for the forward pass (a no-op in fp32)."""
    device_type = "cpu" if device is None else device.type
    return torch.autocast(device_type, dtype=torch.bfloat16, enabled=precision == "bf16")


def run_layout(networks: dict[str, torch.nn.Module]) -> torch.memory_format:
    """NHWC (oneDNN's fast path for convolutions on the CPU) unless a network trips the defect above."""
    return torch.channels_last if channels_last_safe(networks) else torch.contiguous_format


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % (2**32))
    torch.manual_seed(seed)
