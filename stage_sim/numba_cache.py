"""Numba's on-disk cache, keyed by all the compiled code of the project.

numba invalidates a cached kernel only when the source file *of that kernel* changes, not
when a function it calls (and compiles into itself) does: after adding a friction law or
editing the plant, the batch engine would keep running the old code from its cache. So
every kernel is cached under ``stage_sim/__pycache__/numba-<hash>/``, ``<hash>`` taken over
every source file of the project that defines compiled code (a ``@njit`` / ``@jit`` /
``@vectorize`` ... decorator, or ``= njit(...)``): any change to one of them starts a fresh cache
(older ones are removed after an hour), while editing a module that only calls kernels or sets
numba's threads (the bench, the executor) keeps it. Plain-Python constants a kernel reads must
therefore live in a module that defines compiled code. An explicit ``NUMBA_CACHE_DIR`` is
respected. Imported first by each package of the project, before any kernel is defined.
"""
from __future__ import annotations

import hashlib
import os
import re
import shutil
import time
from pathlib import Path

import numba

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("stage_sim", "stage_control", "experiment_runner")


_COMPILED = re.compile(rb"^[ \t]*@(?:numba\.)?(?:njit|jit|vectorize|guvectorize|cfunc|stencil|jitclass)\b"
                       rb"|=[ \t]*(?:numba\.)?(?:njit|jit)\(", re.M)
"""A line that defines compiled code."""


def code_hash(root: Path = ROOT) -> str:
    """Hash of every ``.py`` file of the project's packages under ``root`` that defines compiled code
    (:data:`_COMPILED`)."""
    h = hashlib.sha256()
    for pkg in PACKAGES:
        for f in sorted((root / pkg).rglob("*.py")):
            text = f.read_bytes()
            if _COMPILED.search(text):
                h.update(str(f.relative_to(root)).encode())
                h.update(text)
    return h.hexdigest()[:16]


def configure(root: Path = ROOT) -> Path | None:
    """Point numba's cache at ``numba-<code_hash>`` (unless ``NUMBA_CACHE_DIR`` is set); returns it."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return None
    base = root / "stage_sim" / "__pycache__"
    path = base / f"numba-{code_hash(root)}"
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:            # read-only install: numba's default place
        return None
    now = time.time()
    for old in base.glob("numba-*"):
        if old != path and now - old.stat().st_mtime > 3600:
            shutil.rmtree(old, ignore_errors=True)
    os.utime(path)
    numba.config.CACHE_DIR = str(path)
    return path


CACHE_DIR = configure()
