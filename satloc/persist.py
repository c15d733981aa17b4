"""Plain, versioned, atomic persistence.

Every artefact carries ``format`` (what it is) and ``version`` (integer). Readers check both and raise
:class:`FormatError` naming the file on any mismatch or damage. Writers go through a temporary file in the
same directory and ``os.replace``, so an interrupted write never leaves a half-written file behind.
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
import zipfile
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from .errors import FormatError

FORMAT_VERSION = 1
_UMASK = os.umask(0)
os.umask(_UMASK)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is renamed onto ``path``, else removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp creates 0600; give the file the usual permissions
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary directory beside ``path``; on success it replaces ``path`` (whole), else is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    os.chmod(tmp, 0o777 & ~_UMASK)
    try:
        yield tmp
        if path.exists():
            old = path.with_name(f".{path.name}.old-{os.getpid()}")
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def write_json(path: str | os.PathLike, data: Any) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, sort_keys=False) + "\n")


def read_json(path: str | os.PathLike, fmt: str | None = None) -> dict:
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"{path}: file not found")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise FormatError(f"{path}: damaged JSON ({e})") from e
    if fmt is not None:
        check_header(data, fmt, path)
    return data


def header(fmt: str) -> dict:
    return {"format": fmt, "version": FORMAT_VERSION}


def check_header(meta: Mapping[str, Any], fmt: str, path: Any) -> None:
    if not isinstance(meta, Mapping) or "format" not in meta:
        raise FormatError(f"{path}: not a satloc '{fmt}' file (no 'format' field)")
    if meta["format"] != fmt:
        raise FormatError(f"{path}: expected a satloc '{fmt}' file, found format '{meta['format']}'")
    if meta.get("version") != FORMAT_VERSION:
        raise FormatError(
            f"{path}: '{fmt}' file of version {meta.get('version')!r}; this satloc reads version {FORMAT_VERSION}"
        )


def save_npz(path: str | os.PathLike, fmt: str, arrays: Mapping[str, np.ndarray], meta: Mapping | None = None) -> None:
    """Write arrays plus a JSON header (key ``__meta__``) to a compressed npz, atomically."""
    m = dict(header(fmt))
    if meta:
        m.update(meta)
    payload = {k: np.asarray(v) for k, v in arrays.items()}
    payload["__meta__"] = np.frombuffer(json.dumps(m).encode(), dtype=np.uint8)
    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **payload)


def load_npz(path: str | os.PathLike, fmt: str) -> tuple[dict[str, np.ndarray], dict]:
    """Read an npz written by :func:`save_npz`; checks format and version, never unpickles."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"{path}: file not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as e:
        raise FormatError(f"{path}: damaged or not an npz file ({e})") from e
    if "__meta__" not in arrays:
        raise FormatError(f"{path}: not a satloc '{fmt}' file (no header)")
    try:
        meta = json.loads(arrays.pop("__meta__").tobytes().decode())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise FormatError(f"{path}: damaged header ({e})") from e
    check_header(meta, fmt, path)
    return arrays, meta
