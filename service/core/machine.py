"""What the machine a figure was measured on is: its CPU, the vector units the arithmetic uses, its cores.

The service's latency is mostly convolutions (onnxruntime) and small linear algebra (numpy), and both
run several times faster on one x86 CPU than another of the same core count: 256-bit units at full
or half width, AVX-512, the VNNI dot products int8 convolutions use. A time means little without the
machine, so the benchmarks print :func:`cpu_description` first and the server logs it at start.

Example:
    >>> text = "model name : AMD EPYC 7551\\ncpu family : 23\\nmodel : 1\\nflags : fpu sse avx avx2 fma\\n"
    >>> describe_cpuinfo(text, cores=2)
    'AMD EPYC 7551 (family 23, model 1), 2 cores; AVX2, FMA; no AVX-512, no VNNI'
"""

from __future__ import annotations

import platform
from pathlib import Path

from service.core.threads import available_cores

CPUINFO = Path("/proc/cpuinfo")
FEATURES = (("avx2", "AVX2"), ("fma", "FMA"), ("avx512f", "AVX-512"), ("avx_vnni", "AVX-VNNI"),
            ("avx512_vnni", "AVX-512 VNNI"), ("amx_int8", "AMX"))
"""The x86 ``flags`` of ``/proc/cpuinfo`` that decide which kernels onnxruntime and BLAS run, and their names."""
ARM_FEATURES = (("asimd", "NEON"), ("asimddp", "dot product"), ("i8mm", "int8 matrix"), ("sve", "SVE"))
"""The same for Arm CPUs (their ``Features`` line)."""


def describe_cpuinfo(text: str, cores: int | None, fallback_name: str = "unknown CPU") -> str:
    """One line from the text of ``/proc/cpuinfo`` (its first processor): name (an Arm CPU's
    implementer and part, ``fallback_name`` where the text names none), x86 family and model,
    ``cores`` (the logical CPUs the process may use) and the vector features of :data:`FEATURES` (x86)
    or :data:`ARM_FEATURES`."""
    fields: dict[str, str] = {}
    for line in text.splitlines():
        if not line.strip():
            if fields:
                break                                      # the first processor only
            continue
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    arm = (f"Arm CPU (implementer {fields['CPU implementer']}, part {fields.get('CPU part', '?')})"
           if "CPU implementer" in fields else None)
    name = fields.get("model name") or arm or fallback_name
    family = f" (family {fields['cpu family']}, model {fields.get('model', '?')})" if "cpu family" in fields else ""
    count = "? cores" if cores is None else f"{cores} core{'s' if cores != 1 else ''}"
    parts = [f"{name}{family}, {count}"]
    if "flags" in fields:                                  # x86
        flags = set(fields["flags"].split())
        parts.append(", ".join(label for flag, label in FEATURES if flag in flags) or "no AVX2")
        missing = [label for label, present in (("AVX-512", "avx512f" in flags),
                                                ("VNNI", bool(flags & {"avx_vnni", "avx512_vnni"}))) if not present]
        if missing:
            parts.append("no " + ", no ".join(missing))
    elif "Features" in fields:                             # Arm
        flags = set(fields["Features"].split())
        parts.append(", ".join(label for flag, label in ARM_FEATURES if flag in flags) or "no NEON")
    return "; ".join(parts)


def cpu_description() -> str:
    """:func:`describe_cpuinfo` of this machine (its processor's name alone where there is no
    ``/proc/cpuinfo``)."""
    cores = available_cores()
    try:
        text = CPUINFO.read_text(errors="replace")
    except OSError:
        text = ""
    return describe_cpuinfo(text, cores, platform.processor() or platform.machine() or "unknown CPU")
