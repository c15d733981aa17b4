"""Plain, versioned, atomic persistence.

Every artefact carries ``format`` (what it is) and ``version`` (integer). Readers check both and raise
:class:`FormatError` naming the file on any mismatch or damage. Writers go through a temporary file in the
same directory and ``os.replace``, so an interrupted write never leaves a half-written file behind. A
process killed mid-write (SIGKILL) leaves its temporary behind; the temporary's name says which process owns
it, and the next write of the same path removes it once that process is gone (:func:`remove_stale_temps`).
"""
from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import math
import os
import re
import shutil
import socket
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from .errors import FormatError

FORMAT_VERSION = 1
_UMASK = os.umask(0)
os.umask(_UMASK)


@functools.lru_cache(maxsize=1)
def _host_tag() -> str:
    """A short tag of this machine's name: a temporary name's owner is looked up only on its own host."""
    return hashlib.sha1(socket.gethostname().encode()).hexdigest()[:6]


def _owner_tag() -> str:
    """``<pid>-<host tag>``: put into every temporary name, so a later writer can tell a leftover of a dead
    process (SIGKILL, power loss) from one that is still being written."""
    return f"{os.getpid()}-{_host_tag()}"


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True  # exists (another user's) or cannot tell: keep its files
    try:  # a killed process nobody has reaped yet is a zombie: dead for our purpose
        stat = Path(f"/proc/{pid}/stat").read_text()
        return stat[stat.rindex(")") + 2:][:1] != "Z"
    except (OSError, ValueError):
        return True


def _stale_re(name: str) -> "re.Pattern[str]":
    return re.compile(rf"^\.{re.escape(name)}\.(\d+)-([0-9a-f]{{6}})\.(?:[^/]*\.tmp[^/]*|[^/]*\.old)$")


def remove_stale_temps(path: str | os.PathLike) -> list[Path]:
    """Remove the temporary files and directories that :func:`atomic_path` / :func:`atomic_dir` left beside
    ``path`` in a process that has died since (killed with SIGKILL, say) on this host; returns them.

    Temporaries of live processes, of other hosts, and names this module did not make are left alone."""
    path = Path(path)
    pat, host = _stale_re(path.name), _host_tag()
    removed = []
    try:
        entries = list(os.scandir(path.parent))
    except OSError:
        return removed
    for e in entries:
        m = pat.match(e.name)
        if m is None or m.group(2) != host or _alive(int(m.group(1))):
            continue
        p = Path(e.path)
        if e.is_dir(follow_symlinks=False):
            shutil.rmtree(p, ignore_errors=True)
        else:
            with contextlib.suppress(FileNotFoundError):
                p.unlink()
        removed.append(p)
    return removed


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is renamed onto ``path``, else removed.

    The temporary name is ``.<name>.<pid>-<host>.<random>.tmp<suffix>``; leftovers of dead processes (a
    SIGKILL mid-write) are removed by the next write of the same ``path`` (:func:`remove_stale_temps`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{_owner_tag()}.", suffix=".tmp" + suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp creates 0600; give the file the usual permissions
        yield tmp_path
        os.replace(tmp_path, path)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary directory beside ``path``; on success it replaces ``path`` (whole), else is removed.

    Replacing an existing ``path`` takes two renames (the old one aside, the new one in); an exception
    between them puts the old one back. Temporary names carry the owner as in :func:`atomic_path`, and
    leftovers of dead processes are removed by the next :func:`atomic_dir` of the same ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(path)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.{_owner_tag()}.", suffix=".tmp", dir=path.parent))
    try:
        os.chmod(tmp, 0o777 & ~_UMASK)
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = None
    try:
        if path.exists() or path.is_symlink():
            old = path.with_name(f".{path.name}.{_owner_tag()}.{os.urandom(4).hex()}.old")
            os.replace(path, old)
        os.replace(tmp, path)
    except BaseException:
        if old is not None and not (path.exists() or path.is_symlink()):
            with contextlib.suppress(OSError):
                os.replace(old, path)
        old = None  # put back, or (if that failed) the only copy left: never removed here
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        if old is not None:
            if old.is_dir() and not old.is_symlink():
                shutil.rmtree(old, ignore_errors=True)
            else:
                old.unlink(missing_ok=True)


def write_json(path: str | os.PathLike, data: Any) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, sort_keys=False) + "\n")


def read_json(path: str | os.PathLike, fmt: str | None = None) -> dict:
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"{path}: file not found")
    try:
        data = json.loads(path.read_bytes().decode("utf-8"))
    except (ValueError, RecursionError) as e:  # JSONDecodeError, UnicodeDecodeError; nesting too deep
        raise FormatError(f"{path}: damaged JSON ({type(e).__name__}: {str(e)[:200]})") from e
    except OSError as e:
        raise FormatError(f"{path}: not readable ({e})") from e
    if fmt is not None:
        check_header(data, fmt, path)
    return data


def header(fmt: str) -> dict:
    return {"format": fmt, "version": FORMAT_VERSION}


def check_header(meta: Mapping[str, Any], fmt: str, path: Any) -> None:
    if not isinstance(meta, Mapping) or "format" not in meta:
        raise FormatError(f"{path}: not a satloc '{fmt}' file (no 'format' field)")
    if meta["format"] != fmt:
        raise FormatError(f"{path}: expected a satloc '{fmt}' file, found format {_short_repr(meta['format'])}")
    v = meta.get("version")
    if isinstance(v, bool) or v != FORMAT_VERSION:
        raise FormatError(
            f"{path}: '{fmt}' file of version {_short_repr(v)}; this satloc reads version {FORMAT_VERSION}"
        )


def _short_repr(v: Any, n: int = 60) -> str:
    r = repr(v)
    return r if len(r) <= n else r[:n - 3] + "..."


def save_npz(path: str | os.PathLike, fmt: str, arrays: Mapping[str, np.ndarray], meta: Mapping | None = None,
             compress: bool = True) -> None:
    """Write arrays plus a JSON header (key ``__meta__``) to an npz, atomically: compressed, or with
    ``compress`` False stored as they are (for arrays that barely compress and are read often: no inflating)."""
    m = dict(header(fmt))
    if meta:
        m.update(meta)
    payload = {k: np.asarray(v) for k, v in arrays.items()}
    payload["__meta__"] = np.frombuffer(json.dumps(m).encode(), dtype=np.uint8)
    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as f:
            (np.savez_compressed if compress else np.savez)(f, **payload)


def load_npz(path: str | os.PathLike, fmt: str, spec: Mapping[str, "ArraySpec"] | None = None,
             sizes: Mapping[str, Any] | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """Read an npz written by :func:`save_npz`; checks format and version, never unpickles.

    ``spec``: what its arrays must be (:class:`ArraySpec` by name, checked by :func:`check_arrays`, with
    ``sizes`` the named sizes known beforehand); any damage or mismatch raises :class:`FormatError` naming
    the file."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"{path}: file not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as e:  # BadZipFile, zlib.error, CRC mismatch, pickled arrays, truncated data, huge claimed
        # shapes (MemoryError): numpy and zipfile raise many types for damaged input; all mean the same here
        raise FormatError(f"{path}: damaged or not an npz file ({type(e).__name__}: {str(e)[:200]})") from e
    if "__meta__" not in arrays:
        raise FormatError(f"{path}: not a satloc '{fmt}' file (no header)")
    raw = arrays.pop("__meta__")
    try:
        if raw.dtype != np.uint8 or raw.ndim != 1:
            raise ValueError(f"header array of {raw.dtype} {raw.shape}, expected uint8 bytes")
        meta = json.loads(raw.tobytes().decode("utf-8"))
    except (ValueError, RecursionError) as e:
        raise FormatError(f"{path}: damaged header ({type(e).__name__}: {str(e)[:200]})") from e
    check_header(meta, fmt, path)
    if spec is not None:
        check_arrays(arrays, spec, path, sizes)
    return arrays, meta


# --- read-side validation --------------------------------------------------------------------------------
_KIND_NAMES = {"f": "float", "i": "signed integer", "u": "unsigned integer", "b": "bool"}


@dataclass(frozen=True)
class ArraySpec:
    """What an array of a saved artefact must be.

    ``kinds``: accepted numpy dtype kinds (``"f"`` float, ``"i"``/``"u"`` integers, ``"b"`` bool);
    ``shape``: one entry per axis: an int (that size), a str (a named size, equal wherever the name appears:
    ``"N"`` rows shared by several arrays) or None (any size); ``finite``: float values must be finite;
    ``min`` / ``max``: bounds of the values; ``required``: whether the array must be present."""

    kinds: str
    shape: tuple
    finite: bool = True
    min: float | None = None
    max: float | None = None
    required: bool = True


def check_arrays(arrays: Mapping[str, np.ndarray], spec: Mapping[str, ArraySpec], path: Any,
                 sizes: Mapping[str, Any] | None = None) -> dict[str, int]:
    """Check ``arrays`` against ``spec`` (see :class:`ArraySpec`); returns the named sizes found. ``sizes``:
    named sizes known beforehand, each an int or ``(int, where it comes from)`` for the message. Raises
    :class:`FormatError` naming ``path``, the array and what was expected."""
    known: dict[str, tuple[int, str]] = {}
    for name, v in (sizes or {}).items():
        known[name] = (int(v[0]), str(v[1])) if isinstance(v, tuple) else (int(v), "the header")
    for key, sp in spec.items():
        if key not in arrays:
            if sp.required:
                raise FormatError(f"{path}: missing array '{key}'")
            continue
        a = arrays[key]
        want = "(" + ", ".join("any" if n is None else str(n) for n in sp.shape) + \
            ("," if len(sp.shape) == 1 else "") + ")"
        kinds = " or ".join(_KIND_NAMES.get(k, k) for k in sp.kinds)
        if a.dtype.kind not in sp.kinds or a.ndim != len(sp.shape):
            raise FormatError(f"{path}: array '{key}': expected {kinds} of shape {want}, got {a.dtype} {a.shape}")
        for axis, (n, want_n) in enumerate(zip(a.shape, sp.shape)):
            if isinstance(want_n, int) and n != want_n:
                raise FormatError(f"{path}: array '{key}': expected shape {want}, got {a.shape}")
            if isinstance(want_n, str):
                if want_n in known and known[want_n][0] != n:
                    raise FormatError(f"{path}: array '{key}' has {n} along axis {axis}, expected {known[want_n][0]} "
                                      f"({want_n}, from {known[want_n][1]})")
                known.setdefault(want_n, (n, f"array '{key}'"))
        if a.size == 0:
            continue
        if sp.finite and a.dtype.kind == "f" and not np.isfinite(a).all():
            bad = np.argwhere(~np.isfinite(a))[0]
            raise FormatError(f"{path}: array '{key}': non-finite value {a[tuple(bad)]} at "
                              f"{tuple(int(i) for i in bad)}")
        if sp.min is not None and a.min() < sp.min:
            raise FormatError(f"{path}: array '{key}': values must be >= {sp.min:g}, found {a.min()}")
        if sp.max is not None and a.max() > sp.max:
            raise FormatError(f"{path}: array '{key}': values must be <= {sp.max:g}, found {a.max()}")
    return {k: v[0] for k, v in known.items()}


def nonfinite_path(tree: Any, prefix: str = "") -> str | None:
    """The path (``a.b[2]``) of the first non-finite float in a JSON-like tree, or None."""
    if isinstance(tree, float):
        return None if math.isfinite(tree) else (prefix or "value")
    if isinstance(tree, Mapping):
        for k, v in tree.items():
            p = nonfinite_path(v, f"{prefix}.{k}" if prefix else str(k))
            if p is not None:
                return p
    elif isinstance(tree, (list, tuple)):
        for i, v in enumerate(tree):
            p = nonfinite_path(v, f"{prefix}[{i}]")
            if p is not None:
                return p
    return None


def header_number(meta: Mapping[str, Any], key: str, path: Any, *, positive: bool = False,
                  integer: bool = False, default: Any = ...) -> float:
    """A finite number ``meta[key]`` of a header (``positive``: > 0; ``integer``: an int); FormatError naming
    the file and the field otherwise."""
    if key not in meta:
        if default is not ...:
            return default
        raise FormatError(f"{path}: missing field '{key}'")
    v = meta[key]
    kind = "an integer" if integer else "a number"
    if isinstance(v, bool) or not isinstance(v, int if integer else (int, float)) or not math.isfinite(v):
        raise FormatError(f"{path}: field '{key}': expected {kind}, got {str(v)[:60]!r}")
    if positive and not v > 0:
        raise FormatError(f"{path}: field '{key}': expected {kind} > 0, got {v!r}")
    return v


def header_point(meta: Mapping[str, Any], key: str, path: Any) -> tuple[float, float]:
    """A finite 2-D point ``meta[key]`` (e.g. a map's origin) of a header."""
    v = meta.get(key)
    if (not isinstance(v, (list, tuple)) or len(v) != 2
            or not all(isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in v)):
        raise FormatError(f"{path}: field '{key}': expected [x, y] finite numbers, got {str(v)[:60]!r}")
    return float(v[0]), float(v[1])


def check_zip(path: Path) -> None:
    """Verify the CRC-32 of every member of a zip archive (a torch file: torch itself does not, so a flipped
    bit in a tensor would load as another number); FormatError naming the file on any damage."""
    try:
        with zipfile.ZipFile(path) as z:
            bad = z.testzip()
    except Exception as e:  # BadZipFile, zlib.error, NotImplementedError, OSError, ...: damaged either way
        raise FormatError(f"{path}: damaged or not a zip-based file ({type(e).__name__}: {str(e)[:200]})") from e
    if bad is not None:
        raise FormatError(f"{path}: damaged: member {bad!r} fails its CRC check")
