"""Compiled NLP functions for the RMPC, cached on disk (so a restart does not recompile).

A ``CodeGenerator`` writes the C code of the NLP oracle (``nlp`` and ``nlp_f``, ``nlp_g``,
``nlp_grad``, ``nlp_grad_f``, ``nlp_jac_g``, ``nlp_hess_l``, as ``generate_dependencies``
would); the library compiled from it is stored as ``<cache_dir>/rmpc_<solver>_<hard|soft>_<key>.so``
where ``key`` hashes the generated source, the
CasADi version and the compiler flags. So the key changes whenever the problem (horizon,
weights, terminal matrix, camera, constraint groups ...) changes, and only then.
Compilation goes through CasADi's own ``shell`` importer into a process-unique temporary name
that is renamed atomically, so concurrent processes never load a half-written library.

Generating the source only to find its key costs ~1 s of CPU per library (CasADi derives the
Hessian and Jacobians first): too much for a replay that starts many times. So a cheaper
*problem key* (the digest of the serialized NLP expression graph, the solver's options, the
CasADi version and the flags: ~10 ms, or nothing for a problem built before, whose digest
:mod:`companion.core.rmpc_memo` keeps) names a small alias file
``rmpc_<tag>_<problem key>.alias`` holding the library's file name, written once the library
exists. A later start with the same problem
reads the alias and loads the library without generating anything. The generated source
depends only on what the problem key hashes, so the alias can only point to the library that
generating would have found; a missing or dangling alias falls back to generating.
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import casadi as ca

from companion.core.errors import CoreError
from companion.core.rmpc_memo import graph_digest

log = logging.getLogger(__name__)

COMPILER_FLAGS = ("-O1",)
"""gcc flags: -O1 compiles the ~2 MB source in ~7 s; -O2 doubles that for no measured gain."""


ORACLE_FUNCTIONS = ("nlp_f", "nlp_g", "nlp_grad", "nlp_grad_f", "nlp_jac_g", "nlp_hess_l")
"""The oracle's derived functions an ``nlpsol`` loads from a library (plus ``nlp`` itself)."""


class RmpcBuildError(CoreError):
    """The RMPC could not be generated, compiled or loaded."""


@dataclass(frozen=True)
class CompiledNlp:
    """Where the compiled oracle of one NLP lives and whether this process compiled it."""

    library: Path
    key: str
    compiled_now: bool


def cache_key(source: str, flags: tuple[str, ...] = COMPILER_FLAGS) -> str:
    """SHA-256 (first 24 hex digits) of the generated C source, CasADi version and flags."""
    h = hashlib.sha256()
    h.update(source.encode())
    h.update(str(getattr(ca, "__version__", "?")).encode())
    h.update(" ".join(flags).encode())
    return h.hexdigest()[:24]


def problem_key(nlp: Mapping[str, Any], tag: str, options: str) -> str:
    """SHA-256 (first 24 hex digits) of the NLP's expression graph (the digest of x, p -> f,
    g serialized: :func:`companion.core.rmpc_memo.graph_digest`, known without the graph
    when the problem was built before), ``tag``, the solver ``options`` (their ``repr``), the
    CasADi version, the oracle functions and the flags: what the generated source is a
    function of."""
    h = hashlib.sha256(b"graph-digest\0" + graph_digest(nlp).encode())
    for part in (tag, options, str(getattr(ca, "__version__", "?")), " ".join(ORACLE_FUNCTIONS),
                 " ".join(COMPILER_FLAGS)):
        h.update(b"\0" + part.encode())
    return h.hexdigest()[:24]


def compiled_nlp(solver: ca.Function | Callable[[], ca.Function], cache_dir: str, tag: str,
                 nlp: Mapping[str, Any] | None = None, options: str = "") -> CompiledNlp:
    """The shared library holding ``solver``'s oracle functions, compiling it on a cache miss.

    ``solver`` is an ``nlpsol`` built from symbolic expressions (not yet compiled), or a
    function building it (called only when the source must be generated); ``tag`` is a short
    file-name prefix (``"hard"``, ``"soft"``). With ``nlp`` (the problem ``solver`` is built
    from) and ``options`` (the ``repr`` of its solver options), a problem seen before is found
    through its alias file without generating the source (module docstring).
    """
    directory = Path(cache_dir).expanduser()
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RmpcBuildError(f"rmpc.cache_dir: cannot create {directory}: {exc}") from exc
    alias = None
    if nlp is not None:
        alias = directory / f"rmpc_{tag}_{problem_key(nlp, tag, options)}.alias"
        try:
            name = alias.read_text().strip()
        except OSError:
            name = ""
        prefix = f"rmpc_{tag}_"
        if name.startswith(prefix) and name.endswith(".so") and "/" not in name:
            library = directory / name
            if library.exists():
                log.debug("RMPC %s: cache hit %s (alias %s)", tag, library, alias.name)
                return CompiledNlp(library=library, key=name[len(prefix):-3],
                                   compiled_now=False)
    symbolic = solver if isinstance(solver, ca.Function) else solver()
    found = _generate_and_compile(symbolic, directory, tag)
    if alias is not None:
        _write_alias(alias, found, tag)
    return found


def _generate_and_compile(solver: ca.Function, directory: Path, tag: str) -> CompiledNlp:
    with tempfile.TemporaryDirectory(prefix="rmpc_gen_") as tmp:
        # what Function.generate_dependencies writes, but into tmp (no chdir: threads)
        src_path = Path(tmp) / f"rmpc_{tag}.c"
        gen = ca.CodeGenerator(src_path.name)
        gen.add(solver.oracle())
        for fname in ORACLE_FUNCTIONS:
            if solver.has_function(fname):
                gen.add(solver.get_function(fname))
        gen.generate(str(tmp) + os.sep)
        source = src_path.read_text()
        key = cache_key(source)
        library = directory / f"rmpc_{tag}_{key}.so"
        if library.exists():
            log.debug("RMPC %s: cache hit %s", tag, library)
            return CompiledNlp(library=library, key=key, compiled_now=False)
        log.info("RMPC %s: compiling %s (one-off, a few seconds)", tag, library.name)
        name = f"rmpc_{tag}_{key}.tmp{os.getpid()}"
        try:
            importer = ca.Importer(
                str(src_path),
                "shell",
                {
                    "flags": list(COMPILER_FLAGS),
                    "directory": str(directory) + os.sep,
                    "name": name,
                    "temp_suffix": False,
                    "cleanup": False,
                },
            )
        except RuntimeError as exc:
            raise RmpcBuildError(f"RMPC {tag}: compilation failed: {exc}") from exc
        built = Path(importer.library())
        del importer  # unloads the temporary library before the rename
        os.replace(built, library)
        obj = directory / f"{name}.o"
        if obj.exists():
            obj.unlink()
        return CompiledNlp(library=library, key=key, compiled_now=True)


Source = list[ca.Function] | tuple[list[ca.Function], str]
"""What :func:`compiled_functions` compiles: CasADi functions, and optionally C code appended
after their generated source (which may call them by name)."""


def compiled_functions(build: Callable[[], Source], cache_dir: str, tag: str,
                       alias_key: str, flags: tuple[str, ...] = COMPILER_FLAGS) -> CompiledNlp:
    """The shared library holding the plain CasADi functions ``build()`` returns (load each
    with ``ca.external(name, library)``), compiled on a cache miss; the same cache as the
    NLPs' (:func:`compiled_nlp`): the library is named by the hash of its generated source
    and ``flags`` (gcc's). ``alias_key`` names an alias file that finds the library without
    calling ``build`` (which derives the functions symbolically: ~0.5 s of CPU); it must hash
    everything the functions are built from (the caller's problem and the code that builds
    them)."""
    directory = Path(cache_dir).expanduser()
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RmpcBuildError(f"rmpc.cache_dir: cannot create {directory}: {exc}") from exc
    h = hashlib.sha256()
    for part in (alias_key, tag, str(getattr(ca, "__version__", "?")), " ".join(flags)):
        h.update(b"\0" + part.encode())
    alias = directory / f"rmpc_{tag}_{h.hexdigest()[:24]}.alias"
    prefix = f"rmpc_{tag}_"
    try:
        name = alias.read_text().strip()
    except OSError:
        name = ""
    if name.startswith(prefix) and name.endswith(".so") and "/" not in name \
            and (directory / name).exists():
        return CompiledNlp(library=directory / name, key=name[len(prefix):-3],
                           compiled_now=False)
    found = _compile_source(directory, tag, build(), flags)
    _write_alias(alias, found, tag)
    return found


def _write_alias(alias: Path, found: CompiledNlp, tag: str) -> None:
    """Remember which library ``alias`` names (atomic; a read-only cache still works, without
    the shortcut)."""
    tmp = alias.with_name(f"{alias.name}.tmp{os.getpid()}")
    try:
        tmp.write_text(found.library.name + "\n")
        os.replace(tmp, alias)
    except OSError as exc:
        log.debug("RMPC %s: alias not written: %s", tag, exc)


def _compile_source(directory: Path, tag: str, source: Source,
                    flags: tuple[str, ...]) -> CompiledNlp:
    """Generate the C source of ``source``'s functions (and append its C, if any) and
    compile it with ``flags`` (atomic rename into the cache)."""
    functions, appended = source if isinstance(source, tuple) else (source, "")
    with tempfile.TemporaryDirectory(prefix="rmpc_gen_") as tmp:
        src_path = Path(tmp) / f"rmpc_{tag}.c"
        gen = ca.CodeGenerator(src_path.name)
        for f in functions:
            gen.add(f)
        gen.generate(str(tmp) + os.sep)
        if appended:
            with src_path.open("a") as out:
                out.write(appended)
        key = cache_key(src_path.read_text(), flags)
        library = directory / f"rmpc_{tag}_{key}.so"
        if library.exists():
            return CompiledNlp(library=library, key=key, compiled_now=False)
        log.info("RMPC %s: compiling %s (one-off, a few seconds)", tag, library.name)
        name = f"rmpc_{tag}_{key}.tmp{os.getpid()}"
        try:
            importer = ca.Importer(str(src_path), "shell", {
                "flags": list(flags), "directory": str(directory) + os.sep,
                "name": name, "temp_suffix": False, "cleanup": False})
        except RuntimeError as exc:
            raise RmpcBuildError(f"RMPC {tag}: compilation failed: {exc}") from exc
        built = Path(importer.library())
        del importer
        os.replace(built, library)
        obj = directory / f"{name}.o"
        if obj.exists():
            obj.unlink()
        return CompiledNlp(library=library, key=key, compiled_now=True)
