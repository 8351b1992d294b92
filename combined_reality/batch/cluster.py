"""A batch on a dask.distributed cluster: the compiled model code this machine has is shipped
to every worker that lacks it, so that no worker compiles a structure again."""
from __future__ import annotations

from pathlib import Path
from typing import Iterable

from sim.compiled import cache_dir, cached_model_code

from ..files import atomic_write

__all__ = ["cache_files", "missing_cache_files", "install_cache_files", "share_compiled_code"]


def cache_files() -> dict[str, Path]:
    """The compiled model code of this machine's cache (shipped to cluster workers)."""
    return {p.name: p for p in cached_model_code() if p.suffix == ".so"}


def missing_cache_files(names: Iterable[str]) -> list[str]:
    """Run on a worker: which of these compiled files its cache lacks."""
    d = cache_dir()
    return [n for n in names if not (d / n).exists()]


def install_cache_files(files: dict[str, bytes]) -> int:
    """Run on a worker: store compiled model code in its cache (atomically; existing kept)."""
    d = cache_dir()
    d.mkdir(parents=True, exist_ok=True)
    n = 0
    for name, data in files.items():
        target = d / name
        if not target.exists():
            atomic_write(target, data)
            target.chmod(0o755)
            n += 1
    return n


def share_compiled_code(client) -> int:
    """Give every worker the compiled model code this machine has, so that no worker
    rebuilds a model structure that was compiled once already (workers on the same machine
    share its cache; a task loads the compiled library from there). Returns the number of
    files installed."""
    files = cache_files()
    if not files:
        return 0
    missing = client.run(missing_cache_files, list(files))
    installed = 0
    for worker, names in missing.items():
        if names:
            # read here, for the workers that lack them: usually none, or one new structure
            res = client.run(install_cache_files, {n: files[n].read_bytes() for n in names}, workers=[worker])
            installed += sum(res.values())
    return installed
