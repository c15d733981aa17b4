"""Where the simulator keeps what it makes once and reuses across processes: ``$SATLOC_CACHE`` (default
``~/.cache/satloc``). Built scenes (:func:`satloc_env.world.scene.load_scene`), the auto localizer's builds and the
no-database localizer's map features live in folders of their own under it."""
from __future__ import annotations

import functools
import hashlib
import os
from pathlib import Path

__all__ = ["CACHE_ENV", "cache_root", "code_digest", "library_versions"]

CACHE_ENV = "SATLOC_CACHE"


def cache_root(cache_dir: str | os.PathLike | None = None) -> Path:
    """``cache_dir`` if given, else ``$SATLOC_CACHE``, else ``~/.cache/satloc``."""
    if cache_dir is not None:
        return Path(cache_dir).expanduser()
    env = os.environ.get(CACHE_ENV)
    return Path(env).expanduser() if env else Path.home() / ".cache" / "satloc"


@functools.lru_cache(maxsize=None)
def code_digest(package_dir: str, recursive: bool = True) -> str:
    """sha256 of the Python sources of a package folder (every ``*.py`` below it, or only in it with
    ``recursive=False``, by relative path and content): a cache entry made by other code than this one's misses,
    whether or not the version number moved."""
    root = Path(package_dir)
    h = hashlib.sha256()
    for p in sorted(root.rglob("*.py") if recursive else root.glob("*.py")):
        h.update(str(p.relative_to(root)).encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()


@functools.lru_cache(maxsize=None)
def library_versions(*names: str) -> tuple:
    """The installed versions of the distributions ``names`` (None for one not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    out = []
    for n in names:
        try:
            out.append((n, version(n)))
        except PackageNotFoundError:
            out.append((n, None))
    return tuple(out)
