"""Interrupted runs (issue 15, item 4): ``satloc record``, ``satloc build``, ``satloc train-projection`` and the
auto-localizer cache build, killed with SIGINT and SIGKILL.

Each command runs in a subprocess on a tiny scene and is killed at chosen points (when a file appears, or
right after a given function returns: the driver below wraps it to signal its own process) and at seeded
random times. After each kill: no loader takes what is on disk as whole (it raises naming the file, or the
output is absent or marked incomplete); SIGINT exits with status 130 and one line, and leaves no temporary
files; SIGKILL's leftovers are removed by the rerun. A rerun then finishes (or resumes) and gives what an
uninterrupted run gives, array for array. Two processes asking for the same auto-localizer entry at once
both get the same complete entry, built once.
"""
from __future__ import annotations

import glob
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from test_process import TINY_SCENE, communicate_or_kill

from satloc import ConfigError, FormatError
from satloc.features.projection import Projections
from satloc.localizers.database import LocalizerConfig
from satloc.persist import _host_tag, remove_stale_temps
from satloc.pipeline import load_localizer, train_projection
from satloc_env.envs import auto_localizer as autoloc
from satloc_env.envs.record import load_recording

FRAMES = 12                     # per pass: the database pass spans about 18 m, the query pass 110 m of the loop
BUILD_CFG = "features: rgb\n"
PROJ_CFG = "max_epochs: 3\nmax_anchors: 4000\n"
INTERRUPTED = "satloc: interrupted; run the command again to resume or start over"
TIMEOUT = 180                   # a hung child fails the test instead of hanging the suite

DRIVER = '''\
"""driver.py [--started FILE] [--at module:Qual.name:N:SIGNAL]... (cli ARGS... | auto SCENE CACHE)"""
import importlib, os, signal, sys
from pathlib import Path

argv = sys.argv[1:]
started, hooks = None, []
while argv[0].startswith("--"):
    if argv[0] == "--started":
        started = argv[1]
    else:
        hooks.append(argv[1])
    argv = argv[2:]


def hook(spec):  # after the N-th return of module.Qual.name, send SIGNAL to this process
    mod, qual, n, sig = spec.split(":")
    owner = importlib.import_module(mod)
    *path, name = qual.split(".")
    for p in path:
        owner = getattr(owner, p)
    orig, calls = getattr(owner, name), [0]

    def wrapper(*a, **k):
        r = orig(*a, **k)
        calls[0] += 1
        if calls[0] == int(n):
            os.kill(os.getpid(), getattr(signal, sig))
        return r
    setattr(owner, name, wrapper)


for h in hooks:
    hook(h)
if argv[0] == "cli":
    from satloc_env.cli import entry
    if started:
        Path(started).touch()
    entry(argv[1:])
import logging
from satloc.pipeline import BuildConfig
from satloc.features.projection import ProjectionConfig
from satloc_env.envs.auto_localizer import auto_build_dir
logging.basicConfig(level=logging.INFO, format="%(message)s")  # the cache's announcements, without progress bars
if started:
    Path(started).touch()
try:
    entry = auto_build_dir(argv[1], None, "half", progress=False, cache_dir=argv[2], max_frames=FRAMES,
                           build_config=BuildConfig(features="rgb"),
                           projection_config=ProjectionConfig(max_anchors=2000, max_epochs=2))
except KeyboardInterrupt:
    print("interrupted", file=sys.stderr)
    sys.exit(130)
print(entry)
'''.replace("FRAMES", str(FRAMES))


class Run:
    def __init__(self, rc: int, out: str, err: str):
        self.rc, self.out, self.err = rc, out, err

    def __repr__(self) -> str:
        return f"rc {self.rc}\nstdout: {self.out[-2000:]}\nstderr: {self.err[-3000:]}"


def _default_sigint() -> None:
    # a shell's background job (CI's, nohup's) starts with SIGINT ignored, and Python then installs no
    # KeyboardInterrupt handler: give the child the SIGINT of an interactive run
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def start(args: list[str], cwd: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True, cwd=cwd, preexec_fn=_default_sigint)


def finish(p: subprocess.Popen) -> Run:
    out, err = communicate_or_kill(p, TIMEOUT, str(p.args))
    return Run(p.returncode, out, err)


def run(args: list[str], cwd: Path, sig: int | None = None, when: str | None = None, delay: float = 0.0) -> Run:
    """Run ``python args``; with ``sig``: send it once the glob ``when`` (relative to ``cwd``; ``{pid}``: the
    process's id, as in the name of a temporary it writes) matches, then ``delay`` seconds later (or at the end,
    if the process ends first)."""
    p = start(args, cwd)
    if sig is not None:
        t0 = time.monotonic()
        when = when and when.replace("{pid}", str(p.pid))
        while p.poll() is None and when is not None and not glob.glob(str(cwd / when)):
            if time.monotonic() - t0 > TIMEOUT:
                os.killpg(p.pid, signal.SIGKILL)
                pytest.fail(f"{when} never appeared\n{finish(p)}")
            time.sleep(0.005)
        if delay:
            time.sleep(delay)
        if p.poll() is None:
            p.send_signal(sig)
    return finish(p)


def assert_sigint_exit(r: Run) -> None:
    """Status 130, no traceback, one line (the last one on stderr)."""
    assert r.rc == 130, r
    assert "Traceback" not in r.err, r
    lines = [ln for ln in r.err.splitlines() if ln.strip()]
    assert lines and lines[-1] in (INTERRUPTED, "interrupted") and len(lines) <= 3, r


def temps(d: Path) -> list[str]:
    """Hidden names under ``d``: temporaries and set-aside directories (the cache's lock files excepted)."""
    return sorted(str(p.relative_to(d)) for p in d.rglob(".*") if not p.name.endswith(".lock"))


def npz_equal(a: Path, b: Path) -> bool:
    with np.load(a, allow_pickle=False) as x, np.load(b, allow_pickle=False) as y:
        return sorted(x.files) == sorted(y.files) and all(np.array_equal(x[k], y[k]) for k in x.files)


def projections_equal(a: Path, b: Path) -> bool:
    x, y = (torch.load(p, weights_only=True) for p in (a, b))
    return all(torch.equal(x[k], y[k]) for k in ("W_g", "W_s")) and \
        all(x[k] == y[k] for k in ("loss_curve", "val_curve", "best_epoch", "converged"))


def assert_same_tree(got: Path, ref: Path, skip: tuple[str, ...] = ()) -> None:
    """The same files; npz arrays equal, torch files' projections equal, everything else byte for byte."""
    files = lambda d: sorted(str(p.relative_to(d)) for p in d.rglob("*") if p.is_file())  # noqa: E731
    assert files(got) == files(ref)
    for rel in files(ref):
        if Path(rel).name in skip:
            continue
        a, b = got / rel, ref / rel
        if rel.endswith(".npz"):
            assert npz_equal(a, b), rel
        elif rel.endswith(".pt"):
            assert projections_equal(a, b), rel
        else:
            assert a.read_bytes() == b.read_bytes(), rel


def json_without(path: Path, *keys: str) -> dict:
    d = json.loads(path.read_text())
    return {k: v for k, v in d.items() if k not in keys}


# --- fixtures: the uninterrupted runs -------------------------------------------------------------------------
@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    w = tmp_path_factory.mktemp("interrupt")
    (w / "tiny.yaml").write_text(TINY_SCENE)
    (w / "driver.py").write_text(DRIVER)
    (w / "build.yaml").write_text(BUILD_CFG)
    (w / "proj.yaml").write_text(PROJ_CFG)
    return w


def cli(*args: str, at: tuple[str, ...] = ()) -> list[str]:
    """The driver running ``satloc args`` (``at``: its hooks, module:Qual.name:N:SIGNAL)."""
    return ["driver.py", "--started", "started", *[a for h in at for a in ("--at", h)], "cli", *args]


def after_frame(n: int, sig: str) -> str:
    """A hook: ``sig`` right after the ``n``-th frame of the process is written (not when a file shows up: a
    quick pass can end between two looks at the directory)."""
    return f"satloc.sequence:SequenceWriter.add:{n}:{sig}"


RECORD = ("record", "--scene", "tiny.yaml", "--max-frames", str(FRAMES), "--quiet", "--out")


@pytest.fixture(scope="module")
def ref(work) -> Path:
    """record -> build -> train-projection, uninterrupted, in ``work/ref``."""
    for args in ((*RECORD, "ref/rec"),
                 ("build", "--database", "ref/rec/database", "--map", "ref/rec/map", "--out", "ref/build",
                  "--config", "build.yaml", "--quiet"),
                 ("train-projection", "ref/build", "--config", "proj.yaml", "--quiet")):
        r = run(["-m", "satloc_env.cli", *args], work)
        assert r.rc == 0, r
    return work / "ref"


# --- satloc record --------------------------------------------------------------------------------------------
def test_record_interrupted_resumes(work, ref):
    out = "rec1"
    cmd = ["-m", "satloc_env.cli", *RECORD, out]
    # Ctrl-C in the database pass: one line, status 130, no temporary left, the recording marked incomplete
    r = run(cli(*RECORD, out, at=(after_frame(5, "SIGINT"),)), work)
    assert_sigint_exit(r)
    assert temps(work / out) == []
    assert not (work / out / "database").exists()
    with pytest.raises(FormatError, match="recording.json: the recording is incomplete"):
        load_recording(work / out)
    # SIGKILL in the query pass: its temporary directory stays; the finished database pass is kept
    r = run(cli(*RECORD, out, at=(after_frame(FRAMES + 3, "SIGKILL"),)), work)
    assert r.rc == -signal.SIGKILL, r
    assert [t.split(".")[1] for t in temps(work / out)] == ["query"]
    assert not (work / out / "query").exists()
    with pytest.raises(FormatError, match="incomplete \\(database done"):
        load_recording(work / out)
    db_stamp = (work / out / "database" / "sequence.json").stat()
    # killed again at a seeded random time in the query pass (or after it, if it was quicker)
    rng = np.random.default_rng(4)
    r = run(cmd, work, signal.SIGKILL, f"{out}/.query.{{pid}}-*.tmp", delay=float(rng.uniform(0.0, 0.6)))
    assert r.rc in (0, -signal.SIGKILL), r
    try:
        load_recording(work / out)
        complete = True
    except FormatError as e:
        assert "recording.json: the recording is incomplete" in str(e)
        complete = False
    if complete:                    # killed after the recording was marked complete (or not at all): it is whole
        assert_same_tree(work / out, ref / "rec")
    # the rerun resumes at the query pass (a complete recording is recorded again), removes the leftovers and
    # gives the uninterrupted recording
    r = run(cmd, work)
    assert r.rc == 0, r
    assert temps(work / out) == []
    st = (work / out / "database" / "sequence.json").stat()
    if not complete:                # not recorded again
        assert (st.st_ino, st.st_mtime_ns) == (db_stamp.st_ino, db_stamp.st_mtime_ns)
    sm, db, q = load_recording(work / out)
    assert len(db) == len(q) == FRAMES
    assert_same_tree(work / out, ref / "rec")


def test_record_with_another_configuration_starts_over(work, ref):
    """A recording is never a mix of two configurations: rerun with other options into a complete recording
    and killed in its database pass, the earlier passes and map are gone, not kept beside the new ones."""
    out = work / "rec2"
    shutil.copytree(ref / "rec", out)
    load_recording(out)
    cmd = ["-m", "satloc_env.cli", *RECORD[:-2], "--seed", "5", "--quiet", "--out", "rec2"]
    r = run(cli(*cmd[2:], at=(after_frame(3, "SIGKILL"),)), work)
    assert r.rc == -signal.SIGKILL, r
    with pytest.raises(FormatError, match="recording.json: the recording is incomplete"):
        load_recording(out)
    assert not (out / "database").exists() and not (out / "query").exists()
    assert json.loads((out / "recording.json").read_text())["config"]["database"]["seed"] == 5


# --- satloc build ---------------------------------------------------------------------------------------------
def test_build_interrupted(work, ref):
    out = work / "build1"
    shutil.copytree(ref / "build", out)           # a complete build, with projections, is there
    args = ("build", "--database", "ref/rec/database", "--map", "ref/rec/map", "--out", "build1", "--quiet",
            "--config")
    build = cli(*args, "build.yaml")
    # Ctrl-C at a seeded random time: one line, 130; the earlier build is untouched or unmarked, never mixed
    shutil.copytree(out, work / "before")
    (work / "started").unlink(missing_ok=True)
    r = run(build, work, signal.SIGINT, "started", delay=float(np.random.default_rng(7).uniform(0.0, 2.0)))
    if r.rc == 0:       # finished first: a new, complete build (no projections: they belonged to the old one)
        assert not (out / "projections.pt").exists()
        load_localizer(out, LocalizerConfig(mode="go"), cache_table=False)
    else:
        assert_sigint_exit(r)
        assert temps(out) == []
        if (out / "build.json").exists():          # stopped while computing: the earlier build, whole
            assert_same_tree(out, work / "before")
        else:
            with pytest.raises(FormatError, match="build.json: missing: the build .* is incomplete"):
                load_localizer(out, LocalizerConfig(mode="go"), cache_table=False)
    # SIGKILL right after the new dictionary is written, for another grid: no build.json, so nothing loads
    shutil.rmtree(out)
    shutil.copytree(ref / "build", out)
    (work / "grid24.yaml").write_text(BUILD_CFG + "grid: {step_px: 24}\n")
    r = run(cli(*args, "grid24.yaml", at=("satloc.features.dictionary:Dictionary.save:1:SIGKILL",)), work)
    assert r.rc == -signal.SIGKILL, r
    assert not npz_equal(out / "dictionary.npz", ref / "build" / "dictionary.npz")   # the new one is written
    assert not (out / "build.json").exists() and not (out / "projections.pt").exists()
    for mode in ("go", "full"):
        with pytest.raises(FormatError, match=f"{out / 'build.json'}: missing"):
            load_localizer(out, LocalizerConfig(mode=mode), cache_table=False)
    with pytest.raises(FormatError, match="build.json: missing"):   # nor does the next stage start on it
        train_projection(out, progress=False)
    # the rerun builds it whole, as the uninterrupted run did
    r = run(build, work)
    assert r.rc == 0, r
    assert temps(out) == []
    assert npz_equal(out / "dictionary.npz", ref / "build" / "dictionary.npz")
    assert npz_equal(out / "satellite_features.npz", ref / "build" / "satellite_features.npz")
    timing = ("satellite_features_s", "dictionary_s")
    assert json_without(out / "build.json", *timing) == json_without(ref / "build" / "build.json", *timing)


# --- satloc train-projection ----------------------------------------------------------------------------------
def test_train_projection_interrupted(work, ref):
    out = work / "build2"
    out.mkdir()
    for f in ("build.json", "dictionary.npz", "satellite_features.npz"):
        shutil.copy2(ref / "build" / f, out / f)
    args = ("train-projection", "build2", "--config", "proj.yaml", "--quiet")
    # Ctrl-C in the second epoch (after the 5th batch loss): one line, 130, nothing written, no projections
    r = run(cli(*args, at=("satloc.features.projection:ranking_loss:5:SIGINT",)), work)
    assert_sigint_exit(r)
    assert temps(out) == [] and sorted(p.name for p in out.iterdir()) == ["build.json", "dictionary.npz",
                                                                           "satellite_features.npz"]
    with pytest.raises(ConfigError, match="no projections.pt"):
        load_localizer(out, LocalizerConfig(mode="full"), cache_table=False)
    # SIGKILL right after projections.pt is written: it is whole (the uninterrupted run's); projection.json,
    # which describes it, is not there yet (an earlier one, for other projections, was removed first)
    shutil.copy2(ref / "build" / "projection.json", out / "projection.json")
    r = run(cli(*args, at=("satloc.features.projection:Projections.save:1:SIGKILL",)), work)
    assert r.rc == -signal.SIGKILL, r
    assert projections_equal(out / "projections.pt", ref / "build" / "projections.pt")
    assert not (out / "projection.json").exists()
    # the rerun: the uninterrupted run's projections and summary, no temporaries
    r = run(cli(*args), work)
    assert r.rc == 0, r
    assert temps(out) == []
    assert projections_equal(out / "projections.pt", ref / "build" / "projections.pt")
    assert json_without(out / "projection.json", "seconds") == \
        json_without(ref / "build" / "projection.json", "seconds")
    assert Projections.load(out / "projections.pt").W_g.shape[0] > 0


# --- the auto-localizer cache ---------------------------------------------------------------------------------
def auto(cache: str, *hooks: str) -> list[str]:
    return ["driver.py", "--started", "started", *[a for h in hooks for a in ("--at", h)], "auto", "tiny.yaml",
            cache]


@pytest.fixture(scope="module")
def ref_entry(work) -> Path:
    r = run(auto("cache_ref"), work)
    assert r.rc == 0, r
    return Path(r.out.strip()) if Path(r.out.strip()).is_absolute() else work / r.out.strip()


def test_auto_cache_interrupted_then_built_once_by_two_processes(work, ref_entry):
    cache = work / "cache1"
    entry = cache / ref_entry.name
    # Ctrl-C while recording the database pass: the temporary directory goes, the entry does not appear
    r = run(auto("cache1", after_frame(4, "SIGINT")), work)
    assert_sigint_exit(r)
    assert temps(cache) == [] and not entry.exists()
    # SIGKILL after the dictionary is built (before the projections): the temporary directory stays behind;
    # no entry, so nothing takes it for a cache hit
    r = run(auto("cache1", "satloc.pipeline:build:1:SIGKILL"), work)
    assert r.rc == -signal.SIGKILL, r
    left = temps(cache)
    assert len(left) >= 1 and all(t.startswith(f".{entry.name}.") and ".tmp" in t for t in left)
    assert not entry.exists() and not autoloc.is_complete(entry)
    # two processes at once: one builds (removing the leftover), the other waits for it; both get the entry
    ps = [start(auto("cache1"), work) for _ in range(2)]
    runs = [finish(p) for p in ps]
    for r in runs:
        assert r.rc == 0, r
        assert Path(r.out.strip()).name == entry.name, r
    built = sum("building the localizer for scene 'tiny'" in r.err for r in runs)
    assert built == 1, runs
    assert any("removing the leftover of an interrupted build" in r.err for r in runs), runs
    assert temps(cache) == []
    assert autoloc.is_complete(entry)
    assert_same_tree(entry, ref_entry, skip=("autoloc.json", "projection.json", "build.json"))
    assert autoloc.describe_entry(entry) == autoloc.describe_entry(ref_entry)
    timing = ("satellite_features_s", "dictionary_s", "database", "map")  # timings; paths inside the temporary
    assert json_without(entry / "build.json", *timing) == json_without(ref_entry / "build.json", *timing)
    load_localizer(entry, LocalizerConfig(mode="np"), cache_table=False)


# --- the writers' cleanup of leftovers ------------------------------------------------------------------------
def test_only_leftovers_of_dead_processes_on_this_host_are_removed(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True,
                          check=True)
    pid, host = int(dead.stdout), _host_tag()
    names = {f".x.npz.{pid}-{host}.ab_1.tmp.npz": False,       # a dead process's file: removed
             f".x.npz.{pid}-{host}.cd2.old": False,            # a dead process's set-aside copy: removed
             f".x.npz.{os.getpid()}-{host}.ef3.tmp.npz": True,  # a live process's (this one's): kept
             f".x.npz.{pid}-ffffff.gh4.tmp.npz": host != "ffffff",  # another host's: kept
             ".x.npz.ij5.tmp": True,                           # no owner in the name: kept
             f".y.npz.{pid}-{host}.kl6.tmp": True}             # another file's: kept
    for n in names:
        (tmp_path / n).mkdir() if n.endswith(".old") else (tmp_path / n).write_text("partial")
    removed = remove_stale_temps(tmp_path / "x.npz")
    assert sorted(p.name for p in removed) == sorted(n for n, keep in names.items() if not keep)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(n for n, keep in names.items() if keep)
