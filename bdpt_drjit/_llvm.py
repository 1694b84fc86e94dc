"""Find a usable libLLVM (>= 16) for Dr.Jit's LLVM backend before Dr.Jit starts.

Dr.Jit 1.5's LLVM backend aborts the whole process (``LLVM ERROR: Cannot select
... fminimum``) with LLVM 15 or older, so an old library must be refused before
the first kernel is compiled, with a message that says how to fix it.
"""
from __future__ import annotations

import glob
import os
import re
import sys

MIN_LLVM = 16

FIX = ("Install a newer LLVM shared library, e.g. on Debian/Ubuntu "
       "`sudo apt-get install libllvm19`, or point DRJIT_LIBLLVM_PATH at a "
       "libLLVM.so of version >= %d." % MIN_LLVM)


class LLVMError(RuntimeError):
    """Raised when Dr.Jit's LLVM backend has no LLVM >= 16 to use."""


def _candidates() -> list[tuple[int, str]]:
    """libLLVM shared libraries on this machine, as (major version, path)."""
    pats = ["/usr/lib/x86_64-linux-gnu/libLLVM*.so*", "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
            "/usr/lib/llvm-*/lib/libLLVM*.so*", "/usr/lib64/libLLVM*.so*", "/usr/lib/libLLVM*.so*",
            "/usr/local/lib/libLLVM*.so*", "/opt/homebrew/opt/llvm/lib/libLLVM*.dylib"]
    found = []
    for pat in pats:
        for path in glob.glob(pat):
            m = re.search(r"libLLVM[-.]?(\d+)", os.path.basename(path)) or re.search(r"llvm-(\d+)", path)
            if m:
                found.append((int(m.group(1)), path))
    return sorted(found, reverse=True)


def prepare() -> None:
    """Point Dr.Jit at the newest libLLVM >= 16 unless the user already chose one.

    Must run before ``import drjit`` to have an effect; harmless afterwards.
    """
    if os.environ.get("DRJIT_LIBLLVM_PATH") or "drjit" in sys.modules:
        return
    good = [(v, p) for v, p in _candidates() if v >= MIN_LLVM]
    if good:
        os.environ["DRJIT_LIBLLVM_PATH"] = good[0][1]


def check(variant: str) -> None:
    """Raise LLVMError if ``variant`` is an LLVM variant and no LLVM >= 16 is in use."""
    if not variant.startswith("llvm_"):
        return
    import drjit as dr
    if not dr.has_backend(dr.JitBackend.LLVM):
        raise LLVMError("Dr.Jit's LLVM backend found no libLLVM. " + FIX)
    version = tuple(dr.detail.llvm_version())
    if version[0] < MIN_LLVM:
        raise LLVMError("Dr.Jit loaded LLVM %s, but Dr.Jit 1.5 needs LLVM >= %d "
                        "(older versions abort with 'Cannot select ... fminimum'). %s"
                        % (".".join(map(str, version)), MIN_LLVM, FIX))


if __name__ == "__main__":          # used by ./dev: exit 0 if a usable LLVM exists
    ok = os.environ.get("DRJIT_LIBLLVM_PATH") or any(v >= MIN_LLVM for v, _ in _candidates())
    if not ok:
        print("No libLLVM >= %d found. %s" % (MIN_LLVM, FIX), file=sys.stderr)
    sys.exit(0 if ok else 1)
