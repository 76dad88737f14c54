"""What this CPU offers ONNX Runtime's INT8 kernels (read from /proc/cpuinfo on Linux).

On x86, ONNX Runtime multiplies uint8 activations by int8 weights with VNNI
where the CPU has it (one instruction, 32-bit sums). Without VNNI (AVX2,
AVX-512 before Cascade Lake, AMD before Zen 4) it uses VPMADDUBSW, which adds
each pair of products in 16 bits and saturates when both are near 255 × 127:
a network quantized with full 8-bit weights then computes something else on
those CPUs. Weights quantized to 7 bits (``reduce_range``, ``python -m
export.precision --reduce-range``) keep every pair below 2¹⁵ on every CPU.
"""

from __future__ import annotations

import os
import platform
from functools import cache
from pathlib import Path

# Any of these gives the 32-bit uint8 × int8 dot products (AMX-INT8 CPUs have AVX-512 VNNI too).
VNNI_FLAGS = frozenset({"avx512_vnni", "avx_vnni", "amx_int8"})


@cache
def _cpuinfo(field: str) -> str | None:
    """The first ``field : value`` of /proc/cpuinfo (None where there is none: not Linux, or no such field)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, colon, value = line.partition(":")
            if colon and key.strip() == field:  # whole names: "model" is not "model name"
                return value.strip()
    except OSError:
        pass
    return None


def cpu_flags() -> frozenset[str]:
    """The CPU's feature flags; empty where /proc/cpuinfo lists none (not Linux)."""
    return frozenset((_cpuinfo("flags") or "").split())


# The flags that decide how fast (and, for INT8, how exactly) ONNX Runtime's CPU kernels run.
SPEED_FLAGS = ("avx2", "fma", "avx512f", "avx512_vnni", "avx_vnni", "avx512_bf16", "amx_bf16", "amx_int8")


def speed_flags(flags: frozenset[str] | None = None) -> list[str]:
    """Which of :data:`SPEED_FLAGS` the CPU has, in that order (for benchmark reports)."""
    flags = cpu_flags() if flags is None else flags
    return [flag for flag in SPEED_FLAGS if flag in flags]


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo's ``model name``, else what the platform module says)."""
    return _cpuinfo("model name") or platform.processor() or platform.machine()


def cpu_generation() -> str | None:
    """x86 family and model numbers, "family 25 model 17" (None where /proc/cpuinfo has none). A virtual machine's
    model name is often just "AMD EPYC", while these tell a Zen 2 (family 23 model 49) from a Zen 4 (25, 17)."""
    family, model = _cpuinfo("cpu family"), _cpuinfo("model")
    return f"family {family} model {model}" if family and model else None


def describe() -> dict:
    """The CPU in a report: model, generation, the flags that set ONNX Runtime's speed, and whether INT8 pair sums
    saturate."""
    return {"cpu": cpu_model(), "cpu_generation": cpu_generation(), "cpu_flags": speed_flags(),
            "int8_pair_sums_saturate": int8_pairs_saturate()}


def cpu_label(described: dict | None = None) -> str:
    """The CPU in one phrase for a report's header, "AMD EPYC, family 25 model 17", from :func:`describe`'s dict
    (default: this machine's; one from before the generation was recorded gives the model name alone)."""
    described = describe() if described is None else described
    generation = described.get("cpu_generation")
    return f"{described['cpu']}, {generation}" if generation else described["cpu"]


def is_x86() -> bool:
    return platform.machine().lower() in {"x86_64", "amd64", "i386", "i686"}


def has_vnni(flags: frozenset[str] | None = None) -> bool:
    """Whether the CPU has VNNI (32-bit uint8 × int8 dot products)."""
    return bool((cpu_flags() if flags is None else flags) & VNNI_FLAGS)


def int8_pairs_saturate(flags: frozenset[str] | None = None) -> bool:
    """True where ONNX Runtime's uint8 × int8 kernels add pairs of products in 16 bits: x86 without VNNI.

    An x86 machine whose flags cannot be read counts as saturating (the safe answer).
    """
    return is_x86() and not has_vnni(flags)


CGROUP = Path("/sys/fs/cgroup")


def cpu_quota(root: Path | None = None) -> float | None:
    """The CPUs' worth of time a cgroup quota gives this process (``docker run --cpus 2``, a Kubernetes CPU
    limit): 2.0 for 200 ms per 100 ms period; None without a quota (or off Linux).

    The affinity mask of such a container still lists every core of the host: sized by it, ONNX Runtime
    would start a thread per host core and the kernel throttle them all to the quota. root: the cgroup
    file system (default :data:`CGROUP`).
    """
    root = CGROUP if root is None else root
    try:  # cgroup v2: "max 100000" or "200000 100000"
        quota_text, period_text = (root / "cpu.max").read_text().split()[:2]
        return None if quota_text == "max" else int(quota_text) / int(period_text)
    except (OSError, ValueError):
        pass
    try:  # cgroup v1: a quota of -1 is none
        quota = int((root / "cpu" / "cpu.cfs_quota_us").read_text())
        period = int((root / "cpu" / "cpu.cfs_period_us").read_text())
        return quota / period if quota > 0 and period > 0 else None
    except (OSError, ValueError):
        return None


def usable_cpus() -> int:
    """The CPUs this process may use: its affinity mask (where the OS has one, else all), at most its cgroup
    quota rounded to whole CPUs (at least one)."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    quota = cpu_quota()
    return cpus if quota is None else max(1, min(cpus, int(quota + 0.5)))


SYSFS_CPU = Path("/sys/devices/system/cpu")


def physical_cores(cpus: list[int], root: Path | None = None) -> list[list[int]]:
    """``cpus`` grouped by physical core: SMT siblings (hyper-threads) together, groups in the order of their
    first CPU. Where the topology cannot be read, each CPU is a core of its own. root: default
    :data:`SYSFS_CPU`."""
    root = SYSFS_CPU if root is None else root
    groups: dict[tuple, list[int]] = {}
    for cpu in cpus:
        topology = root / f"cpu{cpu}" / "topology"
        try:
            key: tuple = (int((topology / "physical_package_id").read_text()), int((topology / "core_id").read_text()))
        except (OSError, ValueError):
            key = ("cpu", cpu)
        groups.setdefault(key, []).append(cpu)
    return sorted(groups.values(), key=lambda group: group[0])


def core_shares(cpus: list[int], shares: int, root: Path | None = None) -> list[list[int]]:
    """``cpus`` cut into ``shares`` equal shares of whole physical cores, so that no two shares run on the
    siblings of one core (Linux numbers an SMT box's siblings i and i + N, and a cut in id order gave one
    worker the threads and the other their siblings). With fewer physical cores than shares, the CPUs are
    cut in id order instead."""
    cores = physical_cores(cpus, root)
    if len(cores) < shares:
        per = len(cpus) // shares
        return [cpus[i * per : (i + 1) * per] for i in range(shares)]
    per = len(cores) // shares
    return [[cpu for core in cores[i * per : (i + 1) * per] for cpu in core] for i in range(shares)]
