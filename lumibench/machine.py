"""What machine a benchmark ran on: recorded beside every timing so numbers carry their context."""
from __future__ import annotations

import os
import platform


def cpu_fields(cpuinfo: str = "/proc/cpuinfo") -> dict[str, str] | None:
    """The first processor's "model name", "cpu family", "model" and "flags" from /proc/cpuinfo (those it
    has), or None where the file cannot be read (not Linux)."""
    fields: dict[str, str] = {}
    try:
        with open(cpuinfo) as fh:
            for line in fh:
                key, sep, value = line.partition(":")
                key = key.strip()
                if sep and key in ("model name", "cpu family", "model", "flags") and key not in fields:
                    fields[key] = value.strip()
                if not line.strip() and fields:  # the first processor's block is enough
                    break
    except OSError:
        return None
    return fields


def cpu_description(cpuinfo: str = "/proc/cpuinfo") -> str:
    """The CPU model with its family/model numbers and widest vector unit, e.g. "AMD EPYC (family 25 model 1,
    AVX2)". Why: a virtual machine's model name is often just "AMD EPYC", and two such boxes of this project
    differed 2.1x on the fp32 network and 36x on bf16 (one had AVX-512 with BF16, the other AVX2 only;
    BENCHMARKS.md), so a timing without this cannot be compared with another."""
    fields = cpu_fields(cpuinfo)
    if fields is None:
        return platform.processor() or platform.machine()
    flags = set(fields.get("flags", "").split())
    isa = ("AVX-512 + AMX" if "amx_tile" in flags else "AVX-512 BF16" if "avx512_bf16" in flags
           else "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else "no AVX2" if flags else "")
    name = fields.get("model name") or platform.processor() or platform.machine()
    family = f"family {fields['cpu family']} model {fields['model']}" if "cpu family" in fields and "model" in fields else ""
    detail = [d for d in (family, isa) if d]
    return f"{name} ({', '.join(detail)})" if detail else name


def usable_cores() -> int:
    """Cores this process may run on (affinity), which is what a benchmark actually gets."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1
