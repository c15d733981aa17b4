"""Offscreen stereo rendering of a :class:`~satloc_env.world.World` (colour, metric depth, class labels).

One persistent pyrender scene holds, per world chunk, a colour mesh (texture with mipmaps, baked face shading
as vertex colours) and a label mesh (the same geometry with the label texture, nearest sampling), plus the
episode's occluders as one more such pair. A frame moves the two camera nodes, hides the chunks that cannot
be within ``zfar`` of the camera and draws with flat (unlit) shading into a single-sample framebuffer, so
depth is exact at pixel centres. The GL context is created on the first render, not before: a process that
holds one cannot safely ``fork`` (rendering in such a child raises :class:`satloc_env._gl.GLForkError` at once
instead of hanging; see :mod:`satloc_env._gl`).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from satloc.errors import ConfigError
from satloc.geometry import Pose2, StereoCamera

from .layout import Car, Obstacle, Person
from .world import TexturedMesh, World, build_occluders

__all__ = ["StereoRenderer"]

#: Converts an OpenCV camera frame (x right, y down, z forward) to OpenGL's (x right, y up, z backward).
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])
_SIDES = ("left", "right")


class StereoRenderer:
    """Renders the rectified stereo pair of ``camera`` on a vehicle in ``world``.

    Colour textures are sampled trilinearly from mipmaps with a level-of-detail bias of ``lod_bias`` (negative:
    sharper far ground; -0.5 keeps lane markings visible further out without visible shimmer) and, when
    ``anisotropy`` > 1, anisotropic filtering of that level (clamped to what the driver supports). On Mesa
    22.3's llvmpipe any anisotropy > 1 filters like 16x and makes a frame 3 to 4 times slower, hence the
    default of 1. ``mipmaps=False`` samples every colour texture at full resolution (bilinear, no level
    selection): far ground aliases, but the image no longer depends on how a driver picks mipmap levels, which
    the GL specification leaves open (used to compare renders across drivers). ``znear`` / ``zfar`` (metres)
    bound the rendered depth range. The renderer owns a GL context from the first :meth:`render` until
    :meth:`close`; it may render again after ``close``.
    """

    def __init__(self, world: World, camera: StereoCamera, *, anisotropy: int = 1, lod_bias: float = -0.5,
                 mipmaps: bool = True, znear: float = 0.1, zfar: float = 150.0):
        if not 0 < znear < zfar:
            raise ConfigError(f"renderer: need 0 < znear < zfar, got znear={znear}, zfar={zfar}")
        if anisotropy < 1:
            raise ConfigError(f"renderer: anisotropy must be >= 1, got {anisotropy}")
        self.world = world
        self.camera = camera
        self.anisotropy = int(anisotropy)
        self.lod_bias = float(lod_bias)
        self.mipmaps = bool(mipmaps)
        self.znear = float(znear)
        self.zfar = float(zfar)
        # Farthest a point with z-depth <= zfar can be from the camera: along the ray through an image corner.
        tan_x = max(camera.cx + 0.5, camera.width - camera.cx - 0.5) / camera.fx
        tan_y = max(camera.cy + 0.5, camera.height - camera.cy - 0.5) / camera.fy
        self._reach = self.zfar * math.sqrt(1.0 + tan_x ** 2 + tan_y ** 2) + camera.baseline
        self._chunk_rects = np.array([np.r_[c.bounds[0, :2], c.bounds[1, :2]] for c in world.chunks])
        self._occluders: TexturedMesh | None = None
        self._visible = np.zeros(len(world.chunks), dtype=bool)
        self._scene: Any = None           # pyrender.Scene, built on first use
        self._chunk_meshes: list[tuple[Any, Any]] = []   # (colour mesh, label mesh) per chunk
        self._occluder_nodes: list[Any] = []
        self._camera_nodes: dict[str, Any] = {}
        self._gl: Any = None              # MultiViewOffscreenRenderer while a context is held
        self._sky = np.array([*(v / 255.0 for v in world.sky_rgb), 1.0])

    # --- public API ---------------------------------------------------------------------------------------
    def set_occluders(self, cars: Sequence[Car], persons: Sequence[Person], obstacles: Sequence[Obstacle]) -> None:
        """Replace the episode's extra objects (drawn as one mesh; all lists may be empty)."""
        self._occluders = build_occluders(cars, persons, obstacles, self.world.sun_direction)
        if self._scene is not None:
            self._attach_occluders()

    def render(self, pose: Pose2, depth: bool | str = True, labels: bool = False) -> dict[str, np.ndarray]:
        """Render the stereo pair for the vehicle at ``pose``.

        Returns ``left`` and ``right`` (H x W x 3 uint8 RGB), with ``depth`` also ``depth_left`` and
        ``depth_right`` (H x W float32 z-depth in metres, 0 where nothing was hit; ``depth="left"`` reads the
        left one only), with ``labels`` also
        ``labels_left`` and ``labels_right`` (H x W uint8 class ids, 0 = void / sky). All C-contiguous.
        """
        gl = self._context()
        self._cull(pose)
        cameras = [self._camera_nodes[side] for side in _SIDES]
        for side, node in zip(_SIDES, cameras):
            self._scene.set_pose(node, self.camera.map_from_camera(pose, side) @ _CV_TO_GL)
        out: dict[str, np.ndarray] = {}
        if depth not in (True, False, "left"):
            raise ValueError(f"depth: expected True, False or 'left', got {depth!r}")
        for side, view in zip(_SIDES, gl.render_views(self._scene, cameras, color="rgb",
                                                      depth=1 if depth == "left" else depth)):
            out[side] = view["color"]
            if "depth" in view:
                out[f"depth_{side}"] = view["depth"]
        if labels:
            self._show(label_pass=True)
            self._scene.bg_color = np.zeros(4)            # void
            try:
                views = gl.render_views(self._scene, cameras, color="red", depth=False)
            finally:
                self._show(label_pass=False)
                self._scene.bg_color = self._sky
            for side, view in zip(_SIDES, views):
                out[f"labels_{side}"] = view["color"]
        return out

    @property
    def gl_info(self) -> dict[str, str]:
        """The GL context's ``vendor``, ``renderer`` and ``version`` strings (creates the context if needed):
        which driver draws, e.g. Mesa's llvmpipe or a GPU vendor's."""
        return dict(self._context().gl_info)

    @property
    def visible_chunks(self) -> list[int]:
        """Indices of the world chunks drawn by the latest :meth:`render`."""
        return [int(i) for i in np.flatnonzero(self._visible)]

    def close(self) -> None:
        """Release the GL context and everything uploaded to it (safe to call again; rendering recreates it)."""
        if self._gl is not None:
            gl, self._gl = self._gl, None
            gl.delete()

    def __enter__(self) -> "StereoRenderer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- scene management ---------------------------------------------------------------------------------
    def _context(self) -> Any:
        """The offscreen renderer, creating the scene and the GL context on first use."""
        from satloc_env._gl import MultiViewOffscreenRenderer, check_process, pyrender

        check_process()   # a fork of a process that has rendered: fail now, rendering would hang
        if self._scene is None:
            self._scene = pyrender.Scene(bg_color=self._sky)
            # Named nodes: the multi-view renderer draws equally near nodes in name order, which makes the
            # image the same in every process (see _MultiViewRenderer.render_views).
            for i, chunk in enumerate(self.world.chunks):
                pair = _meshes(chunk)
                for mesh, kind in zip(pair, ("color", "labels")):
                    self._scene.add(mesh, name=f"chunk{i:05d}/{kind}")
                self._chunk_meshes.append(pair)
            cam = self.camera
            for side in _SIDES:
                self._camera_nodes[side] = self._scene.add(pyrender.IntrinsicsCamera(
                    cam.fx, cam.fy, cam.cx + 0.5, cam.cy + 0.5, znear=self.znear, zfar=self.zfar), name=side)
            self._attach_occluders()
        if self._gl is None:
            self._gl = MultiViewOffscreenRenderer(self.camera.width, self.camera.height, self.anisotropy,
                                                  self.lod_bias, self.mipmaps)
        return self._gl

    def _attach_occluders(self) -> None:
        for node in self._occluder_nodes:
            self._scene.remove_node(node)
        self._occluder_nodes = []
        if self._occluders is not None:
            color, label = _meshes(self._occluders)
            label.is_visible = False
            self._occluder_nodes = [self._scene.add(color, name="occluders/color"),
                                    self._scene.add(label, name="occluders/labels")]

    def _cull(self, pose: Pose2) -> None:
        """Show the colour meshes of the chunks whose footprint comes within reach of the camera."""
        r = self._chunk_rects
        dx = np.maximum(np.maximum(r[:, 0] - pose.x, pose.x - r[:, 2]), 0.0)
        dy = np.maximum(np.maximum(r[:, 1] - pose.y, pose.y - r[:, 3]), 0.0)
        self._visible = np.hypot(dx, dy) <= self._reach
        self._show(label_pass=False)

    def _show(self, label_pass: bool) -> None:
        """Make either the colour or the label meshes of the visible chunks (and of the occluders) visible."""
        for (color, label), vis in zip(self._chunk_meshes, self._visible):
            color.is_visible = bool(vis) and not label_pass
            label.is_visible = bool(vis) and label_pass
        if self._occluder_nodes:
            self._occluder_nodes[0].mesh.is_visible = not label_pass
            self._occluder_nodes[1].mesh.is_visible = label_pass


def _meshes(tm: TexturedMesh) -> tuple[Any, Any]:
    """pyrender meshes of a :class:`TexturedMesh`: (colour mesh, label mesh), one primitive each."""
    from satloc_env._gl import pyrender

    wrap = pyrender.GLTF.REPEAT if tm.repeat else pyrender.GLTF.CLAMP_TO_EDGE
    clamp = dict(wrapS=wrap, wrapT=wrap)
    color_tex = pyrender.Texture(source=tm.texture, source_channels="RGB", sampler=pyrender.Sampler(**clamp))
    label_tex = pyrender.Texture(source=tm.labels, source_channels="R", sampler=pyrender.Sampler(
        magFilter=pyrender.GLTF.NEAREST, minFilter=pyrender.GLTF.NEAREST, **clamp))
    shade = np.repeat(tm.shade[:, None], 4, axis=1)
    shade[:, 3] = 1.0
    prims = []
    for tex, colors in ((color_tex, shade), (label_tex, None)):
        material = pyrender.MetallicRoughnessMaterial(baseColorFactor=np.ones(4), baseColorTexture=tex,
                                                      metallicFactor=0.0, roughnessFactor=1.0)
        prims.append(pyrender.Primitive(positions=tm.positions, texcoord_0=tm.uvs, color_0=colors,
                                        indices=tm.faces, material=material))
    return pyrender.Mesh([prims[0]]), pyrender.Mesh([prims[1]])
