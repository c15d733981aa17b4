"""The one entry point to pyrender / OpenGL for the simulator.

Import pyrender only through this module (``from satloc_env.render.gl import pyrender``), and only lazily, inside the
function or class that needs it: importing this module selects the OpenGL platform and patches pyrender, and
``import satloc_env`` must stay cheap and create no GL context (a process that has created one cannot safely
``fork``).

What importing it does:

* **Platform.** Sets ``PYOPENGL_PLATFORM=egl`` unless the user set it. PyOpenGL reads the variable once, at
  its own first import, so this must happen before anything imports ``OpenGL`` or ``pyrender``. EGL on Mesa's
  llvmpipe renders headless without a display server.
* **Headless import.** pyrender's package ``__init__`` imports its interactive viewer, a
  ``pyglet.window.Window`` subclass; on Linux, pyglet's window module loads the X11 client libraries, so on a
  machine without them ``import pyrender`` failed (``XRenderFindVisualFormat``) before any EGL context existed.
  When the platform is ``egl`` or ``osmesa`` and pyrender has not been imported yet, this module registers a
  placeholder for ``pyrender.viewer`` before importing pyrender, so the offscreen path never imports pyglet. The
  placeholder's ``Viewer`` raises :class:`ViewerUnavailableError` saying what to do instead (import pyrender
  before ``satloc_env.render.gl``, with a display, to get the real viewer). If pyrender was already imported, it is
  used as it is.
* **Triton before Mesa.** Mesa's llvmpipe links its own LLVM (libLLVM-15 on Debian 12). Triton, which the
  CUDA builds of torch install from the package index (the CPU wheel does not), carries another LLVM; when
  triton's extension is loaded after Mesa's driver, it binds to Mesa's LLVM symbols and the process dies with a
  segmentation fault (measured with torch 2.13.0 + triton 3.7.1 on Python 3.12: torch imports triton lazily,
  at the first ``torch.optim.Adam``, so learning projections after the first render crashed). Loaded in the
  other order both work, so this module imports triton first when it is installed (0.2 s).
* **The fork.** The project depends on ``pyrender2``, a maintained fork of pyrender 0.1.45 that imports as
  ``pyrender`` (numpy 2's ``np.inf``, PyOpenGL >= 3.1.9 for Python 3.12+). Both distributions install the same
  ``pyrender/`` folder; if the old one's files are in place (``pyrender.__version__`` 0.1.x, which fails on
  numpy 2 and, with its PyOpenGL 3.1.0 pin, on Python 3.12), importing this module raises ImportError with the
  command that repairs the environment.

It also provides :class:`MultiViewOffscreenRenderer`, a ``pyrender.OffscreenRenderer`` that draws several
cameras of a scene in one go, without multisampling, and sets texture filtering (anisotropy, LOD bias) on
uploaded textures.

**Fork safety.** Creating the first context starts the driver's threads (measured on 2 cores: 5 threads, among
them ``llvmpipe-0`` and ``llvmpipe-1``, the rasterizer's, one per core, and Mesa's shader disk-cache thread),
which serve every context of the process until it exits: this module never terminates the EGL display.
``fork`` copies only the thread that calls it, so in a child of a process that has created a context the
driver waits forever for threads that do not exist: measured with Mesa 22.3 llvmpipe, a child creates a
context of its own without complaint, but its first ``glReadPixels`` never returns. That is
how ``gym.make_vec(..., vectorization_mode="async")`` with the default ``fork`` start method hung after the
parent had rendered. The module records the pid that created the first context; every GL entry point
(:class:`MultiViewOffscreenRenderer` creation and :meth:`~MultiViewOffscreenRenderer.render_views`) calls
:func:`check_process` first, which raises :class:`GLForkError` at once in such a child, with the remedy: start
the workers with ``spawn`` or ``forkserver`` (``vector_kwargs={"context": "spawn"}``). Re-creating a context
in the child is not offered: the display, its screen and their locks are shared state copied mid-use.
Deleting a renderer inherited from the parent only drops the references (no GL or EGL call, which could
block). A process that forked before its first render is unaffected.
"""
from __future__ import annotations

import atexit
import ctypes
import importlib
import importlib.util
import itertools
import os
import sys
import weakref
from collections.abc import Iterable, Sequence
from types import ModuleType
from typing import Any, NamedTuple

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")


def _load_triton_before_mesa() -> None:
    """Import triton, if installed and not yet imported, before any GL driver is loaded (see the module notes)."""
    if "triton" in sys.modules or importlib.util.find_spec("triton") is None:
        return
    try:
        importlib.import_module("triton")
    except Exception:   # a broken triton is torch's problem, not the renderer's: torch will report it
        pass


_load_triton_before_mesa()

import cv2  # noqa: E402
import numpy as np  # noqa: E402


class ViewerUnavailableError(RuntimeError):
    """pyrender's interactive viewer was not imported: satloc_env imported pyrender for offscreen rendering."""


class _NoViewer:
    """Stands in for ``pyrender.Viewer`` when pyrender was imported headless by this module."""

    def __init__(self, *args: object, **kwargs: object):
        raise ViewerUnavailableError(
            "pyrender.Viewer is not available: satloc_env imported pyrender for headless rendering "
            f"(PYOPENGL_PLATFORM={os.environ.get('PYOPENGL_PLATFORM')!r}) without its pyglet viewer, so that no "
            "X11 library is needed. To use the interactive viewer, run with a display and `import pyrender` "
            "(with PYOPENGL_PLATFORM unset) before anything imports satloc_env's renderer.")


def _import_pyrender_headless() -> ModuleType:
    """Import pyrender; on a headless platform (egl, osmesa), without its pyglet viewer module."""
    if "pyrender" in sys.modules or os.environ.get("PYOPENGL_PLATFORM") not in ("egl", "osmesa"):
        return importlib.import_module("pyrender")
    placeholder = ModuleType("pyrender.viewer", "satloc_env: pyrender's viewer, not imported (headless).")
    placeholder.Viewer = _NoViewer  # type: ignore[attr-defined]
    sys.modules["pyrender.viewer"] = placeholder
    try:
        return importlib.import_module("pyrender")
    except BaseException:
        if sys.modules.get("pyrender.viewer") is placeholder:
            del sys.modules["pyrender.viewer"]
        raise


pyrender = _import_pyrender_headless()
if tuple(int(p) for p in pyrender.__version__.split(".")[:2]) < (0, 2):
    raise ImportError(
        f"satloc_env needs pyrender2 (a maintained fork of pyrender that imports as `pyrender`), but the files of "
        f"pyrender {pyrender.__version__} are installed at {os.path.dirname(pyrender.__file__)}: it fails on numpy 2 "
        "and, with its PyOpenGL 3.1.0 pin, on Python 3.12. Both distributions install the same `pyrender` folder; "
        "repair the environment with: pip uninstall -y pyrender && pip install --force-reinstall --no-deps "
        "pyrender2 && pip install 'PyOpenGL>=3.1.9'")

from OpenGL import GL  # noqa: E402
from pyrender.constants import ProgramFlags  # noqa: E402

__all__ = ["pyrender", "MultiViewOffscreenRenderer", "ViewGroup", "GLForkError", "ViewerUnavailableError", "check_process",
           "configure_filtering", "gl_info", "max_anisotropy"]

#: GL_TEXTURE_MAX_ANISOTROPY and GL_MAX_TEXTURE_MAX_ANISOTROPY (EXT/ARB_texture_filter_anisotropic, core in 4.6).
_GL_TEXTURE_MAX_ANISOTROPY = 0x84FE
_GL_MAX_TEXTURE_MAX_ANISOTROPY = 0x84FF
_ANISOTROPY_EXTENSIONS = ("GL_EXT_texture_filter_anisotropic", "GL_ARB_texture_filter_anisotropic")
_MIPMAP_FILTERS = (None, GL.GL_LINEAR_MIPMAP_LINEAR, GL.GL_LINEAR_MIPMAP_NEAREST,
                   GL.GL_NEAREST_MIPMAP_LINEAR, GL.GL_NEAREST_MIPMAP_NEAREST)


#: pid of the process that created the first GL context through this module (None: none yet). A forked child
#: inherits the value and so can tell that the driver's threads it would need were left behind.
_gl_pid: int | None = None


class GLForkError(RuntimeError):
    """Raised on GL use in a process forked from one that had already created a GL context."""


def _forked() -> bool:
    """Whether this process is a fork of one that had created a GL context."""
    return _gl_pid is not None and _gl_pid != os.getpid()


def check_process() -> None:
    """Raise :class:`GLForkError` if this process was forked from one that had created a GL context (its
    driver threads are not in this process: rendering would hang). Cheap; called before any GL use."""
    if _forked():
        raise GLForkError(
            f"satloc_env: process {os.getpid()} was forked from process {_gl_pid} after that process had created "
            "an OpenGL context; the GL driver (EGL, Mesa llvmpipe) does not survive fork and rendering here would "
            "hang. Start worker processes with the 'spawn' or 'forkserver' method instead, e.g. "
            "gym.make_vec(\"satloc/SatLoc-v0\", n, vectorization_mode=\"async\", "
            "vector_kwargs={\"context\": \"spawn\"}) or multiprocessing.get_context(\"spawn\"), or fork before "
            "the parent renders anything.")


def _mark_gl_process() -> None:
    global _gl_pid
    if _gl_pid is None:
        _gl_pid = os.getpid()


def max_anisotropy() -> float:
    """Largest anisotropy the current GL context supports; 1.0 when anisotropic filtering is unavailable."""
    n = int(GL.glGetIntegerv(GL.GL_NUM_EXTENSIONS))
    names = {GL.glGetStringi(GL.GL_EXTENSIONS, i).decode() for i in range(n)}
    version = (int(GL.glGetIntegerv(GL.GL_MAJOR_VERSION)), int(GL.glGetIntegerv(GL.GL_MINOR_VERSION)))
    if not names.intersection(_ANISOTROPY_EXTENSIONS) and version < (4, 6):
        return 1.0
    return float(GL.glGetFloatv(_GL_MAX_TEXTURE_MAX_ANISOTROPY))


def gl_info() -> dict[str, str]:
    """``vendor``, ``renderer`` and ``version`` strings of the current GL context (e.g. renderer "llvmpipe
    (LLVM 15.0.6, 256 bits)" for Mesa's software rasterizer, "NVIDIA H100 80GB HBM3/PCIe/SSE2" for the NVIDIA
    driver). Needs the context current."""
    return {key: (GL.glGetString(name) or b"").decode(errors="replace")
            for key, name in (("vendor", GL.GL_VENDOR), ("renderer", GL.GL_RENDERER), ("version", GL.GL_VERSION))}


def configure_filtering(textures: "Iterable[pyrender.Texture]", anisotropy: float, lod_bias: float,
                        mipmaps: bool = True) -> None:
    """Sample the uploaded, mipmapped 2-D ``textures`` bilinearly from the nearest mipmap level
    (``GL_LINEAR_MIPMAP_NEAREST``: on llvmpipe a frame of a detailed street is 5-7 % cheaper than blending two
    levels, and the images differ by 0.24 of 255 on average, 0.4 % of pixels by more than 8), and set their
    level-of-detail bias and ``GL_TEXTURE_MAX_ANISOTROPY`` (clamped to what the context supports; skipped where
    anisotropic filtering is unavailable). With
    ``mipmaps=False`` their level of detail is clamped to 0 (``GL_TEXTURE_MAX_LOD``): the full-resolution level
    is always sampled, bilinearly (the magnification filter), whatever the driver's level selection. Needs the
    context current."""
    textures = [t for t in textures if t._in_context() and t.tex_type == GL.GL_TEXTURE_2D
                and t.sampler.minFilter in _MIPMAP_FILTERS]
    level = min(float(anisotropy), max_anisotropy()) if anisotropy > 1 and textures else 1.0
    for tex in textures:
        tex._bind()
        GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MIN_FILTER, GL.GL_LINEAR_MIPMAP_NEAREST)
        GL.glTexParameterf(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_LOD_BIAS, float(lod_bias))
        if level > 1.0:
            GL.glTexParameterf(GL.GL_TEXTURE_2D, _GL_TEXTURE_MAX_ANISOTROPY, level)
        if not mipmaps:
            GL.glTexParameterf(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAX_LOD, 0.0)
        tex._unbind()


class _MultiViewRenderer(pyrender.Renderer):
    """pyrender's renderer with a lean flat-shaded pass that draws several views into one framebuffer.

    pyrender 0.1.45 always draws offscreen into a 4x multisampled framebuffer and resolves it; the resolved
    depth is one sample's, not the depth at the pixel centre. :meth:`render_views` and :meth:`render_groups`
    instead draw into a single-sample layered framebuffer (RGBA8 colour, 32-bit float depth; view ``k`` in
    layer ``k``) and read each of the two back once. They draw the visible mesh primitives of the scene with
    pyrender's flat (unlit) shader: base colour factor x base colour texture x vertex colour; it supports what
    the simulator uses, i.e. opaque, indexed, textured primitives (no blending, back faces culled). Per
    primitive it issues only the GL calls the flat shader needs, which matters on a software rasterizer where
    pyrender's per-draw bookkeeping costs as much as the drawing.
    """

    def __init__(self, viewport_width: int, viewport_height: int, anisotropy: float = 1.0, lod_bias: float = 0.0,
                 mipmaps: bool = True):
        super().__init__(viewport_width, viewport_height)
        self.anisotropy = float(anisotropy)
        self.lod_bias = float(lod_bias)
        self.mipmaps = bool(mipmaps)
        self._filtered: set = set()
        self._programs: dict = {}
        self._views_fb: tuple[int, int, int] | None = None   # (framebuffer, colour, depth array textures)
        self._views_dims: tuple[int, int, int] = (0, 0, 0)   # width, height, layers
        self._uniform_locs: dict = {}

    def _update_context(self, scene, flags):
        meshes = scene.meshes
        if meshes == self._meshes and not scene.lights:
            return   # the same meshes (materials are never changed in place here) and no lights: nothing to add
        super()._update_context(scene, flags)
        new = self._mesh_textures - self._filtered
        if new:
            configure_filtering(new, self.anisotropy, self.lod_bias, self.mipmaps)
        self._filtered = set(self._mesh_textures)
        self._programs = {p: prog for p, prog in self._programs.items() if p._in_context()}
        live = set(self._programs.values())
        self._uniform_locs = {p: v for p, v in self._uniform_locs.items() if p in live}

    def delete(self):
        if _forked():   # a copy inherited through fork: forget the GL objects, call no GL
            self._filtered, self._programs, self._views_fb = set(), {}, None
            self._meshes, self._mesh_textures, self._shadow_textures = set(), set(), set()
            self._main_fb = self._main_fb_ms = self._shadow_fb = None
            return
        super().delete()
        self._filtered = set()
        self._programs = {}
        self._uniform_locs = {}
        self._delete_views_framebuffer()

    def _delete_views_framebuffer(self) -> None:
        if self._views_fb is not None:
            fb, color, depth = self._views_fb
            GL.glDeleteFramebuffers(1, [fb])
            GL.glDeleteTextures(2, [color, depth])
            self._views_fb = None

    def _views_framebuffer(self, layers: int, bands: int) -> tuple[int, int, int]:
        """The single-sample framebuffer and its two layered textures, (re)allocated to hold ``layers`` layers
        of ``bands`` views each (``bands`` views tall): a 2-D array texture of RGBA8 colour and one of 32-bit
        float depth."""
        w, h = self.viewport_width, self.viewport_height
        if self._views_fb is not None and (self._views_dims[1] != bands * h or self._views_dims[2] < layers):
            self._delete_views_framebuffer()
        if self._views_fb is None:
            color, depth = GL.glGenTextures(2)
            for tex, fmt in ((color, GL.GL_RGBA8), (depth, GL.GL_DEPTH_COMPONENT32F)):
                GL.glBindTexture(GL.GL_TEXTURE_2D_ARRAY, tex)
                GL.glTexStorage3D(GL.GL_TEXTURE_2D_ARRAY, 1, fmt, w, bands * h, layers)
            GL.glBindTexture(GL.GL_TEXTURE_2D_ARRAY, 0)
            self._views_fb = (int(GL.glGenFramebuffers(1)), int(color), int(depth))
            self._views_dims = (w, bands * h, layers)
        return self._views_fb

    def render_views(self, scene: "pyrender.Scene", cameras: Sequence["pyrender.Node"], color: str | None,
                     depth: bool | int) -> list[dict[str, np.ndarray]]:
        """Draw ``scene``'s visible meshes from each camera node (cameras with a finite ``zfar``); per view
        return ``"color"`` (``"rgb"``: H x W x 3 uint8, ``"red"``: H x W uint8 red channel; ``None``: not read)
        and, if ``depth``, ``"depth"`` (H x W float32 metric z-depth, 0 where nothing was drawn). ``depth`` may
        also be an int k: depth is then read for the first k views only. Arrays are C-contiguous.

        The result depends only on the scene, not on the process, when the mesh nodes that the first camera is
        equally far from (e.g. inside several bounding boxes) have distinct names: they are drawn in name
        order (unnamed nodes: in the order of pyrender's node set, which varies between processes)."""
        visible = [node for node in scene.mesh_nodes if node.mesh.is_visible]
        return self.render_groups(scene, [ViewGroup(tuple(cameras), visible)], color, depth)

    def render_groups(self, scene: "pyrender.Scene", groups: Sequence["ViewGroup"], color: str | None,
                      depth: bool | int | str, bg_color: Sequence[float] | None = None) -> list[dict[str, np.ndarray]]:
        """Draw several groups of views in one framebuffer and read it back once: group ``g`` draws the mesh
        nodes ``g.meshes`` (their ``is_visible`` flags are ignored) from each of its cameras. Returns the views of
        all groups in order, as :meth:`render_views` does (``depth`` = k: depth of the first k views of that
        order; ``"first"``: the depth of each group's first view). ``bg_color``: the clear colour (default: the
        scene's).

        Group g is drawn into layer g of the framebuffer's layered (2-D array) colour and depth textures, its
        views in bands from the top of the layer exactly as :meth:`render_views` lays out one group alone
        (view j of n in the j-th band from the top, at window y (n - 1 - j) * height), so that each group is
        drawn exactly as it would be alone: same draw order, same GL state, same window coordinates, so the
        rasterizer's rounding cannot differ (views placed elsewhere, e.g. one car's views further up one tall
        framebuffer, gave colours 2 levels and depths 1 ulp apart). After each view the commands are flushed: a
        software rasterizer (llvmpipe) then draws that view on its threads while this thread issues the next
        view's commands (and does their vertex work); on the 2-core machine a car's step took 4-7 % less."""
        flags = pyrender.RenderFlags.FLAT
        self._update_context(scene, flags)
        w, h = self.viewport_width, self.viewport_height
        bands = max(len(g.cameras) for g in groups)
        fb, color_tex, depth_tex = self._views_framebuffer(len(groups), bands)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, fb)
        GL.glEnable(GL.GL_DEPTH_TEST)
        GL.glDepthMask(GL.GL_TRUE)
        GL.glDepthFunc(GL.GL_LESS)
        GL.glDisable(GL.GL_BLEND)
        GL.glEnable(GL.GL_CULL_FACE)
        GL.glCullFace(GL.GL_BACK)
        GL.glPolygonMode(GL.GL_FRONT_AND_BACK, GL.GL_FILL)
        GL.glActiveTexture(GL.GL_TEXTURE0)
        default_bg = scene.bg_color if bg_color is None else bg_color
        cameras: list = []
        rows: list[tuple[int, int]] = []     # per view: (layer, top row of its band in the upright layer)
        for gi, group in enumerate(groups):
            GL.glFramebufferTextureLayer(GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0, color_tex, 0, gi)
            GL.glFramebufferTextureLayer(GL.GL_FRAMEBUFFER, GL.GL_DEPTH_ATTACHMENT, depth_tex, 0, gi)
            GL.glViewport(0, 0, w, bands * h)
            GL.glClearColor(*(default_bg if group.bg_color is None else group.bg_color))
            GL.glClear(GL.GL_COLOR_BUFFER_BIT | GL.GL_DEPTH_BUFFER_BIT)
            draws = self._draw_list(scene, group)
            n = len(group.cameras)
            for j, cam in enumerate(group.cameras):
                skip = group.hidden[j] if group.hidden else None
                mine = [d for d in draws if id(d[-1]) not in skip] if skip else draws
                GL.glViewport(0, (n - 1 - j) * h, w, h)     # view j in the j-th band from the top
                self._draw(mine, np.linalg.inv(scene.get_pose(cam)), cam.camera.get_projection_matrix(width=w, height=h),
                           group.ranges[j] if group.ranges else None)
                cameras.append(cam)
                rows.append((gi, (bands - n + j) * h))
                GL.glFlush()   # this view is rasterized while the next one's commands are issued
        GL.glBindVertexArray(0)
        GL.glUseProgram(0)
        if depth == "first":
            want = list(itertools.accumulate((len(g.cameras) for g in groups[:-1]), initial=0))
        else:
            want = list(range(len(cameras) if depth is True else min(int(depth), len(cameras))))
        return self._read_views(cameras, rows, len(groups), bands, color, want)

    def _draw_list(self, scene: "pyrender.Scene", group: "ViewGroup") -> list[tuple]:
        """The primitives of ``group.meshes`` in drawing order, each as (sort key..., program, primitive, pose,
        node).

        Front to back (nearest bounding box first, from the group's first camera) so that the depth test
        rejects hidden fragments before they are shaded. Ties (several boxes around the camera: gap 0) are drawn
        in the order of the nodes' names (up to a ``#``: a suffix that tells apart copies of one mesh in a
        batch, see :class:`satloc_env.render.stereo.BatchStereoRenderer`), then of the primitives in their mesh. The
        order decides which of two fragments at exactly the same depth is kept (GL_LESS keeps the first drawn),
        and faces of different meshes at the same depth occur (seen: the episode's occluders and the world chunk
        around the camera, both at gap 0, giving a car's outline one way or the other). pyrender's
        ``scene.mesh_nodes`` is a set of nodes hashed by address, whose order differs from process to process:
        ordering ties by it made a few frames in a thousand differ between processes."""
        eye = scene.get_pose(group.cameras[0])[:3, 3]
        draws = []
        for node in group.meshes:
            pose = scene.get_pose(node)
            lo, hi = node.mesh.bounds
            centre = pose[:3, :3] @ ((lo + hi) / 2) + pose[:3, 3]
            half = np.abs(pose[:3, :3]) @ ((hi - lo) / 2)
            gap = float(np.linalg.norm(np.clip(eye, centre - half, centre + half) - eye))
            name = (node.name or "").split("#", 1)[0]
            for i, prim in enumerate(node.mesh.primitives):
                draws.append((gap, name, i, self._program(prim), prim, pose, node))
        draws.sort(key=lambda d: d[:3])
        return draws

    def _draw(self, draws: list[tuple], view: np.ndarray, proj: np.ndarray, ranges: dict | None = None) -> None:
        """Issue the draw calls of ``draws`` (see :meth:`_draw_list`) with view matrix ``view`` and projection
        ``proj``, setting only the uniforms and bindings that change. Uniform locations are looked up once per
        program (pyrender's ``set_uniform`` queries GL for the location at every call). ``ranges``: per node id,
        the runs of triangles of its one primitive to draw (a :class:`satloc_env.render.stereo.FaceRuns`; see
        :class:`ViewGroup`)."""
        bound, model, factor = None, None, None
        for _, _, _, program, prim, pose, node in draws:
            if program is not bound:
                program._bind()
                loc = self._uniforms(program)
                GL.glUniformMatrix4fv(loc["V"], 1, GL.GL_TRUE, np.asarray(view, np.float32))
                GL.glUniformMatrix4fv(loc["P"], 1, GL.GL_TRUE, np.asarray(proj, np.float32))
                GL.glUniform1i(loc["material.base_color_texture"], 0)
                bound, model, factor = program, None, None
            if model is None or not np.array_equal(model, pose):
                GL.glUniformMatrix4fv(loc["M"], 1, GL.GL_TRUE, np.asarray(pose, np.float32))
                model = pose
            if factor is None or not np.array_equal(factor, prim.material.baseColorFactor):
                factor = prim.material.baseColorFactor
                GL.glUniform4fv(loc["material.base_color_factor"], 1, np.asarray(factor, np.float32))
            prim.material.baseColorTexture._bind()
            prim._bind()
            runs = ranges.get(id(node)) if ranges else None
            if runs is None:
                GL.glDrawElementsInstanced(prim.mode, prim.indices.size, GL.GL_UNSIGNED_INT, None, 1)
            elif len(runs):   # one call for all runs (stereo.FaceRuns: its ctypes arrays, as GL takes them)
                GL.glMultiDrawElements(prim.mode, runs.counts_c, GL.GL_UNSIGNED_INT, runs.starts_c, len(runs))

    def _uniforms(self, program) -> dict[str, int]:
        locs = self._uniform_locs.get(program)
        if locs is None:
            locs = {}
            for name in ("V", "P", "M", "material.base_color_texture", "material.base_color_factor"):
                loc = int(GL.glGetUniformLocation(program._program_id, name))
                if loc == -1:
                    raise ValueError(f"Invalid shader variable: {name}")
                locs[name] = loc
            self._uniform_locs[program] = locs
        return locs

    def _program(self, prim: "pyrender.Primitive") -> "pyrender.shader_program.ShaderProgram":
        """pyrender's flat shader program for ``prim`` (memoised: pyrender rebuilds its cache key per call)."""
        program = self._programs.get(prim)
        if program is None:
            program = self._get_primitive_program(prim, pyrender.RenderFlags.FLAT, ProgramFlags.USE_MATERIAL)
            self._programs[prim] = program
        return program

    def _read_views(self, cameras: Sequence["pyrender.Node"], rows: Sequence[tuple[int, int]], layers: int,
                    bands: int, color: str | None, want: Sequence[int]) -> list[dict[str, np.ndarray]]:
        """Read the layered textures back: one call for the colour of all views and one for the depth of the
        views ``want`` (indices; ``glGetTextureSubImage``, GL 4.5). View k lies in layer ``rows[k][0]``, its
        band starting ``rows[k][1]`` rows from the top of the upright layer (``bands`` views tall)."""
        w, h = self.viewport_width, self.viewport_height
        height = bands * h
        _, color_tex, depth_tex = self._views_fb
        views: list[dict[str, np.ndarray]] = [{} for _ in cameras]
        if color is not None:
            # RGBA is the texture's own layout (the fastest read); GL's rows run bottom-up. Flipping the stack of
            # layers upside down as one image puts layer g, upright, at rows (layers - 1 - g) * height.
            rgba = np.empty((layers * height, w, 4), np.uint8)
            GL.glGetTextureSubImage(color_tex, 0, 0, 0, 0, w, height, layers, GL.GL_RGBA, GL.GL_UNSIGNED_BYTE,
                                    rgba.nbytes, rgba)
            img = _rgba_to(cv2.flip(rgba, 0), color)
            for v, (g, top) in zip(views, rows):
                r0 = (layers - 1 - g) * height + top
                v["color"] = img[r0:r0 + h]
        if want:
            # one read: the rows (from the top) spanned by the wanted bands, in the layers up to the last wanted
            top0 = min(rows[i][1] for i in want)
            top1 = max(rows[i][1] for i in want) + h
            nl = max(rows[i][0] for i in want) + 1
            span = top1 - top0
            d = np.empty((nl * span, w), np.float32)
            GL.glGetTextureSubImage(depth_tex, 0, 0, height - top1, 0, w, span, nl, GL.GL_DEPTH_COMPONENT,
                                    GL.GL_FLOAT, d.nbytes, d)
            d = d[::-1]                                     # layer g upright at rows (nl - 1 - g) * span
            for i in want:
                v, cam, (g, top) = views[i], cameras[i], rows[i]
                near, far = np.float32(cam.camera.znear), np.float32(cam.camera.zfar)
                r0 = (nl - 1 - g) * span + top - top0
                dk = d[r0:r0 + h]
                zk = np.empty((h, w), dtype=np.float32)
                # Window depth dk in [0, 1] to eye z: near * far / ((1 - dk) (far - near) + near). 1 - dk is
                # exact in float32 for dk >= 0.5, which keeps full precision towards the far plane.
                np.subtract(np.float32(1.0), dk, out=zk)
                zk *= far - near
                zk += near
                np.divide(near * far, zk, out=zk)
                zk[dk >= np.float32(1.0)] = 0.0             # the cleared background
                v["depth"] = zk
        return views


#: pixels an OpenCV call converts at most in :func:`_rgba_to`: OpenCV splits an image into stripes of about
#: 2^16 pixels for its thread pool (measured with the pinned OpenCV: a 620 x 94 RGBA image is converted on the
#: calling thread, 620 x 188 wakes the pool)
_SERIAL_PX = 1 << 15


def _rgba_to(rgba: np.ndarray, color: str) -> np.ndarray:
    """The RGB image (``color`` "rgb") or the red channel of the H x W x 4 ``rgba``, converted in bands of rows
    small enough that OpenCV does each on the calling thread. A whole frame wakes OpenCV's thread pool, whose
    worker then spins for about 0.5 ms a call (measured on the 2-core machine: 0.54 ms of CPU a step) on the
    core that llvmpipe's rasterizer needs, and the conversion is no faster for it (0.042 against 0.048 ms for
    two 620 x 188 views). The values are those of one call."""
    h, w = rgba.shape[:2]
    out = np.empty((h, w, 3) if color == "rgb" else (h, w), np.uint8)
    rows = max(1, _SERIAL_PX // max(w, 1))
    for r in range(0, h, rows):
        if color == "rgb":
            cv2.cvtColor(rgba[r:r + rows], cv2.COLOR_RGBA2RGB, dst=out[r:r + rows])
        else:
            cv2.extractChannel(rgba[r:r + rows], 0, dst=out[r:r + rows])
    return out


class ViewGroup(NamedTuple):
    """Views drawn with the same meshes (see :meth:`_MultiViewRenderer.render_groups`): ``cameras``, camera
    nodes of the scene, ``meshes``, the mesh nodes to draw in them (in the order sorted from the first camera),
    ``bg_color``, their background (RGBA in [0, 1]; None: the one of the call), and ``hidden``, per camera the
    ids of nodes it leaves out (wholly outside its view: the image is the same without them), and ``ranges``,
    per camera a dict from node id to the (first triangle, triangles) runs of the node's one primitive to draw
    (the rest wholly outside that view); a node not in it is drawn whole."""

    cameras: tuple
    meshes: Sequence
    bg_color: Sequence[float] | None = None
    hidden: tuple | None = None     # per camera: ids of nodes of ``meshes`` it skips (they cannot be in its view)
    ranges: tuple | None = None     # per camera: {node id: stereo.FaceRuns, the runs of triangles to draw}


#: the renderers not yet deleted; :func:`_delete_live_renderers` frees them at interpreter exit
_LIVE: "weakref.WeakSet[MultiViewOffscreenRenderer]" = weakref.WeakSet()


@atexit.register
def _delete_live_renderers() -> None:
    """Free the GL contexts that a script left open (an environment never closed). Without this, their
    finalizers run while the interpreter tears its modules down, and PyOpenGL prints "Unable to import
    OpenGL.arrays... Python is likely shutting down" and a dict of ctypes classes on the way out."""
    for r in list(_LIVE):
        try:
            r.delete()
        except Exception:   # noqa: BLE001  (at exit nothing can be done about a failing driver)
            pass


def _handle(h: Any) -> int | None:
    """An EGL handle (PyOpenGL's opaque pointer type, or an integer) as an integer; None for a null one."""
    v = h if h is None or isinstance(h, int) else ctypes.cast(h, ctypes.c_void_p).value
    return int(v) if v else None


class MultiViewOffscreenRenderer(pyrender.OffscreenRenderer):
    """A ``pyrender.OffscreenRenderer`` (GL context of its own) whose :meth:`render_views` draws several
    cameras at once without multisampling (see :class:`_MultiViewRenderer`); newly uploaded mipmapped
    textures get ``anisotropy``, ``lod_bias`` and ``mipmaps`` (see :func:`configure_filtering`). ``gl_info`` holds
    the context's vendor, renderer and version strings (see :func:`gl_info`)."""

    def __init__(self, viewport_width: int, viewport_height: int, anisotropy: float = 1.0, lod_bias: float = 0.0,
                 mipmaps: bool = True):
        check_process()
        self._filtering = (float(anisotropy), float(lod_bias), bool(mipmaps))
        self.gl_info: dict[str, str] = {}
        super().__init__(viewport_width, viewport_height)
        _LIVE.add(self)

    def _create(self):
        check_process()
        _mark_gl_process()   # before the driver starts its threads, so that a failure half-way still counts
        super()._create()
        # The stock renderer has allocated no GL objects yet, so swapping it out leaks nothing.
        self._renderer = _MultiViewRenderer(self.viewport_width, self.viewport_height, *self._filtering)
        self.gl_info = gl_info()     # the stock _create leaves the new context current

    def delete(self):
        """Free the GL objects and the context. Unlike pyrender's (and its platform's ``__del__``), this does
        not ``eglTerminate`` the EGL display: the display is shared by every context of the process, so
        terminating it breaks the other renderers still alive. (pyrender's ``delete`` also runs a full
        ``gc.collect``, which this skips.)"""
        if self._renderer is None:
            return
        platform = self._platform
        if _forked():    # a copy inherited through fork: no GL or EGL call (eglTerminate could block)
            self._renderer.delete()
            if hasattr(platform, "_egl_display"):
                platform._egl_context = platform._egl_display = None   # its __del__ would eglTerminate
            self._renderer = None
            self._platform = None
            return
        egl = hasattr(platform, "_egl_display")                # pyrender's EGLPlatform
        if egl:
            from OpenGL import EGL

            # a finalizer can run in the middle of another renderer's frame (the garbage collector runs at any
            # allocation): give that renderer its context back, or its next GL call finds none current
            before = (EGL.eglGetCurrentDisplay(), EGL.eglGetCurrentSurface(EGL.EGL_DRAW),
                      EGL.eglGetCurrentSurface(EGL.EGL_READ), EGL.eglGetCurrentContext())
        platform.make_current()
        self._renderer.delete()
        if egl:
            EGL.eglMakeCurrent(platform._egl_display, EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, EGL.EGL_NO_CONTEXT)
            own = _handle(platform._egl_context)
            EGL.eglDestroyContext(platform._egl_display, platform._egl_context)
            platform._egl_context = platform._egl_display = None   # its __del__ would terminate the display
            if _handle(before[3]) not in (None, own):
                EGL.eglMakeCurrent(*before)
        else:
            platform.delete_context()
        self._renderer = None
        self._platform = None

    def render_views(self, scene: "pyrender.Scene", cameras: Sequence["pyrender.Node"], color: str | None = "rgb",
                     depth: bool | int = True) -> list[dict[str, np.ndarray]]:
        """See :meth:`_MultiViewRenderer.render_views`."""
        check_process()
        self._platform.make_current()
        try:
            return self._renderer.render_views(scene, cameras, color, depth)
        finally:
            self._platform.make_uncurrent()

    def render_groups(self, scene: "pyrender.Scene", groups: Sequence[ViewGroup], color: str | None = "rgb",
                      depth: bool | int | str = True, bg_color: Sequence[float] | None = None) -> list[dict[str, np.ndarray]]:
        """See :meth:`_MultiViewRenderer.render_groups`."""
        check_process()
        self._platform.make_current()
        try:
            return self._renderer.render_groups(scene, groups, color, depth, bg_color)
        finally:
            self._platform.make_uncurrent()
