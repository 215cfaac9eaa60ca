"""What this CPU can do, asked once: the one place that decides which fast paths run.

    >>> from segmo import cpu
    >>> cpu.describe()
    'Intel(R) Xeon(R) Processor; torch kernels AVX512; oneDNN linear yes; oneDNN bf16 yes; native bf16 AVX512_BF16, AMX'
    >>> cpu.auto_precision()
    ('bf16', 'native bf16 on this CPU (AVX512_BF16, AMX)')

Every answer comes from torch's own probes (CPUID through cpuinfo and oneDNN), never from
an assumption about the CPU; an answer a torch build cannot give is "no". Nothing here
imports segmo, so `segmo.models` can use it.

- `onednn_linear()`: oneDNN's linear with weights pre-packed in its own layout, fp32
  (`torch.ops.mkldnn._reorder_linear_weight` / `_linear_pointwise`) runs and agrees with a
  plain matmul. It does on every x86 CPU tried, AVX2-only ones included.
- `onednn_bf16()`: oneDNN takes bf16 at all: AVX512BW/VL/DQ or AVX-NE-CONVERT (x86), BF16
  (Arm). This is the check behind "mkldnn_reorder_linear_weight: bf16 path needs the cpu
  support avx_ne_convert or avx512bw, avx512vl and avx512dq"; without it, bf16 matmuls
  fall back to torch's slow reference kernels. oneDNN reads it from CPUID, so
  `ONEDNN_MAX_CPU_ISA=AVX2` turns it off on any host: a cheap way to test the fallback.
- `native_bf16()`: the CPU also computes in bf16 (AVX512-BF16, AMX-BF16, AVX-NE-CONVERT or
  Arm BF16) rather than emulating it with fp32 instructions: only then is bf16 faster than
  fp32, so only then does `precision="auto"` choose it.
"""

from __future__ import annotations

import functools
import platform
from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class CPUInfo:
    """The answers, as one value (tests replace it to simulate another CPU).

    model: the CPU's name ("AMD EPYC 7B13"); isa: the vector ISA torch's own kernels
    dispatch to ("AVX512", "AVX2", "DEFAULT", …; `ATEN_CPU_CAPABILITY` lowers it);
    onednn_linear, onednn_bf16: the oneDNN paths above; native_bf16: the bf16
    instructions found, () for none.
    """

    model: str
    isa: str
    onednn_linear: bool
    onednn_bf16: bool
    native_bf16: tuple[str, ...]

    def describe(self) -> str:
        def yes(flag: bool) -> str:
            return "yes" if flag else "no"

        native = ", ".join(self.native_bf16) or "none"
        return (f"{self.model}; torch kernels {self.isa}; oneDNN linear "
                f"{yes(self.onednn_linear)}; oneDNN bf16 {yes(self.onednn_bf16)}; "
                f"native bf16 {native}")


def _probe(name: str) -> bool:
    """torch.cpu._is_<name>_supported() where this torch has it, else False."""
    check = getattr(torch.cpu, f"_is_{name}_supported", None)
    try:
        return bool(check()) if check is not None else False
    except RuntimeError:
        return False


def _model_name() -> str:
    # /proc/cpuinfo is the kernel's view of the host: under user-mode emulation
    # (qemu-x86_64 -cpu Haswell) it still names the host, while CPUID-based answers follow
    # the emulated CPU. It only names the CPU here; no feature is read from it.
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as file:
            for line in file:
                key, _, value = line.partition(":")
                if key.strip() in ("model name", "Model", "cpu model") and value.strip():
                    return value.strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


def _isa() -> str:
    try:
        return str(torch.backends.cpu.get_cpu_capability())
    except (AttributeError, RuntimeError):
        return "unknown"


def _onednn_linear() -> bool:
    """Run oneDNN's packed fp32 linear once on a small layer and compare with a matmul."""
    mkldnn = getattr(torch.ops, "mkldnn", None)
    pack = getattr(mkldnn, "_reorder_linear_weight", None)
    run = getattr(mkldnn, "_linear_pointwise", None)
    if pack is None or run is None or not torch.backends.mkldnn.is_available():
        return False
    generator = torch.Generator().manual_seed(0)
    x, weight = torch.randn(3, 8, generator=generator), torch.randn(5, 8, generator=generator)
    bias = torch.randn(5, generator=generator)
    try:
        with torch.no_grad(), torch.autocast("cpu", enabled=False):
            expected = torch.addmm(bias, x, weight.t())
            packed = run(x, pack(weight, 64), bias, "none", [], "")
            plain = run(x, weight, bias, "none", [], "")
    except RuntimeError:
        return False
    return all(torch.allclose(y, expected, rtol=1e-4, atol=1e-4) for y in (packed, plain))


def _onednn_bf16() -> bool:
    check = getattr(getattr(torch.ops, "mkldnn", None), "_is_mkldnn_bf16_supported", None)
    if check is None or not torch.backends.mkldnn.is_available():
        return False
    try:
        return bool(check())
    except RuntimeError:
        return False


def _native_bf16(onednn_bf16: bool) -> tuple[str, ...]:
    # Without oneDNN's bf16 path no bf16 instruction is used, whatever the CPU has.
    if not onednn_bf16:
        return ()
    if platform.machine().lower() not in ("x86_64", "amd64", "i386", "i686"):
        return ("BF16",)  # oneDNN's Arm check is the BF16 extension itself
    found = tuple(name for probe, name in (("avx512_bf16", "AVX512_BF16"), ("amx_tile", "AMX"))
                  if _probe(probe))
    if found:
        return found
    # oneDNN takes bf16 on AVX512BW/VL/DQ or on AVX-NE-CONVERT; torch has no probe for the
    # latter, so a CPU that passes oneDNN's check without AVX-512 must have it. An
    # AVX-512 CPU without AVX512-BF16 (Skylake, Cascade Lake) only emulates bf16.
    return () if _probe("avx512") else ("AVX_NE_CONVERT",)


@functools.cache
def info() -> CPUInfo:
    """This CPU's answers, probed once per process."""
    bf16 = _onednn_bf16()
    return CPUInfo(model=_model_name(), isa=_isa(), onednn_linear=_onednn_linear(),
                   onednn_bf16=bf16, native_bf16=_native_bf16(bf16))


def model_name() -> str:
    return info().model


def vector_isa() -> str:
    return info().isa


def onednn_linear() -> bool:
    return info().onednn_linear


def onednn_bf16() -> bool:
    return info().onednn_bf16


def native_bf16() -> bool:
    return bool(info().native_bf16)


def describe() -> str:
    """One line for logs and benchmarks: model, torch's ISA, the oneDNN paths, native bf16."""
    return info().describe()


def auto_precision() -> tuple[str, str]:
    """What `precision="auto"` runs on this CPU, and why: ("bf16" | "fp32", reason)."""
    found = info().native_bf16
    if found:
        return "bf16", f"native bf16 on this CPU ({', '.join(found)})"
    if onednn_bf16():
        return "fp32", "this CPU only emulates bf16 (no AVX512-BF16, AMX or AVX-NE-CONVERT)"
    return "fp32", ("this CPU has no bf16 path in oneDNN (needs AVX512BW/VL/DQ or "
                    "AVX-NE-CONVERT); bf16 would run in torch's slow reference kernels")
