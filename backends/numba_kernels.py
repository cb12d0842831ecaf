"""How the backends use Numba's compiled kernels: their on-disk cache kept honest across
modules, and calls from Python that skip the dispatcher's per-call type resolution.

**The cache.** Numba stamps a module's cached kernels with that module's own source file
only: a kernel that calls kernels of another module has their machine code compiled into its
own, and keeps running that old code after the other module changes, until its own file
changes (numba/numba#1833). A developer who edits `floor_friction.py` would then measure and
test the planar and MuJoCo steps of the edit before. `stamp_with_sources` binds a module's
cached kernels to the sources of the modules they call as well: change any of them and the
cache is stale, so Numba compiles afresh (tests/test_numba_kernels.py).

**Direct calls.** A dispatcher resolves the types of its arguments at every call; for a
NamedTuple of arrays (the kernels' geometry) that is ~5 us a call in Python, as much as a
step's friction solve on a resting object. `DirectCall` resolves them once and then calls
the compiled overload's entry point.
"""

from __future__ import annotations

import ctypes
import hashlib
from pathlib import Path
from types import ModuleType

from llvmlite import binding as llvm
from numba import types
from numba.core.dispatcher import Dispatcher

# C's memcpy(dst, src, n) for compiled code that reads or writes an engine's memory by address
# (pointers as integers: the same registers in the x86-64 and AArch64 C ABIs)
c_memcpy = types.ExternalFunction("memcpy", types.intp(types.intp, types.intp, types.intp))


def bind_library_functions(path: str, names: tuple[str, ...]) -> bool:
    """Bind the compiled code's external functions `names` to those of the shared library at
    `path` (`llvm.add_symbol`, by address). Loading a library Python has already loaded returns
    the same handle, so these are the very functions its module calls; the process's global
    symbol scope is left as it is (a library made global could interpose its symbols, a
    bundled C++ runtime's say, on libraries loaded later). False, nothing bound, when the
    library or one of the names is missing."""
    try:
        lib = ctypes.CDLL(path)
        addresses = {n: ctypes.cast(getattr(lib, n), ctypes.c_void_p).value for n in names}
    except (OSError, AttributeError):
        return False
    if not all(addresses.values()):
        return False
    for name, address in addresses.items():
        llvm.add_symbol(name, address)
    return True


class DirectCall:
    """A compiled kernel called at one call site whose argument types never change: the
    first call goes through the dispatcher (compiling or loading the overload), later ones
    straight to that overload's entry point (`Dispatcher.overloads[sig].entry_point`).

    Only for call sites that build their arguments with fixed types: the entry point unboxes
    them as the first call's types without checking (an array of another dtype, number of
    dimensions or layout would be misread). Should the overload not be found by the first
    call's types, every call goes through the dispatcher."""

    def __init__(self, dispatcher: Dispatcher) -> None:
        self.dispatcher = dispatcher
        self._entry = None
        self.__doc__ = dispatcher.__doc__

    def __call__(self, *args):
        entry = self._entry
        if entry is not None:
            return entry(*args)
        out = self.dispatcher(*args)
        sig = tuple(self.dispatcher.typeof_pyval(a) for a in args)
        cres = self.dispatcher.overloads.get(sig)
        self._entry = cres.entry_point if cres is not None else self.dispatcher
        return out


def sources_digest(*modules: ModuleType) -> str:
    """A digest of the modules' source files."""
    h = hashlib.sha256()
    for mod in modules:
        h.update(Path(mod.__file__).read_bytes())
    return h.hexdigest()[:16]


def stamp_with_sources(namespace: dict, *modules: ModuleType) -> None:
    """Make every cached kernel defined in `namespace` (a module's `globals()`, called after
    its kernels are defined) stale when the source of any of `modules` changes: the digest
    of their sources joins the cache index's stamp of the kernel's own file.

    This reaches into Numba's cache (the index's `_source_stamp`); should a Numba release
    move it, the kernel is compiled without the cache rather than run stale."""
    digest = sources_digest(*modules)
    name = namespace["__name__"]
    for obj in list(namespace.values()):
        if not isinstance(obj, Dispatcher) or obj.py_func.__module__ != name:
            continue
        cache = getattr(obj, "_cache", None)
        index = getattr(cache, "_cache_file", None)
        stamp = getattr(index, "_source_stamp", None)
        if stamp is None:
            if cache is not None and hasattr(cache, "disable"):
                cache.disable()  # a cache we cannot stamp is not used
            continue
        index._source_stamp = (stamp, digest)
