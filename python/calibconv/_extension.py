"""The native CPU kernels as torch operators: compiled against the installed torch at first use.

The C++ sources are the Rust crate's (``src/ops/native``), embedded in ``calibconv._native`` when
the wheel is built (:func:`calibconv._native.native_sources`), so the package and the crate run
one source. :func:`load` writes them to a cache directory, compiles them with the system's C++
compiler against the headers and libraries of the ``torch`` that is imported (its C++ ABI, its
OpenMP), links one shared library and loads it with ``torch.ops.load_library``, which registers
``torch.ops.calibconv.deform_conv2d`` and ``deform_conv2d_backward`` (``torch_op.cpp``).

Why at first use and not at ``pip install``: the wheel is one abi3 build for every CPython and
every torch (it links no libtorch); a C++ extension is bound to one torch's ABI, so building it
at install time would tie the wheel to the torch present then and break on the next torch
upgrade. Built here, it follows the torch that is imported: the cache key is the torch version,
its C++ ABI, the compiler, the flags and the sources' hash, so an upgrade (of torch or of
calibconv) builds a new library once, in about 35 s on two cores, and every later process
loads it in milliseconds. ninja is not needed: the sources are compiled in parallel by a thread
pool here.

Cache: ``$CALIBCONV_EXTENSION_DIR``, else ``$XDG_CACHE_HOME/calibconv/torch-ext``, else
``~/.cache/calibconv/torch-ext``; one directory per key, built under a file lock (several
processes may start at once) and published by an atomic rename. ``CALIBCONV_NATIVE=0`` turns
the extension off (the torchvision path then runs, without a warning). Linux and macOS compilers
that accept GCC's flags (``$CXX``, else ``c++``); elsewhere, or when the build fails, :func:`load`
returns the reason and the caller falls back.
"""

from __future__ import annotations

import concurrent.futures
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import List, Optional

#: The library's file name inside its cache directory.
LIBRARY = "calibconv_torch_ops.so"
#: Flags of every compilation, as build.rs compiles the same files into the Rust crate (C++17,
#: -O3, OpenMP for at::parallel_for); no -march: the kernels pick their instruction set at run
#: time.
CXX_FLAGS = ["-std=c++17", "-O3", "-fPIC", "-fopenmp", "-DGLOG_USE_GLOG_EXPORT", "-w"]

_state: dict = {}


def cache_root() -> Path:
    """The directory that holds one built library per cache key."""
    if os.environ.get("CALIBCONV_EXTENSION_DIR"):
        return Path(os.environ["CALIBCONV_EXTENSION_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "calibconv" / "torch-ext"


def _compiler() -> Optional[str]:
    return shutil.which(os.environ.get("CXX", "c++"))


def _build_settings():
    import torch
    from torch.utils import cpp_extension

    abi = int(bool(torch._C._GLIBCXX_USE_CXX11_ABI))
    includes = cpp_extension.include_paths()
    libs = cpp_extension.library_paths()
    flags = CXX_FLAGS + [f"-D_GLIBCXX_USE_CXX11_ABI={abi}"]
    for inc in includes:
        flags += ["-isystem", inc]
    link = [f"-L{d}" for d in libs] + [f"-Wl,-rpath,{d}" for d in libs]
    link += ["-lc10", "-ltorch_cpu", "-ltorch", "-fopenmp"]
    return torch.__version__, flags, link


def _key(sources, torch_version: str, cxx: str, flags: List[str], link: List[str]) -> str:
    h = hashlib.sha256()
    version = subprocess.run([cxx, "--version"], capture_output=True, text=True).stdout
    for part in [torch_version, cxx, version, *flags, *link]:
        h.update(part.encode() + b"\0")
    for name, text in sorted(sources):
        h.update(name.encode() + b"\0" + text.encode() + b"\0")
    return f"torch-{torch_version.replace('+', '_')}-{h.hexdigest()[:16]}"


def _compile(cxx: str, flags: List[str], link: List[str], src: Path, out: Path) -> None:
    """Compiles every .cpp of ``src`` (in parallel) and links them into ``out``."""
    cpps = sorted(src.glob("*.cpp"))

    def one(cpp: Path) -> Path:
        obj = cpp.with_suffix(".o")
        r = subprocess.run([cxx, *flags, "-c", str(cpp), "-o", str(obj)], capture_output=True,
                           text=True)
        if r.returncode != 0:
            raise RuntimeError(f"{cxx} failed on {cpp.name}:\n{r.stderr[-4000:]}")
        return obj

    workers = max(1, min(len(cpps), os.cpu_count() or 1))
    with concurrent.futures.ThreadPoolExecutor(workers) as pool:
        objs = list(pool.map(one, cpps))
    r = subprocess.run([cxx, "-shared", *map(str, objs), "-o", str(out), *link],
                       capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"linking {out.name} failed:\n{r.stderr[-4000:]}")


def library_path() -> Path:
    """The built library for this torch and these sources, compiled first if it is missing.

    Raises ``RuntimeError`` (no compiler, a failed build) with the reason.
    """
    from . import _native

    cxx = _compiler()
    if cxx is None:
        raise RuntimeError(f"no C++ compiler ({os.environ.get('CXX', 'c++')} not found; set CXX)")
    sources = _native.native_sources()
    torch_version, flags, link = _build_settings()
    target = cache_root() / _key(sources, torch_version, cxx, flags, link)
    lib = target / LIBRARY
    if lib.is_file():
        return lib
    target.mkdir(parents=True, exist_ok=True)
    import fcntl

    with open(target / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if lib.is_file():  # another process built it while this one waited
            return lib
        sys.stderr.write(
            f"calibconv: compiling the native CPU kernels for torch {torch_version} into "
            f"{target} (once; about 35 s on two cores)\n"
        )
        with tempfile.TemporaryDirectory(dir=target) as tmp:
            src = Path(tmp)
            for name, text in sources:
                (src / name).write_text(text)
            built = src / LIBRARY
            _compile(cxx, flags, link, src, built)
            os.replace(built, lib)
    return lib


def load() -> Optional[str]:
    """Loads the operators (building them first if needed), once per process.

    Returns ``None`` when ``torch.ops.calibconv.deform_conv2d`` is available, else the reason it
    is not (``CALIBCONV_NATIVE=0``, no compiler, the build's error).
    """
    if "reason" in _state:
        return _state["reason"]
    reason = None
    if os.environ.get("CALIBCONV_NATIVE", "1") == "0":
        reason = "CALIBCONV_NATIVE=0"
    elif not sys.platform.startswith(("linux", "darwin")):
        reason = f"building the kernels on {sys.platform} is not supported"
    else:
        try:
            import torch

            torch.ops.load_library(str(library_path()))
        except Exception as e:  # noqa: BLE001 (any failure means the fallback, with its reason)
            reason = f"{type(e).__name__}: {e}"
    _state["reason"] = reason
    return reason
