"""Process safety, cross-process determinism and the import graph (issue 15, items 1, 2 and 7).

- A process that has rendered and then forks must fail at once with a message naming ``spawn`` (the GL driver's
  threads are not copied by fork; rendering in the child would hang). ``spawn`` works, and so does ``fork``
  before the parent's first render. Scripts run in subprocesses with a timeout, so a regression fails the
  test instead of hanging the suite.
- torch in a forked child of a process that ran torch on several threads must not hang.
- Renders are identical in two fresh processes (different ``PYTHONHASHSEED``; the second one also iterates
  pyrender's node sets in reverse, as another memory layout may), including a frame of the FCN's training
  set that differed between processes before the fix. The cause (equally near meshes drawn in the order of
  a set ordered by address) is also tested directly, in process, on two coplanar quads.
- ``satloc`` and ``satloc_env`` import each other in one direction only, and ``satloc`` never imports
  ``satloc_env``.
"""
from __future__ import annotations

import ast
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("satloc", "satloc_env")

# A one-block scene (84 m x 84 m): loads in about a second.
TINY_SCENE = """\
name: tiny
seed: 3
generator: {type: grid, style: city, blocks: [1, 1], pitch_m: 60, road_width_m: 12, sidewalk_m: 3, margin_m: 12}
meters_per_pixel: 0.4
ground_mpp: 0.2
routes:
  main:
    waypoints: [[12, 12], [72, 12], [72, 72], [12, 72]]
    closed: true
database_route: main
query_route: main
knobs: {aliasing: 0.0, occlusion: 0.0, appearance: 0.0}
"""


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("scene") / "tiny.yaml"
    p.write_text(TINY_SCENE)
    return p


def communicate_or_kill(proc: subprocess.Popen, timeout: float, what: str) -> tuple[str, str]:
    """``proc``'s output; past ``timeout`` kill its whole process group (workers included) and fail."""
    try:
        return proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        pytest.fail(f"{what} did not end within {timeout} s (hung?)\n{out}\n{err[-3000:]}")


def run_script(path: Path, args: list[str], timeout: float) -> subprocess.CompletedProcess:
    """Run ``python path args`` in a session of its own; on timeout kill the whole group (workers included)
    and fail."""
    proc = subprocess.Popen([sys.executable, str(path), *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True, cwd=path.parent)
    out, err = communicate_or_kill(proc, timeout, f"{path.name} {args}")
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


# --- 1. fork after rendering --------------------------------------------------------------------------------
VEC_SCRIPT = """\
import sys

import numpy as np
import gymnasium as gym

import satloc_env  # noqa: F401


def main():
    scene, context, render_first = sys.argv[1], sys.argv[2], sys.argv[3] == "1"
    kw = dict(scene=scene, localizer=None)
    if render_first:
        env = gym.make("satloc/SatLoc-v0", **kw)
        ref, _ = env.reset(seed=3)
    vec = gym.make_vec("satloc/SatLoc-v0", 2, vectorization_mode="async", vector_kwargs={"context": context}, **kw)
    try:
        first, _ = vec.reset(seed=3)                 # worker 0 gets seed 3
        obs, *_ = vec.step(np.array([[5.0, 0.0], [5.0, 0.0]], np.float32))
    finally:
        vec.close()
    if render_first:
        env.close()
        assert np.array_equal(first["left"][0], ref["left"])   # the worker renders what the parent rendered
    assert obs["left"].shape[0] == 2 and obs["left"].std() > 5
    print("OK", context, obs["left"].shape)


if __name__ == "__main__":
    main()
"""


@pytest.fixture(scope="module")
def vec_script(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("scripts") / "vec.py"
    p.write_text(VEC_SCRIPT)
    return p


def test_fork_after_render_fails_fast_with_the_remedy(vec_script, tiny_scene):
    r = run_script(vec_script, [str(tiny_scene), "fork", "1"], timeout=120)
    assert r.returncode != 0, r.stdout
    assert "GLForkError" in r.stderr and "forked from process" in r.stderr, r.stderr[-3000:]
    assert "vector_kwargs={\"context\": \"spawn\"}" in r.stderr


def test_spawn_after_render_works(vec_script, tiny_scene):
    r = run_script(vec_script, [str(tiny_scene), "spawn", "1"], timeout=180)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "OK spawn" in r.stdout


def test_fork_before_any_render_works(vec_script, tiny_scene):
    r = run_script(vec_script, [str(tiny_scene), "fork", "0"], timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "OK fork" in r.stdout


def test_gl_entry_points_refuse_in_a_forked_process(monkeypatch):
    """In process: pretend the GL context was created by another process (what a fork child sees)."""
    from satloc.geometry import Pose2, StereoCamera
    from satloc_env.render import gl as _gl
    from satloc_env.render.stereo import StereoRenderer

    r = _gl.MultiViewOffscreenRenderer(16, 16)           # a context of this process
    assert _gl._gl_pid == os.getpid()
    monkeypatch.setattr(_gl, "_gl_pid", -1)
    with pytest.raises(_gl.GLForkError, match="spawn"):
        _gl.check_process()
    with pytest.raises(_gl.GLForkError):
        _gl.MultiViewOffscreenRenderer(16, 16)
    world = type("W", (), {"chunks": [], "sky_rgb": (1, 2, 3)})()
    cam = StereoCamera(width=32, height=16, fx=20, fy=20, cx=16, cy=8, baseline=0.5)
    with pytest.raises(_gl.GLForkError):
        StereoRenderer(world, cam).render(Pose2())
    # deleting a renderer inherited through fork makes no GL/EGL call and leaves nothing for __del__ to do
    platform = r._platform
    display, context = platform._egl_display, platform._egl_context
    monkeypatch.setattr(_gl, "GL", None)                # any GL call from _gl would now raise
    r.delete()
    assert r._platform is None and r._renderer is None
    assert platform._egl_display is None and platform._egl_context is None
    monkeypatch.undo()
    from OpenGL import EGL

    EGL.eglDestroyContext(display, context)              # this process did create it: free it


# --- torch in a forked child -----------------------------------------------------------------------------
TORCH_FORK_SCRIPT = """\
import multiprocessing as mp

import torch

from satloc.features.fcn import SegEdgeNet

torch.set_num_threads(2)                 # the parent's OpenMP pool has two threads, whatever the machine
net = SegEdgeNet().eval()
x = torch.rand(1, 3, 128, 384)
with torch.inference_mode():
    net(x)


def child(q):
    with torch.inference_mode():
        q.put((torch.get_num_threads(), tuple(net(x).shape)))


if __name__ == "__main__":
    ctx = mp.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=child, args=(q,))
    p.start()
    print("CHILD", q.get(timeout=60))
    p.join(10)
"""


def test_torch_in_a_forked_child_does_not_hang(tmp_path):
    p = tmp_path / "torch_fork.py"
    p.write_text(TORCH_FORK_SCRIPT)
    r = run_script(p, [], timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "CHILD (1, (1, 12, 128, 384))" in r.stdout


# --- 2. cross-process determinism ----------------------------------------------------------------------------
RENDER_SCRIPT = """\
import sys

import numpy as np
import gymnasium as gym

import satloc_env  # noqa: F401
from satloc_env.render.gl import pyrender


def main():
    scene, out, reverse = sys.argv[1], sys.argv[2], sys.argv[3] == "1"
    if reverse:
        # pyrender's set of mesh nodes iterates in an order that follows memory addresses, i.e. differs from
        # process to process; this process takes the reverse of its own order, so that the two processes
        # surely see different orders
        nodes = pyrender.Scene.mesh_nodes.fget
        pyrender.Scene.mesh_nodes = property(lambda self: list(nodes(self))[::-1])
    frames = {}
    for name, kw, episodes in (
            ("tiny", dict(scene=scene, aliasing=0.5), [(s, dict(occlusion=0.9, appearance=0.5)) for s in (0, 1, 2)]),
            # a frame of the FCN's training set that differed between processes before the fix
            ("city", dict(scene="city", aliasing=0.5, dt=0.25),
             [(1357791134, dict(occlusion=0.5533027156665171, appearance=0.6599293106688717,
                                lane_offset_m=-1.8611956529460563))])):
        env = gym.make("satloc/SatLoc-v0", labels=True, depth=True, random_start=True, localizer=None, **kw)
        for seed, options in episodes:
            obs, _ = env.reset(seed=seed, options=options)
            for i in range(9 if name == "tiny" else 1):
                for k in ("left", "right", "labels", "depth"):
                    frames[f"{name}/{seed}/{i}/{k}"] = obs[k]
                obs, *_ = env.step(env.unwrapped.autopilot_action())
        env.close()
    np.savez(out, **frames)


if __name__ == "__main__":
    main()
"""


def test_renders_are_identical_across_processes(tmp_path, tiny_scene):
    p = tmp_path / "render.py"
    p.write_text(RENDER_SCRIPT)
    procs = []
    for hashseed, reverse in (("1", "0"), ("2", "1")):
        out = tmp_path / f"frames{hashseed}.npz"
        procs.append((out, subprocess.Popen([sys.executable, str(p), str(tiny_scene), str(out), reverse],
                                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                            start_new_session=True, cwd=tmp_path,
                                            env={**os.environ, "PYTHONHASHSEED": hashseed})))
    for out, proc in procs:
        try:
            _, err = proc.communicate(timeout=300)
        except subprocess.TimeoutExpired:
            for _, q in procs:
                os.killpg(q.pid, signal.SIGKILL)
            pytest.fail("rendering subprocess hung")
        assert proc.returncode == 0, err[-3000:]
    a, b = (np.load(out) for out, _ in procs)
    assert sorted(a.files) == sorted(b.files) and len(a.files) == 4 * (3 * 9 + 1)
    differing = [k for k in a.files if not np.array_equal(a[k], b[k])]
    assert not differing, f"{len(differing)} of {len(a.files)} arrays differ between processes: {differing[:8]}"


def test_draw_order_of_equally_near_meshes_does_not_depend_on_set_order(monkeypatch):
    """Two coplanar quads in different meshes, equally far from the camera: the image must not depend on the
    order in which pyrender's node set yields them (it follows memory addresses: it differs between
    processes). The node named first is drawn first and wins the depth tie."""
    from satloc_env.render.gl import MultiViewOffscreenRenderer, pyrender

    scene = pyrender.Scene(bg_color=np.zeros(4))
    quad = dict(positions=np.array([[-5, -5, -4], [5, -5, -4], [5, 5, -4], [-5, 5, -4]], np.float32),
                texcoord_0=np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32),
                indices=np.array([[0, 1, 2], [0, 2, 3]], np.uint32))
    for name, colour in (("b-blue", (0, 0, 255)), ("a-red", (255, 0, 0))):
        tex = pyrender.Texture(source=np.full((4, 4, 3), colour, np.uint8), source_channels="RGB")
        mat = pyrender.MetallicRoughnessMaterial(baseColorFactor=np.ones(4), baseColorTexture=tex)
        scene.add(pyrender.Mesh([pyrender.Primitive(material=mat, **quad)]), name=name)
    cam = scene.add(pyrender.IntrinsicsCamera(20, 20, 16, 16, znear=0.1, zfar=50), name="cam")
    nodes = list(pyrender.Scene.mesh_nodes.fget(scene))
    renderer = MultiViewOffscreenRenderer(32, 32)
    images = []
    try:
        for order in (nodes, nodes[::-1]):
            monkeypatch.setattr(pyrender.Scene, "mesh_nodes", property(lambda self, o=order: list(o)))
            images.append(renderer.render_views(scene, [cam], color="rgb", depth=False)[0]["color"])
    finally:
        renderer.delete()
    assert np.array_equal(images[0], images[1])
    assert tuple(images[0][16, 16]) == (255, 0, 0)          # "a-red" is drawn first and kept


# --- 7. import graph ----------------------------------------------------------------------------------------
def _modules(root: Path, packages: tuple[str, ...]) -> dict[str, Path]:
    mods = {}
    for pkg in packages:
        for path in sorted((root / pkg).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join(parts)] = path
    return mods


def import_graph(root: Path = ROOT, packages: tuple[str, ...] = PACKAGES) -> dict[str, set[str]]:
    """module -> the modules of ``packages`` it imports anywhere in its source (top level, in functions, under
    ``TYPE_CHECKING``): ``from a import b`` counts as importing ``a.b`` where that is a module, else ``a``."""
    mods = _modules(root, packages)

    def owner(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {m: set() for m in mods}
    for mod, path in mods.items():
        package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[:len(package.split(".")) - node.level + 1]
                    src = ".".join(base + ([node.module] if node.module else []))
                else:
                    src = node.module or ""
                targets = [f"{src}.{a.name}" if f"{src}.{a.name}" in mods else src for a in node.names]
            for t in targets:
                o = owner(t)
                if o is not None and o != mod:
                    graph[mod].add(o)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_import_graph_is_acyclic_and_satloc_stands_alone():
    g = import_graph()
    # the graph sees the imports it must see (so that an empty graph cannot pass)
    assert "satloc.features.fcn" in g["satloc.features.pixelwise"] and "satloc.features.extractor" in g["satloc.features.fcn"]
    assert {"satloc_env.envs.auto_localizer", "satloc_env.render.stereo"} <= g["satloc_env.envs.drive"]
    assert "satloc_env.envs.record" in g["satloc_env.envs.auto_localizer"]
    assert "satloc_env.envs.drive" in g["satloc_env.envs"] and "satloc_env.envs" in g["satloc_env"]
    assert not cycles(g), cycles(g)
    into_env = {m: sorted(t for t in ts if t.split(".")[0] == "satloc_env")
                for m, ts in g.items() if m.split(".")[0] == "satloc"}
    assert not {m: t for m, t in into_env.items() if t}


def test_graph_sees_deferred_and_relative_imports(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("from .a import f\n")
    (pkg / "a.py").write_text("import os\n\ndef f():\n    from .sub import c\n    return c\n")
    (pkg / "b.py").write_text("from pkg.a import f\n")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "sub" / "c.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from ..b import f\n")
    g = import_graph(tmp_path, ("pkg",))
    assert g == {"pkg": {"pkg.a"}, "pkg.a": {"pkg.sub.c"}, "pkg.b": {"pkg.a"}, "pkg.sub": set(),
                 "pkg.sub.c": {"pkg.b"}}
    assert cycles(g) == [["pkg.a", "pkg.b", "pkg.sub.c"]]


def test_recorders_make_the_registered_environment():
    import satloc_env
    from satloc_env.envs.drive import SatLocEnv
    from satloc_env.envs.record import ENV_ID, make_env

    assert ENV_ID == satloc_env.ENV_ID
    env = make_env(scene="city", localizer=None)
    try:
        assert type(env) is SatLocEnv
    finally:
        env.close()
