"""Seeded mutation fuzzing of the files satloc reads (issue 15, item 3); the engine of ``tests/test_fuzz.py``.

A :class:`Format` is a valid artefact written by the project's own writers into a template directory, the
files in it that may be mutated (:class:`Target`, each of a *kind*), a loader that reads the artefact as the
project does, a digest of what it loaded and the invariants any loaded result must satisfy.

A *case* applies one seeded mutation to one target in a fresh copy of the template and runs the loader under
a time bound (``signal.setitimer``) and a memory bound (``RLIMIT_AS``). Mutations (:func:`mutate`):

* any file: truncate at a random offset, flip random bits or set a random byte, replace it by a foreign file
  of another kind under the right name (empty, PNG, JPEG, JSON, YAML, npz, torch, text, random bytes),
  delete it;
* JSON, YAML and torch dicts (trees): drop a key, a value of the wrong type, NaN, +-inf, a negative, huge or
  zero number, another string, an unknown key;
* npz: one array of a wrong dtype kind or size, of another number of dimensions, empty, with a NaN, inf,
  negative or huge element, an array dropped or an unknown one added; the JSON header as a tree or replaced;
* torch tensors (in a torch tree): NaN, inf, huge, another dtype, another shape;
* text (KITTI calibration, OXTS, timestamps, Malaga camera file and GPS log, world files): drop, duplicate or
  swap lines, a token replaced by a non-number, NaN, inf, a huge or negative number, a column dropped or
  added, CRLF line endings;
* images: another size, grey or colour, another bit depth.

Each mutation carries what the loader must do with it (:data:`EXPECTS`):

* ``reject``: raise :class:`satloc.FormatError` or :class:`satloc.ConfigError`;
* ``same``: reject it, or load a result whose digest equals the original's (the mutation touched nothing the
  loader reads, or a checksum must catch it: zip CRCs of npz and torch files, PNG chunk CRCs);
* ``valid``: reject it, or load any result that satisfies the format's invariants (the mutation may have
  made another valid file, e.g. a digit changed in a text file).

Whatever the expectation: an error must be a FormatError/ConfigError whose message names the mutated file
(its name), never another exception, never a hang; a loaded result must satisfy the invariants.
"""
from __future__ import annotations

import contextlib
import faulthandler
import io
import json
import math
import os
import resource
import shutil
import signal
import time
import traceback
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from satloc import ConfigError, FormatError

EXPECTS = ("reject", "same", "valid")
KINDS = ("json", "yaml", "npz", "png", "jpeg", "torch", "tiff", "text", "unused")


# --- formats and cases -------------------------------------------------------------------------------------
@dataclass
class Target:
    """A file of an artefact that cases mutate.

    ``path``: relative to the artefact's root; ``kind``: one of :data:`KINDS` (``unused``: a file the loader
    must not depend on, e.g. a listing it does not read); ``delete``: the expectation when the file is
    deleted; ``expect``: if set, the expectation of every mutation of this file (e.g. ``same`` for a cache
    the loader recomputes); ``free``: paths of tree nodes (tuples of keys) or npz array names whose content
    the loader does not validate and the digest leaves out (free-form metadata), except below the paths in
    ``bound``; ``nan_ok``: npz arrays where NaN is allowed; ``required``: npz arrays the loader needs;
    ``image``: expectations of image mutations by name (default ``valid``); ``weight``: how often the
    file is picked."""

    path: str
    kind: str
    delete: str = "reject"
    expect: str | None = None
    free: tuple = ()
    bound: tuple = ()
    nan_ok: tuple = ()
    required: tuple = ()
    image: dict = field(default_factory=dict)
    weight: float = 1.0

    def __post_init__(self):
        assert self.kind in KINDS, self.kind
        assert self.delete in EXPECTS and (self.expect is None or self.expect in EXPECTS)


@dataclass
class Targeted:
    """A hand-written mutation run before the seeded ones (a known pitfall: a value just outside its domain,
    a huge size that must not be allocated): ``apply(path)`` edits the file ``target`` of a fresh copy."""

    target: str
    op: str
    apply: Callable[[Path], None]
    expect: str = "reject"


@dataclass
class Format:
    """A fuzzed file format: ``make(dir)`` writes the valid artefact into ``dir``; ``load(dir)`` reads it as
    the project does; ``digest(result)`` is what is compared (nested dicts, lists, primitives and numpy
    arrays); ``check(result)`` asserts the invariants; ``cases``: how many seeded cases a run tries;
    ``targeted``: hand-written cases run first."""

    name: str
    make: Callable[[Path], None]
    targets: list[Target]
    load: Callable[[Path], Any]
    digest: Callable[[Any], Any]
    check: Callable[[Any], None]
    cases: int
    time_limit_s: float = 20.0
    targeted: list[Targeted] = field(default_factory=list)


@dataclass
class Mutation:
    target: str
    op: str
    expect: str


@dataclass
class CaseResult:
    index: int
    mutation: Mutation | None
    outcome: str            # loaded_same | loaded_changed | rejected | FAIL
    detail: str = ""
    seconds: float = 0.0


class CaseTimeout(BaseException):
    """The per-case time bound ran out (a BaseException, so that no loader's ``except Exception`` hides it)."""


class NotApplicable(Exception):
    """This mutation does not apply to this file (e.g. NaN into an integer array); another one is drawn."""


# --- running -----------------------------------------------------------------------------------------------
@contextlib.contextmanager
def time_bound(seconds: float, hard_factor: float = 6.0):
    """Raise :class:`CaseTimeout` after ``seconds`` (SIGALRM: interrupts Python code, and C code when it
    returns). A loader stuck inside C code for ``hard_factor`` times longer makes the process dump every
    thread's traceback and exit (``faulthandler``): a failed run rather than a hang."""
    def handler(signum, frame):
        raise CaseTimeout(f"no result within {seconds:g} s")

    old = signal.signal(signal.SIGALRM, handler)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    faulthandler.dump_traceback_later(seconds * hard_factor, exit=True)
    try:
        yield
    finally:
        faulthandler.cancel_dump_traceback_later()
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def _vm_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")


@contextlib.contextmanager
def memory_bound(extra_bytes: int):
    """Limit the address space to its current size plus ``extra_bytes`` (a loader that believes a huge size
    gets a MemoryError instead of exhausting the shared machine); no-op where unsupported."""
    try:
        soft, hard = resource.getrlimit(resource.RLIMIT_AS)
        want = _vm_bytes() + extra_bytes
        if hard != resource.RLIM_INFINITY:
            want = min(want, hard)
        resource.setrlimit(resource.RLIMIT_AS, (want, hard))
    except (OSError, ValueError):
        yield
        return
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


def equal(a: Any, b: Any) -> bool:
    """Deep equality of digests: arrays by dtype, shape and values (NaN equal to NaN)."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        if not (isinstance(a, np.ndarray) and isinstance(b, np.ndarray)):
            return False
        if a.dtype != b.dtype or a.shape != b.shape:
            return False
        if a.dtype.kind in "fc":
            return bool(np.array_equal(a, b, equal_nan=True))
        return bool(np.array_equal(a, b))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(equal(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(equal(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return type(a) is type(b) and a == b


def first_difference(a: Any, b: Any, where: str = "") -> str:
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return f"{where or 'digest'}: keys {sorted(map(str, a))} != {sorted(map(str, b))}"
        for k in a:
            if not equal(a[k], b[k]):
                return first_difference(a[k], b[k], f"{where}.{k}")
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b)):
            if not equal(x, y):
                return first_difference(x, y, f"{where}[{i}]")
    short = lambda v: (f"array {v.dtype} {v.shape}" if isinstance(v, np.ndarray) else repr(v)[:80])  # noqa: E731
    return f"{where or 'digest'}: {short(a)} != {short(b)}"


def run_format(fmt: Format, work: Path, cases: int | None = None, seed: int = 0,
               memory_extra: int = 3 << 30) -> tuple[dict, list[CaseResult]]:
    """Write the template, load it (must succeed), then run the targeted cases and ``cases`` (default
    ``fmt.cases``) seeded ones; returns the counts ({tried, loaded_same, loaded_changed, rejected, failed})
    and every case's result."""
    work = Path(work)
    template = work / "template"
    fmt.make(template)
    probe = work / "probe"
    shutil.copytree(template, probe, symlinks=True)
    ref = fmt.load(probe)
    fmt.check(ref)
    ref_digest = fmt.digest(ref)
    del ref
    results = []
    n = cases if cases is not None else fmt.cases
    for i in range(-len(fmt.targeted), n):  # targeted cases get negative indices
        d = work / f"case{i:+05d}"
        shutil.copytree(template, d, symlinks=True)
        t0 = time.perf_counter()
        try:
            if i < 0:
                tc = fmt.targeted[i + len(fmt.targeted)]
                tc.apply(d / tc.target)
                m = Mutation(tc.target, f"targeted: {tc.op}", tc.expect)
            else:
                m = mutate(fmt, d, np.random.default_rng([seed, zlib.crc32(fmt.name.encode()), i]))
        except Exception as e:  # the engine itself failed: report, do not hide
            results.append(CaseResult(i, None, "FAIL", f"mutation failed: {type(e).__name__}: {e}"))
            shutil.rmtree(d, ignore_errors=True)
            continue
        outcome, detail = _run_case(fmt, d, m, ref_digest, memory_extra)
        results.append(CaseResult(i, m, outcome, detail, time.perf_counter() - t0))
        shutil.rmtree(d, ignore_errors=True)
    counts = {"tried": len(results)}
    for k in ("loaded_same", "loaded_changed", "rejected", "FAIL"):
        counts[k if k != "FAIL" else "failed"] = sum(r.outcome == k for r in results)
    return counts, results


def _run_case(fmt: Format, d: Path, m: Mutation, ref_digest, memory_extra: int) -> tuple[str, str]:
    name = Path(m.target).name
    try:
        with memory_bound(memory_extra), time_bound(fmt.time_limit_s):
            result = fmt.load(d)
    except CaseTimeout as e:
        return "FAIL", f"hang: {e}"
    except (FormatError, ConfigError) as e:
        if name not in str(e):
            return "FAIL", f"{type(e).__name__} does not name {name}: {e}"
        return "rejected", f"{type(e).__name__}: {str(e)[:300]}"
    except Exception as e:  # noqa: BLE001 - the point of the test
        tb = "".join(traceback.format_exception(type(e), e, e.__traceback__)[-6:])
        return "FAIL", f"{type(e).__name__}: {e}\n{tb}"
    try:
        fmt.check(result)
    except Exception as e:  # noqa: BLE001 - an AssertionError, or the result failing when used
        return "FAIL", f"loaded a result that breaks the invariants: {type(e).__name__}: {str(e)[:300]}"
    dg = fmt.digest(result)
    same = equal(dg, ref_digest)
    if m.expect == "reject":
        how = "equal to" if same else "differs from"
        return "FAIL", f"accepted (expected a rejection); result {how} the original" + (
            "" if same else f" ({first_difference(dg, ref_digest)})")
    if m.expect == "same" and not same:
        return "FAIL", f"loaded a different result: {first_difference(dg, ref_digest)}"
    return ("loaded_same" if same else "loaded_changed"), ""


# --- drawing a mutation ------------------------------------------------------------------------------------
TREE_KINDS = ("json", "yaml")


def mutate(fmt: Format, root: Path, rng: np.random.Generator) -> Mutation:
    """Apply one seeded mutation to one target of ``fmt`` in the artefact copy ``root``."""
    weights = np.array([t.weight for t in fmt.targets], np.float64)
    for _ in range(50):
        t = fmt.targets[int(rng.choice(len(fmt.targets), p=weights / weights.sum()))]
        path = root / t.path
        ops = _ops(t)
        op = ops[int(rng.integers(len(ops)))]
        try:
            desc, expect = op(t, path, rng)
        except NotApplicable:
            continue
        return Mutation(t.path, desc, t.expect or expect)
    raise RuntimeError(f"{fmt.name}: no applicable mutation found")


def _ops(t: Target) -> list[Callable]:
    generic = [op_truncate, op_bitflip, op_foreign, op_delete]
    special = {"json": [op_tree] * 4, "yaml": [op_tree] * 4, "npz": [op_npz] * 5, "torch": [op_torch] * 4,
               "text": [op_text] * 4, "png": [op_image] * 2, "jpeg": [op_image] * 2, "tiff": [op_image],
               "unused": [op_text]}
    return generic + special.get(t.kind, [])


# generic byte-level mutations -------------------------------------------------------------------------------
_TRUNCATE = {"json": "same", "yaml": "valid", "npz": "same", "png": "same", "jpeg": "same", "torch": "same",
             "tiff": "same", "text": "valid", "unused": "same"}
_FLIP = {"json": "valid", "yaml": "valid", "npz": "same", "png": "same", "jpeg": "valid", "torch": "same",
         "tiff": "valid", "text": "valid", "unused": "same"}


def op_truncate(t: Target, path: Path, rng) -> tuple[str, str]:
    data = _read(path)
    if len(data) < 2:
        raise NotApplicable
    cut = int(rng.integers(0, len(data)))
    path.write_bytes(data[:cut])
    return f"truncate at byte {cut} of {len(data)}", _TRUNCATE[t.kind]


def op_bitflip(t: Target, path: Path, rng) -> tuple[str, str]:
    data = bytearray(_read(path))
    if not data:
        raise NotApplicable
    if rng.random() < 0.7:
        pos = sorted(int(p) for p in rng.integers(0, len(data), int(rng.integers(1, 4))))
        for p in pos:
            data[p] ^= 1 << int(rng.integers(8))
        desc = f"flip bits at bytes {pos} of {len(data)}"
    else:
        p, v = int(rng.integers(len(data))), int(rng.integers(256))
        desc = f"byte {p} of {len(data)}: {data[p]:#04x} -> {v:#04x}"
        data[p] = v
    path.write_bytes(bytes(data))
    return desc, _FLIP[t.kind]


def op_delete(t: Target, path: Path, rng) -> tuple[str, str]:
    if not path.exists():
        raise NotApplicable
    path.unlink()
    return "delete", t.delete


_FOREIGN_OF = {"json": "json", "yaml": "yaml", "npz": "npz", "png": "png", "jpeg": "jpeg", "torch": "torch",
               "tiff": "tiff", "text": "text", "unused": None}


def op_foreign(t: Target, path: Path, rng) -> tuple[str, str]:
    kinds = [k for k in FOREIGN_KINDS if k != _FOREIGN_OF[t.kind]]
    k = kinds[int(rng.integers(len(kinds)))]
    path.write_bytes(foreign_bytes(k))
    return f"foreign file ({k}) under the right name", "same" if t.kind == "unused" else "reject"


FOREIGN_KINDS = ("empty", "png", "jpeg", "json", "yaml", "npz", "torch", "text", "binary", "tiff")
_FOREIGN_CACHE: dict[str, bytes] = {}


def foreign_bytes(kind: str) -> bytes:
    """A small file of ``kind`` that is no satloc artefact (made once per process)."""
    if kind not in _FOREIGN_CACHE:
        _FOREIGN_CACHE[kind] = _make_foreign(kind)
    return _FOREIGN_CACHE[kind]


def _make_foreign(kind: str) -> bytes:
    import cv2

    img = np.zeros((5, 7, 3), np.uint8)
    img[..., 0], img[..., 1], img[..., 2] = 40, 90, 200
    if kind == "empty":
        return b""
    if kind in ("png", "jpeg"):
        ok, buf = cv2.imencode(".png" if kind == "png" else ".jpg", img)
        assert ok
        return buf.tobytes()
    if kind == "json":
        return b'{"format": "something_else", "version": 1, "values": [1, 2, 3]}\n'
    if kind == "yaml":
        return b"name: something_else\nvalues: [1, 2, 3]\nnested: {a: 1}\n"
    if kind == "npz":
        from satloc.persist import header

        buf = io.BytesIO()
        np.savez_compressed(buf, a=np.arange(6.0).reshape(2, 3),
                            __meta__=np.frombuffer(json.dumps(header("something_else")).encode(), np.uint8))
        return buf.getvalue()
    if kind == "torch":
        import torch

        buf = io.BytesIO()
        torch.save({"format": "something_else", "version": 1, "w": torch.zeros(2, 2)}, buf)
        return buf.getvalue()
    if kind == "text":
        return b"this is not the file you are looking for\n1 2 3\n"
    if kind == "binary":
        return np.random.default_rng(12345).integers(0, 256, 200, dtype=np.uint8).tobytes()
    if kind == "tiff":
        import tempfile

        from satloc.geodata.georef import write_geotiff

        with tempfile.TemporaryDirectory() as tmp:
            p = Path(tmp) / "f.tif"
            write_geotiff(p, img, (1.0, 0.0, 500000.0, 0.0, -1.0, 5400000.0), "EPSG:32632")
            return p.read_bytes()
    raise ValueError(kind)


def _read(path: Path) -> bytes:
    if not path.is_file():
        raise NotApplicable
    return path.read_bytes()


# trees (JSON, YAML, torch dicts) --------------------------------------------------------------------------
def tree_nodes(obj: Any, prefix: tuple = (), max_list: int = 3) -> list[tuple]:
    """Paths (tuples of keys and indices) of every node below ``obj``; of a long list only the first
    ``max_list`` and the last element."""
    out = []
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.append(prefix + (k,))
            out += tree_nodes(v, prefix + (k,), max_list)
    elif isinstance(obj, list):
        idx = list(range(len(obj)))
        if len(idx) > max_list + 1:
            idx = idx[:max_list] + idx[-1:]
        for i in idx:
            out.append(prefix + (i,))
            out += tree_nodes(obj[i], prefix + (i,), max_list)
    return out


def tree_get(obj, path):
    for k in path:
        obj = obj[k]
    return obj


def _parent(obj, path):
    return tree_get(obj, path[:-1]), path[-1]


def is_free(t: Target, path: tuple) -> bool:
    """Whether tree path ``path`` lies in free-form content of ``t`` (not validated, not digested)."""
    free = any(path[:len(f)] == tuple(f) for f in t.free)
    bound = any(path[:len(b)] == tuple(b) for b in t.bound)
    return free and not bound


_WRONG = {"str": [7, [1, 2], {"k": 1}, True], "num": ["x", [1, 2], {"k": 1}, True],
          "bool": [7, "yes", [1], {"k": 1}], "list": ["x", 7, {"k": 1}], "dict": ["x", 7, [1, 2]],
          "none": []}  # a null's type is unknown (e.g. int | None): no "wrong" type to put there


def _jtype(v) -> str:
    if v is None:
        return "none"
    if isinstance(v, bool):
        return "bool"
    if isinstance(v, (int, float)):
        return "num"
    if isinstance(v, str):
        return "str"
    if isinstance(v, list):
        return "list"
    if isinstance(v, dict):
        return "dict"
    return "other"


def mutate_tree(tree: Any, t: Target, rng, prefix: tuple = ()) -> tuple[Any, str, str]:
    """One mutation of a JSON-like tree; returns (new tree, description, expectation). ``prefix``: the path of
    ``tree`` in the file (for the free-form rules)."""
    nodes = tree_nodes(tree)
    if not nodes:
        raise NotApplicable
    path = nodes[int(rng.integers(len(nodes)))]
    parent, key = _parent(tree, path)
    v = parent[key]
    free = is_free(t, prefix + path)
    name = ".".join(map(str, prefix + path))
    ops = ["drop", "type", "nan", "inf", "negative", "huge", "zero", "string", "unknown", "null"]
    op = ops[int(rng.integers(len(ops)))]
    if op == "drop":
        if not isinstance(parent, dict):
            raise NotApplicable
        del parent[key]
        return tree, f"drop {name}", "same" if free else "valid"
    if op == "type":
        choices = _WRONG.get(_jtype(v))
        if not choices:
            raise NotApplicable
        new = choices[int(rng.integers(len(choices)))]
        parent[key] = new
        return tree, f"{name}: {_short(v)} -> wrong type {new!r}", "same" if free else "reject"
    if op in ("nan", "inf"):
        if _jtype(v) != "num":
            raise NotApplicable
        new = math.nan if op == "nan" else (math.inf if rng.random() < 0.5 else -math.inf)
        parent[key] = new
        return tree, f"{name}: {_short(v)} -> {new}", "same" if free else "reject"
    if op in ("negative", "huge", "zero"):
        if _jtype(v) != "num":
            raise NotApplicable
        if op == "negative":
            new = -v if v != 0 else -1
        elif op == "huge":
            new = 10 ** 18 if isinstance(v, int) else 1e300
        else:
            new = 0 if isinstance(v, int) else 0.0
        if new == v:
            raise NotApplicable
        parent[key] = new
        return tree, f"{name}: {_short(v)} -> {new!r}", "same" if free else "valid"
    if op == "string":
        if _jtype(v) != "str":
            raise NotApplicable
        choices = ["", "x" * 300, "../" + v, v + "_other", "ünïcødé"]
        new = choices[int(rng.integers(len(choices)))]
        parent[key] = new
        return tree, f"{name}: {_short(v)} -> {_short(new)}", "same" if free else "valid"
    if op == "unknown":
        target = v if isinstance(v, dict) else (parent if isinstance(parent, dict) else None)
        if target is None:
            raise NotApplicable
        target["zz_unknown_key"] = 1
        where = name if target is v else ".".join(map(str, prefix + path[:-1])) or "top level"
        return tree, f"unknown key in {where}", "same"
    if op == "null":
        if v is None:
            raise NotApplicable
        parent[key] = None
        return tree, f"{name}: {_short(v)} -> null", "same" if free else "valid"
    raise AssertionError(op)


def _short(v) -> str:
    r = repr(v)
    return r if len(r) <= 40 else r[:37] + "..."


def op_tree(t: Target, path: Path, rng) -> tuple[str, str]:
    import yaml

    text = _read(path).decode()
    tree = json.loads(text) if t.kind == "json" else yaml.safe_load(text)
    if not isinstance(tree, (dict, list)):
        raise NotApplicable
    tree, desc, expect = mutate_tree(tree, t, rng)
    if t.kind == "json":
        path.write_text(json.dumps(tree, indent=2) + "\n")  # NaN/Infinity as Python's json writes them
    else:
        path.write_text(yaml.safe_dump(tree, sort_keys=False))
    return desc, expect


# npz ------------------------------------------------------------------------------------------------------
def op_npz(t: Target, path: Path, rng) -> tuple[str, str]:
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    keys = [k for k in arrays if k != "__meta__"]
    ops = ["dtype", "length", "ndim", "empty", "nan", "inf", "negative", "huge", "drop", "unknown", "header",
           "header_raw"]
    op = ops[int(rng.integers(len(ops)))]
    if op in ("header", "header_raw"):
        if "__meta__" not in arrays:
            raise NotApplicable
        if op == "header":
            meta = json.loads(arrays["__meta__"].tobytes().decode())
            meta, desc, expect = mutate_tree(meta, t, rng, ("__meta__",))
            arrays["__meta__"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
        else:
            choices = [np.arange(4.0), np.frombuffer(b"\xff\xfe{not json", np.uint8), np.array("text"),
                       np.frombuffer(b'["a", "list"]', np.uint8)]
            j = int(rng.integers(len(choices)))
            arrays["__meta__"] = choices[j]
            desc, expect = f"header replaced by {['floats', 'bad utf-8', 'a string array', 'a JSON list'][j]}", "reject"
        _save_npz_raw(path, arrays)
        return desc, expect
    if op == "unknown":
        arrays["zz_unknown_array"] = np.arange(3)
        _save_npz_raw(path, arrays)
        return "unknown array added", "same"
    if not keys:
        raise NotApplicable
    k = keys[int(rng.integers(len(keys)))]
    a = arrays[k]
    free = k in t.free
    strict = "same" if free else None
    if op == "drop":
        del arrays[k]
        desc, expect = f"drop array {k!r}", strict or ("reject" if k in t.required else "valid")
    elif op == "dtype":
        new = _wrong_dtype(a, rng)
        arrays[k] = new
        same_kind = new.dtype.kind == a.dtype.kind or {new.dtype.kind, a.dtype.kind} <= {"i", "u"}
        desc = f"{k}: dtype {a.dtype} -> {new.dtype}"
        expect = strict or ("valid" if same_kind else "reject")
    elif op == "length":
        if a.ndim == 0 or a.shape[0] < 1:
            raise NotApplicable
        new = a[:-1] if rng.random() < 0.5 else np.concatenate([a, a[-1:]])
        arrays[k] = new
        desc, expect = f"{k}: shape {a.shape} -> {new.shape}", strict or "valid"
    elif op == "ndim":
        new = a.reshape(-1) if a.ndim > 1 else (a[None] if rng.random() < 0.5 else a.reshape(1, -1, 1))
        if a.ndim == 0:
            new = a.reshape(1, 1)
        arrays[k] = new
        desc, expect = f"{k}: shape {a.shape} -> {new.shape}", strict or "reject"
    elif op == "empty":
        if a.size == 0:
            raise NotApplicable
        new = a[:0] if a.ndim else np.zeros(0, a.dtype)
        arrays[k] = new
        desc, expect = f"{k}: shape {a.shape} -> {new.shape} (empty)", strict or "valid"
    else:
        if a.size == 0:
            raise NotApplicable
        new = a.copy()
        flat = new.reshape(-1)
        i = int(rng.integers(flat.size))
        if op in ("nan", "inf"):
            if a.dtype.kind != "f":
                raise NotApplicable
            flat[i] = np.nan if op == "nan" else (np.inf if rng.random() < 0.5 else -np.inf)
            expect = strict or ("valid" if k in t.nan_ok else "reject")
        elif op == "negative":
            if a.dtype.kind not in "fi":
                raise NotApplicable
            flat[i] = -flat[i] if flat[i] != 0 else -1
            expect = strict or "valid"
        else:  # huge
            if a.dtype.kind == "f":
                flat[i] = np.finfo(a.dtype).max / 2
            elif a.dtype.kind in "iu":
                flat[i] = np.iinfo(a.dtype).max
            else:
                raise NotApplicable
            expect = strict or "valid"
        arrays[k] = new
        desc = f"{k}: element {i} {a.reshape(-1)[i]!r} -> {flat[i]!r}"
    _save_npz_raw(path, arrays)
    return desc, expect


def _wrong_dtype(a: np.ndarray, rng) -> np.ndarray:
    kinds = ["U", "c", "b", "O", "f", "i", "M"]
    for _ in range(10):
        k = kinds[int(rng.integers(len(kinds)))]
        if k == a.dtype.kind:
            continue
        if k == "U":
            return a.astype("U12")
        if k == "c":
            return a.astype(np.complex128) if a.dtype.kind in "fiub" else np.zeros(a.shape, np.complex128)
        if k == "b":
            return a.astype(bool) if a.dtype.kind in "fiub" else np.zeros(a.shape, bool)
        if k == "O":
            return a.astype(object)
        if k == "f":
            if a.dtype.kind in "iub":
                return a.astype(np.float64) + 0.5
            return np.zeros(a.shape, np.float64)
        if k == "i":
            if a.dtype.kind in "fb":
                return np.nan_to_num(a).astype(np.int64)
            return np.zeros(a.shape, np.int64)
        if k == "M":
            return np.zeros(a.shape, "datetime64[s]")
    return a.astype("U12")


def _save_npz_raw(path: Path, arrays: dict) -> None:
    with open(path, "wb") as f:
        np.savez_compressed(f, **arrays)  # object arrays are pickled here; the loader must refuse them


# torch trees ----------------------------------------------------------------------------------------------
def op_torch(t: Target, path: Path, rng) -> tuple[str, str]:
    import torch

    obj = torch.load(path, weights_only=True, map_location="cpu")
    if rng.random() < 0.5:
        # a tensor leaf
        leaves = [p for p in tree_nodes(obj, max_list=10**9) if isinstance(tree_get(obj, p), torch.Tensor)]
        if not leaves:
            raise NotApplicable
        p = leaves[int(rng.integers(len(leaves)))]
        parent, key = _parent(obj, p)
        a = parent[key]
        name = ".".join(map(str, p))
        free = is_free(t, p)
        ops = ["nan", "inf", "huge", "dtype", "length", "ndim"]
        op = ops[int(rng.integers(len(ops)))]
        if op in ("nan", "inf", "huge"):
            if not a.is_floating_point() or a.numel() == 0:
                raise NotApplicable
            new = a.clone()
            i = int(rng.integers(new.numel()))
            val = {"nan": math.nan, "inf": math.inf, "huge": float(torch.finfo(a.dtype).max) / 2}[op]
            new.view(-1)[i] = val
            desc, expect = f"{name}: element {i} -> {val}", ("valid" if op == "huge" else "reject")
        elif op == "dtype":
            choices = [torch.int64, torch.bool, torch.complex64, torch.float64, torch.uint8]
            dt = choices[int(rng.integers(len(choices)))]
            if dt == a.dtype:
                raise NotApplicable
            new = a.to(dt)
            same_kind = a.is_floating_point() == new.is_floating_point() and a.is_complex() == new.is_complex() \
                and (a.dtype == torch.bool) == (new.dtype == torch.bool)
            desc, expect = f"{name}: dtype {a.dtype} -> {dt}", ("valid" if same_kind else "reject")
        elif op == "length":
            if a.dim() == 0 or a.shape[0] < 1:
                raise NotApplicable
            new = a[:-1].clone() if rng.random() < 0.5 else torch.cat([a, a[-1:]])
            desc, expect = f"{name}: shape {tuple(a.shape)} -> {tuple(new.shape)}", "valid"
        else:
            new = a.reshape(-1).clone() if a.dim() > 1 else a[None].clone()
            desc, expect = f"{name}: shape {tuple(a.shape)} -> {tuple(new.shape)}", "reject"
        parent[key] = new
        if free:
            expect = "same"
    else:
        obj, desc, expect = mutate_tree(obj, t, rng)
    torch.save(obj, path)
    return desc, expect


# text -----------------------------------------------------------------------------------------------------
_GARBLE = ["abc", "nan", "NaN", "inf", "-inf", "1e999", "0x1F", "1,5", "--1", "½", "1e300", "-1e300", "", "0", "89.9",
           "-1.56", "179.99"]


def op_text(t: Target, path: Path, rng) -> tuple[str, str]:
    data = _read(path)
    try:
        text = data.decode()
    except UnicodeDecodeError:
        raise NotApplicable from None
    lines = text.splitlines()
    nonempty = [i for i, ln in enumerate(lines) if ln.strip()]
    if not nonempty:
        raise NotApplicable
    ops = ["drop_line", "dup_line", "swap_lines", "garble", "garble", "drop_column", "add_column", "negate",
           "crlf", "blank_lines"]
    op = ops[int(rng.integers(len(ops)))]
    default = "same" if t.kind == "unused" else "valid"
    i = nonempty[int(rng.integers(len(nonempty)))]
    if op == "drop_line":
        del lines[i]
        desc = f"drop line {i + 1}"
    elif op == "dup_line":
        lines.insert(i, lines[i])
        desc = f"duplicate line {i + 1}"
    elif op == "swap_lines":
        if len(nonempty) < 2:
            raise NotApplicable
        j = nonempty[int(rng.integers(len(nonempty)))]
        if lines[i] == lines[j]:
            raise NotApplicable
        lines[i], lines[j] = lines[j], lines[i]
        desc = f"swap lines {i + 1} and {j + 1}"
    elif op == "crlf":
        path.write_bytes(text.replace("\r\n", "\n").replace("\n", "\r\n").encode())
        return "CRLF line endings", "same"
    elif op == "blank_lines":
        lines.insert(i, "")
        desc = f"blank line before line {i + 1}"
    else:
        toks = _tokens(lines[i])
        if not toks:
            raise NotApplicable
        a, b = toks[int(rng.integers(len(toks)))]
        tok = lines[i][a:b]
        if op == "garble":
            new = _GARBLE[int(rng.integers(len(_GARBLE)))]
            if new == tok:
                raise NotApplicable
            lines[i] = lines[i][:a] + new + lines[i][b:]
            desc = f"line {i + 1}: token {tok!r} -> {new!r}"
        elif op == "drop_column":
            lines[i] = (lines[i][:a] + lines[i][b:]).replace("  ", " ", 1)
            desc = f"line {i + 1}: drop token {tok!r}"
        elif op == "add_column":
            lines[i] = lines[i][:b] + " 1.5" + lines[i][b:]
            desc = f"line {i + 1}: extra token after {tok!r}"
        else:  # negate a number
            try:
                v = float(tok.strip("[]"))
            except ValueError:
                raise NotApplicable from None
            if v == 0:
                raise NotApplicable
            new = tok[1:] if tok.startswith("-") else "-" + tok
            lines[i] = lines[i][:a] + new + lines[i][b:]
            desc = f"line {i + 1}: {tok!r} -> {new!r}"
    path.write_text("\n".join(lines) + ("\n" if text.endswith("\n") else ""))
    return desc, default


def _tokens(line: str) -> list[tuple[int, int]]:
    """(start, end) of the whitespace-, '='- and bracket-separated tokens of a line."""
    out, start = [], None
    for j, ch in enumerate(line + " "):
        sep = ch.isspace() or ch in "=[],:"
        if sep and start is not None:
            out.append((start, j))
            start = None
        elif not sep and start is None:
            start = j
    return out


# images ---------------------------------------------------------------------------------------------------
def op_image(t: Target, path: Path, rng) -> tuple[str, str]:
    import cv2

    if t.kind == "tiff":
        return _op_tiff(t, path, rng)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise NotApplicable
    ops = ["resize", "channels", "depth"]
    op = ops[int(rng.integers(len(ops)))]
    if op == "resize":
        h, w = img.shape[:2]
        nw, nh = max(1, w + int(rng.choice([-3, -1, 1, 5]))), max(1, h + int(rng.choice([-2, 0, 1, 4])))
        new = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_NEAREST)
        desc = f"resize {w}x{h} -> {nw}x{nh}"
    elif op == "channels":
        if img.ndim == 3:
            new = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
            desc = "colour -> grey"
        else:
            new = cv2.merge([img, img, img])
            desc = "grey -> colour"
    else:
        if t.kind == "jpeg":
            raise NotApplicable
        if img.dtype == np.uint8:
            new = img.astype(np.uint16) * 257
            desc = "8-bit -> 16-bit"
        else:
            new = (img // 257).astype(np.uint8)
            desc = "16-bit -> 8-bit"
    ext = ".jpg" if t.kind == "jpeg" else ".png"
    ok, buf = cv2.imencode(ext, new)
    assert ok
    path.write_bytes(buf.tobytes())
    return desc, t.image.get(op, "valid")


def _op_tiff(t: Target, path: Path, rng) -> tuple[str, str]:
    """A GeoTIFF rewritten with one property changed: no CRS, float or 11-bit bands (with a nodata value), one
    or two bands, a degenerate transform."""
    import rasterio

    with rasterio.open(path) as ds:
        arr, profile = ds.read(), dict(ds.profile)
    ops = ["no_crs", "float", "degenerate", "one_band", "two_bands", "eleven_bit"]
    op = ops[int(rng.integers(len(ops)))]
    expect = "valid"
    if op == "no_crs":
        profile.pop("crs", None)
        desc, expect = "GeoTIFF without a CRS", "reject"
    elif op == "float":
        arr = arr.astype(np.float32) / 255
        arr[:, :3, :3] = np.nan
        profile["dtype"] = "float32"
        desc = "float32 bands in 0..1 with NaN"
    elif op == "eleven_bit":
        arr = arr.astype(np.uint16) * 8
        profile.update(dtype="uint16", nodata=0)
        desc = "11-bit samples in 16-bit bands, nodata 0"
    elif op == "degenerate":
        from affine import Affine

        tr = profile["transform"]
        profile["transform"] = Affine(tr.a, tr.b, tr.c, tr.d, 0.0, tr.f) if rng.random() < 0.5 else \
            Affine(0.0, 0.0, tr.c, 0.0, 0.0, tr.f)
        desc, expect = "degenerate geotransform (pixels without area)", "reject"
    elif op == "one_band":
        arr = arr[:1]
        profile.update(count=1, photometric="MINISBLACK")
        desc = "one (grey) band"
    else:
        arr = arr[:2]
        profile.update(count=2, photometric="MINISBLACK")
        profile.pop("alpha", None)
        desc = "two bands"
    profile.pop("blockxsize", None), profile.pop("blockysize", None), profile.pop("tiled", None)
    with rasterio.Env(GDAL_PAM_ENABLED="NO"), rasterio.open(path, "w", **profile) as dst:
        dst.write(arr)
    return desc, expect
