"""Small C kernels of the companion, built once with the system's C compiler and cached.

A kernel's source ships beside its Python module; :func:`compiled_library` compiles it with
``$CC`` (else ``gcc``, else ``cc``) into a cache directory (``~/.cache/rmpc-ibvs`` by default,
the RMPC's), named by the hash of the source, the flags and the machine's architecture, and
returns the library's path for ctypes. The flags round every operation as written (no
contraction into fused multiply-adds, no fast-math) and target no particular CPU, so a kernel
can compute the IEEE numbers of the Python or numpy code it replaces; each kernel's module
checks that on this machine before first use and falls back to that code otherwise.
"""

from __future__ import annotations

import hashlib
import logging
import os
import platform
import shutil
import subprocess
import tempfile
from pathlib import Path

_log = logging.getLogger(__name__)

FLAGS = ("-O2", "-fPIC", "-shared", "-ffp-contract=off", "-fno-fast-math")
"""gcc flags: every operation rounded as written (no contraction into fma, no fast-math);
no -march (a cached library runs on any machine of the architecture)."""
DEFAULT_CACHE_DIR = "~/.cache/rmpc-ibvs"


def source_key(text: str) -> str:
    """The cache key of a kernel's source: its text, :data:`FLAGS` and the architecture."""
    h = hashlib.sha256(text.encode())
    for part in (" ".join(FLAGS), platform.machine()):
        h.update(b"\0" + part.encode())
    return h.hexdigest()[:24]


def compiled_library(directory: Path, text: str, stem: str, what: str) -> Path | None:
    """The library ``<stem>_<key>.so`` of the C source ``text`` in ``directory``, compiled on
    a miss (an atomic rename: a concurrent process never loads half a file); None without a
    compiler (logged, ``what`` naming the kernel). A compiler error raises
    :class:`subprocess.CalledProcessError`."""
    library = directory / f"{stem}_{source_key(text)}.so"
    if library.exists():
        return library
    env_cc = os.environ.get("CC")
    cc = shutil.which(env_cc) if env_cc else shutil.which("gcc") or shutil.which("cc")
    if not cc:
        _log.info("%s: no C compiler; the Python path", what)
        return None
    directory.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f"{stem}_gen_") as tmp:
        src = Path(tmp) / f"{stem}.c"
        src.write_text(text)
        built = directory / f"{library.name}.tmp{os.getpid()}"
        _log.info("%s: compiling %s (one-off)", what, library.name)
        subprocess.run([cc, *FLAGS, "-o", str(built), str(src), "-lm"], check=True,
                       capture_output=True, timeout=120)
        os.replace(built, library)
    return library
