"""Dr.Jit / Mitsuba start-up: find a working LLVM, pick a variant, check versions.

Dr.Jit's CPU backend loads a system ``libLLVM.so``; versions older than 16 abort
on some kernels ("Cannot select ... fminimum"). The ``karellen-llvm-core`` wheel
ships a recent LLVM: when it is installed and the user has not set
``DRJIT_LIBLLVM_PATH`` themselves, we point Dr.Jit at it *before* ``drjit`` is
imported. This module must therefore be imported before ``mitsuba`` or ``drjit``
anywhere in the package, and users must ``import mirad`` first: Dr.Jit loads LLVM at import and
cannot switch afterwards, so ``check_llvm`` names that cause (``LATE``) when it is the one.

Measured here (Mitsuba 3.9.1, Dr.Jit 1.5.0, wheel LLVM 23.1): the library loads
without preloading the wheel's libc++/libc++abi/libunwind, and preloading them
with RTLD_GLOBAL must be avoided: libc++abi then takes over C++ exception
handling and every Mitsuba error (a malformed XML file, say) aborts the process
with "terminating due to uncaught exception" instead of raising in Python.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from .errors import EnvironmentProblem

MIN_LLVM = (16, 0, 0)


def _bundled_llvm() -> Path | None:
    """Path of the pip-installed libLLVM (karellen-llvm-core), or None."""
    for prefix in dict.fromkeys((sys.prefix, sys.base_prefix)):
        lib = Path(prefix) / "lib"
        for candidate in sorted(lib.glob("libLLVM.so.*"), reverse=True):
            if candidate.is_file():
                return candidate
    return None


def _preload_llvm() -> None:
    if os.environ.get("DRJIT_LIBLLVM_PATH") or not sys.platform.startswith("linux"):
        return
    llvm = _bundled_llvm()
    if llvm is not None:
        os.environ["DRJIT_LIBLLVM_PATH"] = str(llvm)


#: True when Dr.Jit was imported (``import mitsuba`` or ``import drjit``) before mirad: it loads its
#: LLVM at import, so the bundled one could not be pointed at any more.
LATE = "drjit" in sys.modules
_preload_llvm()

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

_LLVM_ADVICE = (
    "install a newer LLVM: 'pip install karellen-llvm-core' (x86-64 Linux), or "
    "'apt-get install -y libllvm19', or set DRJIT_LIBLLVM_PATH to a libLLVM.so of version >= 16"
)


def exact_arithmetic():
    """Context in which Dr.Jit compiles the kernels traced inside it without fast math.

    On CUDA, Dr.Jit's fast math (on by default) takes approximate division, reciprocals and
    square roots, which round differently from one scene to its copy scaled by 1000 or moved:
    on an H100 the same room solved in millimetres or moved by a few metres differed by up to
    0.7 % per triangle (0.02 % median), rays flipping at edges and refinement deciding
    otherwise. Without it the CUDA solve matched the CPU's (LLVM) to the ray and within 1e-6
    per triangle, and scaling by a power of two bitwise. mirad's own waves are a small share of
    a solve, so exact arithmetic costs it little."""
    return dr.scoped_set_flag(dr.JitFlag.FastMath, False)


def has_cuda() -> bool:
    """True when Dr.Jit can use a CUDA device."""
    try:
        return bool(dr.has_backend(dr.JitBackend.CUDA))
    except Exception:  # pragma: no cover - depends on the driver
        return False


def check_llvm() -> tuple[int, int, int]:
    """Return the LLVM version Dr.Jit loaded; raise if it is missing or too old."""
    try:
        has_llvm = dr.has_backend(dr.JitBackend.LLVM)
    except Exception:  # pragma: no cover
        has_llvm = False
    version = tuple(int(v) for v in dr.detail.llvm_version()) if has_llvm else None
    if version is not None and version >= MIN_LLVM:
        return version
    found = f"LLVM {'.'.join(map(str, version))}, which aborts on some kernels (needs >= 16)" if version \
        else "no usable LLVM library"
    bundled = _bundled_llvm()
    if LATE and bundled is not None and os.environ.get("DRJIT_LIBLLVM_PATH") == str(bundled):
        raise EnvironmentProblem(
            f"Dr.Jit loaded {found} because mitsuba or drjit was imported before mirad, and Dr.Jit picks its "
            f"LLVM at import; the installed one at {bundled} would work: 'import mirad' before 'import "
            f"mitsuba', or set DRJIT_LIBLLVM_PATH={bundled} in the environment before Python starts"
        )
    raise EnvironmentProblem(f"Dr.Jit loaded {found}; {_LLVM_ADVICE}.")


def choose_variant(requested: str | None = None) -> str:
    """Set and return the Mitsuba variant: the requested one, else CUDA if present, else LLVM.

    Only the ``*_ad_rgb``/``*_rgb`` JIT variants are supported: mirad solves per RGB channel.
    """
    if requested is None:
        current = mi.variant()
        if current in ("cuda_ad_rgb", "llvm_ad_rgb", "cuda_rgb", "llvm_rgb"):
            if current.startswith("llvm"):
                check_llvm()
            return current
        requested = "cuda_ad_rgb" if has_cuda() else "llvm_ad_rgb"
    if requested not in ("cuda_ad_rgb", "llvm_ad_rgb", "cuda_rgb", "llvm_rgb"):
        raise EnvironmentProblem(
            f"variant {requested!r} is not supported; use 'llvm_ad_rgb' (CPU) or 'cuda_ad_rgb' (GPU)"
        )
    if requested not in mi.variants():
        raise EnvironmentProblem(f"this Mitsuba build has no variant {requested!r}")
    if requested.startswith("llvm"):
        check_llvm()
    if mi.variant() != requested:
        mi.set_variant(requested)
    return requested
