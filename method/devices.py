"""Devices: the --device a user asks for, checked before anything loads, and what a run records of it."""
from __future__ import annotations

import resource

import torch

from lumibench.machine import cpu_description, cpu_fields

from lumibench.errors import UserError


def check_device(device: str) -> torch.device:
    """--device as a torch.device that exists here, else a one-line error (checked before anything loads,
    so a missing GPU is not reported as an unreadable checkpoint)."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise UserError(f"--device {device!r} is not a device name torch knows (use cpu, cuda or cuda:N)") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise UserError(f"--device {device} asked for, but this torch has no CUDA device (use --device cpu)")
        n = torch.cuda.device_count()
        if dev.index is not None and dev.index >= n:
            raise UserError(f"--device {device} asked for, but this machine has {n} CUDA device(s) "
                            f"(use cuda:0..cuda:{n - 1} or cpu)")
    elif dev.type == "mps":
        if not (getattr(torch.backends, "mps", None) and torch.backends.mps.is_available()):
            raise UserError(f"--device {device} asked for, but this torch has no MPS device (use --device cpu)")
    elif dev.type != "cpu":
        raise UserError(f"--device {device}: unsupported device type '{dev.type}' (use cpu or cuda)")
    return dev


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def peak_memory_bytes(device: torch.device) -> int:
    if device.type == "cuda":
        return int(torch.cuda.max_memory_allocated(device))
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024  # Linux: KiB


def device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return cpu_description()


def cpu_has_native_bf16(cpuinfo: str = "/proc/cpuinfo") -> bool | None:
    """Whether this CPU multiplies bf16 natively (AVX512-BF16 or AMX-BF16 in its flags); None where the flags
    cannot be read (not Linux). Without it oneDNN emulates bf16, and ``model.mlp_precision: bf16`` is slower
    than fp32."""
    fields = cpu_fields(cpuinfo)
    if not fields or "flags" not in fields:
        return None
    return bool(set(fields["flags"].split()) & {"avx512_bf16", "amx_bf16"})
