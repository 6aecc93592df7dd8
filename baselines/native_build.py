"""Build, cache and load the project's compiled CPU kernels (plain C++ shared libraries, ctypes).

    library = NativeLibrary("raster_kernel", source, abi_version, bind, entry_check)
    library.load() -> ctypes.CDLL          (built on first use, one attempt per process)
    library.available() -> (True, path) or (False, reason)

A kernel here is one C++17 source without Python or torch headers, compiled with the system
compiler (`$CXX`, else c++, g++ or clang++) and loaded with ctypes; tensors are passed as raw
pointers to contiguous memory. That takes seconds, where a `torch.utils.cpp_extension` build
spends most of a minute parsing torch headers, and it needs no ninja. The flags are portable
(-O3, no -march=native), so a cache shared by machines of one architecture stays valid.

Cache: `$REFLOW4DGS_KERNEL_CACHE`, else `$XDG_CACHE_HOME/reflow4dgs/kernels`, else
`~/.cache/reflow4dgs/kernels`; the file name holds a hash of the source, the ABI version, the
compiler (path and `--version`), the flags and the platform (not the torch version: the libraries
do not link torch). Each build writes into a private temporary directory and is moved into place
with an atomic rename, so processes that build at the same time (pytest-xdist, two trainings)
never see a torn file. Users: baselines/render/kernel.py (compositing),
baselines/render/project_kernel.py (EWA projection), baselines/fourdgs/plane_kernel.py (HexPlane
lookups), baselines/fourdgs/regularization_kernel.py (HexPlane regularisers), baselines/ssim_kernel.py
(the SSIM map) and reflow_plugin/flow_kernel.py (ReFlow's per-Gaussian flow channels).
"""
from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path

logger = logging.getLogger(__name__)

ENV_CACHE_DIR = "REFLOW4DGS_KERNEL_CACHE"
ENV_COMPILER = "CXX"
CXX_FLAGS = ("-O3", "-std=c++17", "-shared", "-fPIC", "-ffp-contract=off", "-pthread")
COMPILE_TIMEOUT_S = 600


OFF_VALUES = frozenset({"0", "false", "off", "no"})  # an environment switch set to one of these turns a kernel off


def switched_off_by_env(what: str, *names: str) -> str | None:
    """Why `what` (e.g. "the compiled projection") is off: the first of the environment variables
    `names` set to 0/false/off/no, as a reason string; None when none of them is."""
    for name in names:
        value = os.environ.get(name, "").strip().lower()
        if value in OFF_VALUES:
            return f"{what} is disabled by {name}={os.environ[name]}"
    return None


class KernelUnavailable(RuntimeError):
    """A compiled kernel cannot be built or loaded; the message says why."""


def cache_dir() -> Path:
    """Directory holding built kernel libraries (see the module docstring for the lookup order)."""
    explicit = os.environ.get(ENV_CACHE_DIR)
    if explicit:
        return Path(explicit).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base).expanduser() / "reflow4dgs" / "kernels"


def find_compiler() -> str | None:
    """Absolute path of the C++ compiler to use: $CXX, else the first of c++, g++, clang++."""
    candidates = [os.environ[ENV_COMPILER]] if os.environ.get(ENV_COMPILER) else ["c++", "g++", "clang++"]
    for name in candidates:
        found = shutil.which(name)
        if found:
            return found
    return None


def _compiler_identity(compiler: str) -> str:
    try:
        proc = subprocess.run([compiler, "--version"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.SubprocessError) as exc:
        raise KernelUnavailable(f"the C++ compiler {compiler} does not run ({exc})") from exc
    return proc.stdout + proc.stderr


def check_abi_version(lib: ctypes.CDLL, function: str, expected: int, what: str) -> None:
    """Call the library's `function` (no arguments, returns int) and raise KernelUnavailable
    unless it returns `expected`: a stale or foreign library is never called with our signatures."""
    version_of = getattr(lib, function)
    version_of.argtypes, version_of.restype = [], ctypes.c_int
    version = version_of()
    if version != expected:
        raise KernelUnavailable(f"{what} library reports ABI version {version}, expected {expected}")


def library_path(name: str, source: Path, abi_version: int, compiler: str) -> Path:
    """Cache path of the library `name` built from `source` with `compiler`."""
    key = hashlib.sha256()
    for part in (
        source.read_bytes(),
        str(abi_version).encode(),
        compiler.encode(),
        _compiler_identity(compiler).encode(),
        " ".join(CXX_FLAGS).encode(),
        f"{sys.platform}-{platform.machine()}".encode(),
    ):
        key.update(part)
        key.update(b"\0")
    return cache_dir() / f"{name}-{key.hexdigest()[:24]}.so"


def build(compiler: str, source: Path, target: Path) -> None:
    """Compile `source` into `target` atomically (private temp dir, then os.replace)."""
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp_dir = tempfile.mkdtemp(prefix=".build-", dir=target.parent)
    except OSError as exc:
        raise KernelUnavailable(f"cannot write the kernel cache {target.parent} ({exc}); set {ENV_CACHE_DIR}") from exc
    try:
        built = Path(tmp_dir) / target.name
        cmd = [compiler, *CXX_FLAGS, str(source), "-o", str(built)]
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=COMPILE_TIMEOUT_S)
        except (OSError, subprocess.SubprocessError) as exc:
            raise KernelUnavailable(f"running {' '.join(cmd)} failed ({exc})") from exc
        if proc.returncode != 0:
            tail = (proc.stderr or proc.stdout).strip()[-2000:]
            raise KernelUnavailable(f"compiling {source.name} failed (exit {proc.returncode}): {' '.join(cmd)}\n{tail}")
        os.replace(built, target)
    finally:
        shutil.rmtree(tmp_dir, ignore_errors=True)


class NativeLibrary:
    """One kernel source: built on first use, cached on disk, loaded once per process.

    Args:
        name: file-name stem of the cached library.
        source: the C++ source.
        abi_version: what the library's version function must return (checked by `bind`).
        bind: sets the ctypes signatures and checks the ABI version; raises KernelUnavailable
            (or AttributeError for a missing symbol) when the library does not fit.
    """

    def __init__(self, name: str, source: Path, abi_version: int, bind: Callable[[ctypes.CDLL], ctypes.CDLL]) -> None:
        self.name, self.source, self.abi_version, self.bind = name, source, abi_version, bind
        self._lock = threading.Lock()
        self._library: ctypes.CDLL | None = None
        self._load_error: str | None = None
        self._failed_under: tuple | None = None  # the environment the recorded failure happened in

    def reset(self) -> None:
        """Forget the loaded library or the recorded failure (tests; a changed environment)."""
        with self._lock:
            self._library, self._load_error, self._failed_under = None, None, None

    @staticmethod
    def _build_environment() -> tuple:
        return os.environ.get(ENV_COMPILER), os.environ.get(ENV_CACHE_DIR)

    def path(self, compiler: str) -> Path:
        """Cache path of this library built with `compiler`."""
        return library_path(self.name, self.source, self.abi_version, compiler)

    def build(self, compiler: str, target: Path) -> None:
        build(compiler, self.source, target)

    def _load_or_build(self) -> ctypes.CDLL:
        if not self.source.is_file():
            raise KernelUnavailable(f"kernel source {self.source} is missing from the installation")
        compiler = find_compiler()
        if compiler is None:
            wanted = f"$CXX={os.environ[ENV_COMPILER]!r}" if os.environ.get(ENV_COMPILER) else "c++, g++ or clang++"
            raise KernelUnavailable(f"no C++ compiler found ({wanted} not on PATH)")
        target = self.path(compiler)
        if target.is_file():
            try:
                return self.bind(ctypes.CDLL(str(target)))
            except (OSError, AttributeError, KernelUnavailable) as exc:
                logger.warning("cached kernel %s does not load (%s); rebuilding it", target, exc)
        self.build(compiler, target)
        try:
            return self.bind(ctypes.CDLL(str(target)))
        except (OSError, AttributeError) as exc:
            raise KernelUnavailable(f"the freshly built kernel {target} does not load ({exc})") from exc

    def load(self) -> ctypes.CDLL:
        """The loaded library, building it on first use (one attempt per process and environment).

        A failure is remembered (no build attempt per call) for the $CXX and cache directory it
        happened under; once those change (a test's temporary CXX gone) the next call tries again.

        Raises:
            KernelUnavailable: with the reason (no compiler, build failure, unwritable cache, ...).
        """
        with self._lock:
            if self._load_error is not None and self._failed_under != self._build_environment():
                self._load_error = None
            if self._library is None and self._load_error is None:
                try:
                    self._library = self._load_or_build()
                except KernelUnavailable as exc:
                    self._load_error, self._failed_under = str(exc), self._build_environment()
            if self._library is None:
                raise KernelUnavailable(self._load_error)
            return self._library

    def available(self) -> tuple[bool, str]:
        """(True, library path) when the library loads, else (False, the reason)."""
        try:
            lib = self.load()
        except KernelUnavailable as exc:
            return False, str(exc)
        return True, str(lib._name)
