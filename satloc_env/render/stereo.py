"""Offscreen stereo rendering of a :class:`~satloc_env.world.meshes.World` (colour, metric depth, class labels).

One persistent pyrender scene holds, per world chunk, a colour mesh (texture with mipmaps, baked face shading
as vertex colours) and a label mesh (the same geometry with the label texture, nearest sampling), plus the
episode's occluders as one more such pair. A frame moves the two camera nodes, hides the chunks that cannot
be within ``zfar`` of the camera and draws with flat (unlit) shading into a single-sample framebuffer, so
depth is exact at pixel centres. The GL context is created on the first render, not before: a process that
holds one cannot safely ``fork`` (rendering in such a child raises :class:`satloc_env.render.gl.GLForkError` at once
instead of hanging; see :mod:`satloc_env.render.gl`).
"""
from __future__ import annotations

import ctypes
import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from satloc.errors import ConfigError
from satloc.geometry import Pose2, StereoCamera
from satloc_env.world.layout import Car, Obstacle, Person
from satloc_env.world.meshes import FAR, GROUND, INSIDE, LOD_M, NEAR, TexturedMesh, World, build_occluders

__all__ = ["BatchStereoRenderer", "StereoRenderer", "StereoSlot"]

#: Converts an OpenCV camera frame (x right, y down, z forward) to OpenGL's (x right, y up, z backward).
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])
_SIDES = ("left", "right")


class BatchStereoRenderer:
    """Renders the rectified stereo pairs of ``camera`` for several vehicles, each in a world of its own or a
    shared one, in one GL context, one pyrender scene and one framebuffer, read back once per call.

    Each vehicle is a *slot* (:meth:`slot`: a :class:`StereoRenderer`-like view with its world, its episode's
    occluders and its two camera nodes). :meth:`render_many` draws the slots' pairs as groups of
    :meth:`satloc_env.render.gl._MultiViewRenderer.render_groups`: every pair is drawn exactly as the slot alone
    would draw it (its world's chunks within reach, its occluders, the same draw order), only in another band of
    the framebuffer. A world's meshes are uploaded once for all the slots that use it, and dropped when the
    last of them leaves it. Filtering and depth range as in :class:`StereoRenderer`."""

    def __init__(self, camera: StereoCamera, *, anisotropy: int = 1, lod_bias: float = -0.5, mipmaps: bool = True,
                 znear: float = 0.1, zfar: float = 150.0, detail_m: float | None = LOD_M):
        if not 0 < znear < zfar:
            raise ConfigError(f"renderer: need 0 < znear < zfar, got znear={znear}, zfar={zfar}")
        if detail_m is not None and not (math.isfinite(detail_m) and detail_m >= 0):
            raise ConfigError(f"renderer: detail_m must be a finite number >= 0 or None, got {detail_m}")
        #: metres from the vehicle within which objects keep their full detail (world.meshes.LOD_M); None: all
        self.detail_m = math.inf if detail_m is None else float(detail_m)
        if anisotropy < 1:
            raise ConfigError(f"renderer: anisotropy must be >= 1, got {anisotropy}")
        self.camera = camera
        self.anisotropy = int(anisotropy)
        self.lod_bias = float(lod_bias)
        self.mipmaps = bool(mipmaps)
        self.znear = float(znear)
        self.zfar = float(zfar)
        # Farthest a point with z-depth <= zfar can be from the camera: along the ray through an image corner.
        tan_x = max(camera.cx + 0.5, camera.width - camera.cx - 0.5) / camera.fx
        tan_y = max(camera.cy + 0.5, camera.height - camera.cy - 0.5) / camera.fy
        self.reach = self.zfar * math.sqrt(1.0 + tan_x ** 2 + tan_y ** 2) + camera.baseline
        self._scene: Any = None           # pyrender.Scene, built on first use
        self._worlds: dict[int, _WorldNodes] = {}   # by id(world): its nodes (while a slot uses it)
        self._slots: list[StereoSlot] = []
        self._next_world = 0
        self._next_slot = 0
        self._gl: Any = None              # MultiViewOffscreenRenderer while a context is held

    # --- slots --------------------------------------------------------------------------------------------
    def slot(self, world: World) -> "StereoSlot":
        """A new vehicle rendering ``world`` (see :class:`StereoSlot`)."""
        slot = StereoSlot(self, world, self._next_slot)
        self._next_slot += 1
        self._slots.append(slot)
        return slot

    def render_many(self, requests: Sequence[tuple], depth: bool | str = True,
                    labels: bool = False) -> list[dict[str, np.ndarray]]:
        """Render the stereo pair of each (slot, pose) or (slot, pose, tilt) of ``requests`` (each slot at most
        once; ``tilt`` as :meth:`StereoRenderer.render` takes it), as :meth:`StereoRenderer.render` does for one,
        in one framebuffer: one ``glReadPixels`` for all colour images, one for the depth (and, with ``labels``,
        one more pass of the label meshes)."""
        if depth not in (True, False, "left"):
            raise ValueError(f"depth: expected True, False or 'left', got {depth!r}")
        requests = [tuple(r) if len(r) == 3 else (*r, None) for r in requests]
        if len({id(slot) for slot, _, _ in requests}) != len(requests):
            raise ValueError("render_many: a slot appears twice in one call")
        if not requests:
            return []
        gl = self._context()
        for slot, pose, tilt in requests:
            if slot.batch is not self or slot.closed:
                raise ValueError("render_many: a slot of another renderer, or a closed one")
            slot._place(pose, tilt)
        n = len(requests)
        groups = [slot._draw_group(False, (*(v / 255.0 for v in slot.world.sky_rgb), 1.0))
                  for slot, _, _ in requests]
        views = gl.render_groups(self._scene, groups, color="rgb",
                                 depth={True: True, False: False, "left": "first"}[depth])
        outs: list[dict[str, np.ndarray]] = []
        for i in range(n):
            left, right = views[2 * i], views[2 * i + 1]
            out = {"left": left["color"], "right": right["color"]}
            if depth:
                out["depth_left"] = left["depth"]
                if depth is True:
                    out["depth_right"] = right["depth"]
            outs.append(out)
        if labels:
            groups = [slot._draw_group(True) for slot, _, _ in requests]
            views = gl.render_groups(self._scene, groups, color="red", depth=False, bg_color=np.zeros(4))  # 0: void
            for i, out in enumerate(outs):
                out["labels_left"], out["labels_right"] = views[2 * i]["color"], views[2 * i + 1]["color"]
        return outs

    @property
    def gl_info(self) -> dict[str, str]:
        """The GL context's ``vendor``, ``renderer`` and ``version`` strings (creates the context if needed):
        which driver draws, e.g. Mesa's llvmpipe or a GPU vendor's."""
        return dict(self._context().gl_info)

    def close(self) -> None:
        """Release the GL context and everything uploaded to it (safe to call again; rendering recreates it)."""
        if self._gl is not None:
            gl, self._gl = self._gl, None
            gl.delete()

    def __enter__(self) -> "BatchStereoRenderer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- scene management ---------------------------------------------------------------------------------
    def _context(self) -> Any:
        """The offscreen renderer, creating the scene and the GL context on first use."""
        from satloc_env.render.gl import MultiViewOffscreenRenderer, check_process, pyrender

        check_process()   # a fork of a process that has rendered: fail now, rendering would hang
        if self._scene is None:
            self._scene = pyrender.Scene()   # each slot's views are cleared to its world's sky (render_many)
            for slot in self._slots:
                if not slot.closed:
                    slot._attach()
        if self._gl is None:
            self._gl = MultiViewOffscreenRenderer(self.camera.width, self.camera.height, self.anisotropy,
                                                  self.lod_bias, self.mipmaps)
        return self._gl

    def _world_nodes(self, world: World) -> "_WorldNodes":
        """The scene nodes of ``world``'s chunks, adding them on first use. Named nodes: the multi-view
        renderer draws equally near nodes in name order (the part before ``#``), which makes the image the same
        in every process and the same in a batch as alone (see ``_MultiViewRenderer._draw_list``)."""
        entry = self._worlds.get(id(world))
        if entry is None:
            tag = f"#w{self._next_world}"
            self._next_world += 1
            nodes, textures = [], {}
            for i, chunk in enumerate(world.chunks):
                pair = _meshes(chunk, textures)
                nodes.append(tuple(self._scene.add(mesh, name=f"chunk{i:05d}/{kind}{tag}")
                                   for mesh, kind in zip(pair, ("color", "labels"))))
            rects = np.array([np.r_[c.bounds[0, :2], c.bounds[1, :2]] for c in world.chunks])
            boxes = np.array([c.bounds for c in world.chunks], np.float64)
            entry = self._worlds[id(world)] = _WorldNodes(world, nodes, rects, boxes, set(), _Cells.of(world.chunks))
        return entry

    def _release_world(self, world: World, slot: "StereoSlot") -> None:
        entry = self._worlds.get(id(world))
        if entry is None:
            return
        entry.users.discard(slot.index)
        if not entry.users:
            for pair in entry.nodes:
                for node in pair:
                    self._scene.remove_node(node)
            del self._worlds[id(world)]


def body_tilt(pitch: float, roll: float) -> np.ndarray:
    """4x4 rotation of the vehicle's body about its origin (x forward, y left, z up): ``pitch`` radians nose
    down (positive when braking), then ``roll`` radians about the forward axis (positive: the left side up,
    as the body leans out of a right turn)."""
    cp, sp, cr, sr = math.cos(pitch), math.sin(pitch), math.cos(roll), math.sin(roll)
    ry = np.array([[cp, 0, sp, 0], [0, 1, 0, 0], [-sp, 0, cp, 0], [0, 0, 0, 1]])
    rx = np.array([[1, 0, 0, 0], [0, cr, -sr, 0], [0, sr, cr, 0], [0, 0, 0, 1]])
    return ry @ rx


class FaceRuns:
    """Runs of triangles of one indexed primitive, as ``glMultiDrawElements`` takes them: ``counts`` (int32:
    3 indices per triangle) and ``starts`` (byte offsets of uint32 indices), with the ctypes arrays over the
    same memory. Iterates as (first triangle, triangles) pairs."""

    __slots__ = ("counts", "starts", "counts_c", "starts_c")

    def __init__(self, counts: np.ndarray, starts: np.ndarray):
        self.counts, self.starts = counts, starts
        n = len(counts)
        self.counts_c = (ctypes.c_int32 * n).from_buffer(counts) if n else None
        self.starts_c = (ctypes.c_void_p * n).from_buffer(starts) if n else None

    def __len__(self) -> int:
        return len(self.counts)

    def __iter__(self):
        return zip((self.starts // 12).tolist(), (self.counts // 3).tolist())


_NO_RUNS = FaceRuns(np.zeros(0, np.int32), np.zeros(0, np.uintp))


class _Cells(NamedTuple):
    """The cells (:attr:`TexturedMesh.cell_faces`) of all chunks of a world that have several, in one flat list."""

    chunk: np.ndarray      # (C,) the chunk each cell belongs to
    first: np.ndarray      # (C,) its first face in its chunk's mesh
    count: np.ndarray      # (C,) its faces
    ground: np.ndarray     # (C,) whether it is its chunk's ground (the last cell: drawn whenever the chunk is)
    boxes: np.ndarray      # (C, 2, 3) its box
    rects: np.ndarray      # (C, 4) x0, y0, x1, y1 of its box
    squares: np.ndarray    # (C, 4) x0, y0, x1, y1 of the square of ground whose distance chooses its detail
    bands: np.ndarray      # (C,) its level-of-detail band (meshes.ALWAYS, NEAR, FAR, INSIDE)
    mirror: np.ndarray     # (C,) whether its chunk is a reflection beyond the layout's edge
    whole: np.ndarray      # (C,) a flat chunk's ground: drawn whenever its chunk is (not a terrain's cell)
    near_band: np.ndarray  # (C,) bands == NEAR
    far_band: np.ndarray   # (C,) bands == FAR
    inside_mirror: np.ndarray  # (C,) bands == INSIDE in a reflection (drawn within detail_m only)
    has_cells: np.ndarray  # (chunks,) whether the chunk is cut into cells (then drawn by its runs alone)

    @staticmethod
    def of(chunks: Sequence[TexturedMesh]) -> "_Cells":
        """The cells of ``chunks``; cells without faces are left out (they draw nothing), but a chunk cut into
        cells keeps ``has_cells`` even if all of its are empty."""
        parts = []
        has_cells = np.zeros(len(chunks), bool)
        for i, c in enumerate(chunks):
            if c.cell_faces is None or len(c.cell_faces) < 3:
                continue   # one cell: the chunk drawn whole
            has_cells[i] = True
            f = np.asarray(c.cell_faces, np.int64)
            k = len(f) - 1
            bands = np.asarray(c.cell_bands, np.int8)
            # the ground: a terrain's cells (band GROUND), else the chunk's last cell
            ground = bands == GROUND if (bands == GROUND).any() else np.arange(k) == k - 1
            parts.append((np.full(k, i), f[:-1], np.diff(f), ground,
                          np.asarray(c.cell_bounds, np.float64), np.asarray(c.cell_squares, np.float64),
                          bands, np.full(k, c.mirror)))
        if not parts:
            z = np.zeros(0)
            parts = [(z.astype(np.int64), z.astype(np.int64), z.astype(np.int64), z.astype(bool),
                      np.zeros((0, 2, 3)), np.zeros((0, 4)), z.astype(np.int8), z.astype(bool))]
        chunk, first, count, ground, boxes, squares, bands, mirror = (np.concatenate(a) for a in zip(*parts))
        live = count > 0
        chunk, first, count, ground, boxes, squares, bands, mirror = (
            a[live] for a in (chunk, first, count, ground, boxes, squares, bands, mirror))
        rects = np.concatenate([boxes[:, 0, :2], boxes[:, 1, :2]], axis=1)
        return _Cells(chunk, first, count, ground, boxes, rects, squares, bands, mirror,
                      ground & (bands != GROUND), bands == NEAR, bands == FAR, (bands == INSIDE) & mirror, has_cells)

    def runs(self, drawn: np.ndarray, in_view: tuple, views: Sequence[np.ndarray], pose: Pose2, reach: float,
             camera: StereoCamera, znear: float, detail_m: float, zfar: float = math.inf,
             planes: Sequence[np.ndarray | None] = (None, None)) -> tuple:
        """Per view, {chunk: (first face, faces) of each of its cells to draw} for the chunks of ``drawn``
        (those in that view, ``in_view[view]``): a cell is drawn when its box is within ``reach`` of the pose
        and meets the view volume (a cell that does neither puts no fragment in the image) and its band suits
        its square's distance to the vehicle (within ``detail_m``: NEAR, not FAR; INSIDE everywhere but in the
        reflections beyond the layout's edge); nearest box first (the depth test then rejects what it hides
        before it is shaded), the ground last (a flat chunk's whole, a terrain's cells that meet the view).

        Every chunk of ``in_view[view]`` that has cells gets an entry, an empty list if no cell is kept: a chunk
        missing there would be drawn whole (every cell, out of reach or not, at every level of detail)."""
        idx = np.flatnonzero(drawn[self.chunk])
        if not len(idx):
            return ({}, {})
        # the bands are exclusive: NEAR cells within detail_m, FAR ones beyond it, INSIDE ones within it or
        # not in a reflection, the others always
        lod = _near(self.squares[idx], pose, detail_m)
        detail = (lod | ~self.near_band[idx]) & ~(lod & self.far_band[idx]) & (lod | ~self.inside_mirror[idx])
        take = self.whole[idx] | (detail & _near(self.rects[idx], pose, reach))
        cand = idx[take]
        whole = self.whole[cand]
        chunk = self.chunk[cand]
        out = []
        for side, m in enumerate(views):
            sel = in_view[side][chunk]
            k = cand[sel]
            keep = whole[sel].copy()
            test = ~keep
            keep[test] = _box_in_view(self.boxes[k[test]], m, camera, znear, zfar=zfar, planes=planes[side])
            k = k[keep]
            eye = m[:3, 3]
            gap = np.linalg.norm(np.clip(eye, self.boxes[k, 0], self.boxes[k, 1]) - eye, axis=1)
            order = k[np.lexsort((gap, self.ground[k], self.chunk[k]))]
            chunks = self.chunk[order]
            cut = np.flatnonzero(np.diff(chunks)) + 1
            counts = 3 * self.count[order].astype(np.int32)            # indices: uint32, 3 per triangle
            starts = 12 * self.first[order].astype(np.uintp)           # byte offsets into the index buffer
            runs: dict = dict.fromkeys(np.flatnonzero(in_view[side] & self.has_cells).tolist(), _NO_RUNS)
            for a, z in zip([0, *cut.tolist()], [*cut.tolist(), len(order)]):
                if z > a:
                    runs[int(chunks[a])] = FaceRuns(counts[a:z], starts[a:z])
            out.append(runs)
        return tuple(out)


class _WorldNodes(NamedTuple):
    world: World
    nodes: list            # (colour node, label node) per chunk
    rects: np.ndarray      # (chunks, 4) x0, y0, x1, y1
    boxes: np.ndarray      # (chunks, 2, 3) the chunks' bounding boxes (min row, max row)
    users: set             # indices of the slots that render this world
    cells: _Cells          # the cells of the chunks that have several (the others are drawn whole)


def _near(rects: np.ndarray, pose: Pose2, reach: float) -> np.ndarray:
    """(n,) whether each rectangle (x0, y0, x1, y1) comes within ``reach`` of the pose's position."""
    dx = np.maximum(np.maximum(rects[:, 0] - pose.x, pose.x - rects[:, 2]), 0.0)
    dy = np.maximum(np.maximum(rects[:, 1] - pose.y, pose.y - rects[:, 3]), 0.0)
    return np.hypot(dx, dy) <= reach


def _view_planes(map_from_cam: np.ndarray, camera: StereoCamera, znear: float, margin_px: float = 4.0,
                 zfar: float = math.inf) -> np.ndarray:
    """(6, 4) the planes of a camera's view volume in map coordinates, as :func:`_box_in_view` tests them."""
    # pixel u = fx x / z + cx + 0.5 in [0, width] (GL window coordinates, see the camera nodes), likewise v;
    # the planes in camera coordinates (x, y, z, 1), then in map coordinates
    u0, u1 = camera.cx + 0.5 + margin_px, camera.cx + 0.5 - camera.width - margin_px
    v0, v1 = camera.cy + 0.5 + margin_px, camera.cy + 0.5 - camera.height - margin_px
    return np.array([[0.0, 0.0, 1.0, -znear], [camera.fx, 0.0, u0, 0.0], [-camera.fx, 0.0, -u1, 0.0],
                     [0.0, camera.fy, v0, 0.0], [0.0, -camera.fy, -v1, 0.0],
                     [0.0, 0.0, -1.0, min(zfar + 1e-3, 1e30)]]) @ np.linalg.inv(map_from_cam)   # 1 mm spare


def _box_in_view(boxes: np.ndarray, map_from_cam: np.ndarray, camera: StereoCamera, znear: float,
                 margin_px: float = 4.0, zfar: float = math.inf, planes: np.ndarray | None = None) -> np.ndarray:
    """(n,) False for the axis-aligned boxes (``boxes``, (n, 2, 3) min and max rows, map frame) wholly on the
    outer side of one plane of the camera's view volume (in front of the near plane, beyond the far plane
    ``zfar``, or beyond an image edge widened by ``margin_px``): such a box puts no fragment in the image, so
    skipping it changes no pixel. A conservative test: a box that misses the volume across a corner may still
    be kept.

    Each plane is a linear function f of the point, f >= 0 on the volume's side; its largest value over a box
    is f(centre) + |grad f| . half-extent, so a box is wholly outside when that is negative. ``planes``: those
    of :func:`_view_planes` for the same camera and arguments, when the caller already has them (a slot tests
    the chunks and then their cells against each view's)."""
    if planes is None:
        planes = _view_planes(map_from_cam, camera, znear, margin_px, zfar)
    b = np.asarray(boxes, np.float64)
    centre, half = (b[:, 0] + b[:, 1]) / 2, (b[:, 1] - b[:, 0]) / 2
    top = centre @ planes[:, :3].T + planes[:, 3] + half @ np.abs(planes[:, :3]).T     # (n, 6)
    return ~(top < 0).any(axis=1)


class StereoSlot:
    """One vehicle of a :class:`BatchStereoRenderer`: renders ``world`` (its chunks within reach of the camera)
    and its own occluders. Has the interface of :class:`StereoRenderer` (:meth:`render` draws this slot alone;
    :meth:`BatchStereoRenderer.render_many` draws several slots at once)."""

    def __init__(self, batch: BatchStereoRenderer, world: World, index: int):
        self.batch = batch
        self.world = world
        self.camera = batch.camera
        self.index = index
        self.closed = False
        self._occluders: TexturedMesh | None = None
        self._occluder_nodes: list[Any] = []
        self._cameras: tuple = ()
        self._visible = np.zeros(len(world.chunks), dtype=bool)   # the chunks within reach of the cameras
        self._in_view: tuple = (self._visible, self._visible)     # per camera: within reach and in its view
        self._runs: tuple = ({}, {})     # per camera: {chunk index: face runs of its cells within reach and view}
        self._vehicle_from_cameras = tuple(self.camera.vehicle_from_camera(side) for side in _SIDES)
        if batch._scene is not None:
            self._attach()

    def _attach(self) -> None:
        """Add this slot's world (if new), camera nodes and occluders to the batch's scene."""
        from satloc_env.render.gl import pyrender

        b, cam = self.batch, self.camera
        b._world_nodes(self.world).users.add(self.index)
        tag = f"#s{self.index}"
        self._cameras = tuple(b._scene.add(pyrender.IntrinsicsCamera(
            cam.fx, cam.fy, cam.cx + 0.5, cam.cy + 0.5, znear=b.znear, zfar=b.zfar), name=f"{side}{tag}")
            for side in _SIDES)
        self._attach_occluders()

    def _attach_occluders(self) -> None:
        scene = self.batch._scene
        for node in self._occluder_nodes:
            scene.remove_node(node)
        self._occluder_nodes = []
        if self._occluders is not None:
            tag = f"#s{self.index}"
            color, label = _meshes(self._occluders)
            self._occluder_nodes = [scene.add(color, name=f"occluders/color{tag}"),
                                    scene.add(label, name=f"occluders/labels{tag}")]

    def set_occluders(self, cars: Sequence[Car], persons: Sequence[Person], obstacles: Sequence[Obstacle]) -> None:
        """Replace the episode's extra objects (drawn as one mesh; all lists may be empty)."""
        self._occluders = build_occluders(cars, persons, obstacles, self.world.sun_direction, self.world.terrain)
        if self.batch._scene is not None and not self.closed:
            self._attach_occluders()

    def render(self, pose: Pose2, depth: bool | str = True, labels: bool = False,
               tilt: tuple[float, float] | None = None) -> dict[str, np.ndarray]:
        """See :meth:`StereoRenderer.render`."""
        if self.closed:
            raise RuntimeError("render: this slot was closed")
        return self.batch.render_many([(self, pose, tilt)], depth, labels)[0]

    def _map_from_camera(self, pose: Pose2, side: str, tilt: tuple[float, float] | None) -> np.ndarray:
        return self._map_from_vehicle(pose, tilt) @ self.camera.vehicle_from_camera(side)

    def _map_from_vehicle(self, pose: Pose2, tilt: tuple[float, float] | None) -> np.ndarray:
        body = pose.matrix3d()
        terrain = self.world.terrain
        if not terrain.flat:   # the car stands on the ground under its wheels, its own tilt on top
            z, pitch, roll = terrain.tilt(pose.x, pose.y, pose.yaw)
            body[2, 3] += z
            tilt = (pitch, roll) if tilt is None else (pitch + tilt[0], roll + tilt[1])
        if tilt is not None:
            body = body @ body_tilt(*tilt)
        return body

    def _place(self, pose: Pose2, tilt: tuple[float, float] | None = None) -> None:
        """Put the cameras at ``pose`` (the body tilted by ``tilt``) and find the chunks whose footprint comes
        within reach of them."""
        scene = self.batch._scene
        body = self._map_from_vehicle(pose, tilt)
        views = [body @ m for m in self._vehicle_from_cameras]
        for view, node in zip(views, self._cameras):
            scene.set_pose(node, view @ _CV_TO_GL)
        entry = self.batch._world_nodes(self.world)
        reach, znear = self.batch.reach, self.batch.znear
        self._visible = _near(entry.rects, pose, reach)
        zfar = self.batch.zfar
        planes = [_view_planes(m, self.camera, znear, zfar=zfar) for m in views]
        self._in_view = tuple(self._visible & _box_in_view(entry.boxes, m, self.camera, znear, zfar=zfar, planes=p)
                              for m, p in zip(views, planes))
        self._runs = entry.cells.runs(self._in_view[0] | self._in_view[1], self._in_view, views, pose, reach,
                                      self.camera, znear, self.batch.detail_m, zfar, planes)

    def _draw_group(self, label_pass: bool, bg_color=None):
        """The slot's two views as a ``ViewGroup``: its chunks within reach, colour (or label) meshes, and its
        occluders', each view skipping the chunks wholly outside its own view volume."""
        from satloc_env.render.gl import ViewGroup

        k = 1 if label_pass else 0
        pairs = self.batch._world_nodes(self.world).nodes
        seen = self._in_view[0] | self._in_view[1]
        nodes = [pair[k] for pair, vis in zip(pairs, seen) if vis]
        if self._occluder_nodes:
            nodes.append(self._occluder_nodes[k])
        hidden = tuple(frozenset(id(pair[k]) for pair, vis, mine in zip(pairs, seen, in_view) if vis and not mine)
                       for in_view in self._in_view)
        ranges = tuple({id(pairs[i][k]): r for i, r in runs.items()} for runs in self._runs)
        return ViewGroup(self._cameras, nodes, bg_color, hidden, ranges)

    @property
    def gl_info(self) -> dict[str, str]:
        return self.batch.gl_info

    @property
    def visible_chunks(self) -> list[int]:
        """Indices of the world chunks drawn by the latest render."""
        return [int(i) for i in np.flatnonzero(self._visible)]

    def close(self) -> None:
        """Leave the batch: its nodes are removed (and its world's, if no other slot uses it)."""
        if self.closed:
            return
        self.closed = True
        b = self.batch
        if b._scene is not None:
            for node in (*self._occluder_nodes, *self._cameras):
                b._scene.remove_node(node)
            b._release_world(self.world, self)
        self._occluder_nodes, self._cameras = [], ()
        if self in b._slots:
            b._slots.remove(self)


class StereoRenderer:
    """Renders the rectified stereo pair of ``camera`` on a vehicle in ``world``.

    Colour textures are sampled bilinearly from the nearest mipmap level with a level-of-detail bias of
    ``lod_bias`` (negative: sharper far ground; -0.5 keeps lane markings visible further out without visible
    shimmer) and, when
    ``anisotropy`` > 1, anisotropic filtering of that level (clamped to what the driver supports). On Mesa
    22.3's llvmpipe any anisotropy > 1 filters like 16x and makes a frame 3 to 4 times slower, hence the
    default of 1. ``mipmaps=False`` samples every colour texture at full resolution (bilinear, no level
    selection): far ground aliases, but the image no longer depends on how a driver picks mipmap levels, which
    the GL specification leaves open (used to compare renders across drivers). ``znear`` / ``zfar`` (metres)
    bound the rendered depth range. The renderer owns a GL context from the first :meth:`render` until
    :meth:`close`; it may render again after ``close``. It is a :class:`BatchStereoRenderer` of one slot.

    Each view draws only the chunks, and within them the cells (the objects on one square of
    :data:`~satloc_env.world.meshes.CELL_M`), whose boxes are within reach and meet its view volume: the image
    is the same as drawing them all. ``detail_m`` (default :data:`~satloc_env.world.meshes.LOD_M`) is the
    distance from the vehicle within which street furniture and trees of a species of their own keep their
    full detail; beyond it, furniture is left out and those trees are drawn coarse, and the parked cars of
    the reflections beyond the layout's edge are left out (None: full detail everywhere, the image of a
    renderer without levels of detail). Worlds at variety 0 have none of these objects and draw the same
    either way.
    """

    def __init__(self, world: World, camera: StereoCamera, *, anisotropy: int = 1, lod_bias: float = -0.5,
                 mipmaps: bool = True, znear: float = 0.1, zfar: float = 150.0, detail_m: float | None = LOD_M):
        self._batch = BatchStereoRenderer(camera, anisotropy=anisotropy, lod_bias=lod_bias, mipmaps=mipmaps,
                                          znear=znear, zfar=zfar, detail_m=detail_m)
        self._slot = self._batch.slot(world)
        self.world = world
        self.camera = camera

    def set_occluders(self, cars: Sequence[Car], persons: Sequence[Person], obstacles: Sequence[Obstacle]) -> None:
        """Replace the episode's extra objects (drawn as one mesh; all lists may be empty)."""
        self._slot.set_occluders(cars, persons, obstacles)

    def render(self, pose: Pose2, depth: bool | str = True, labels: bool = False,
               tilt: tuple[float, float] | None = None) -> dict[str, np.ndarray]:
        """Render the stereo pair for the vehicle at ``pose``, its body tilted by ``tilt`` = (pitch, roll)
        radians (:func:`body_tilt`; None: level, the camera's fixed mount).

        Returns ``left`` and ``right`` (H x W x 3 uint8 RGB), with ``depth`` also ``depth_left`` and
        ``depth_right`` (H x W float32 z-depth in metres, 0 where nothing was hit; ``depth="left"`` reads the
        left one only), with ``labels`` also
        ``labels_left`` and ``labels_right`` (H x W uint8 class ids, 0 = void / sky). All C-contiguous.
        """
        return self._slot.render(pose, depth, labels, tilt)

    @property
    def gl_info(self) -> dict[str, str]:
        """The GL context's ``vendor``, ``renderer`` and ``version`` strings (creates the context if needed):
        which driver draws, e.g. Mesa's llvmpipe or a GPU vendor's."""
        return self._batch.gl_info

    @property
    def visible_chunks(self) -> list[int]:
        """Indices of the world chunks drawn by the latest :meth:`render`."""
        return self._slot.visible_chunks

    def close(self) -> None:
        """Release the GL context and everything uploaded to it (safe to call again; rendering recreates it)."""
        self._batch.close()

    def __enter__(self) -> "StereoRenderer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _meshes(tm: TexturedMesh, textures: dict | None = None) -> tuple[Any, Any]:
    """pyrender meshes of a :class:`TexturedMesh`: (colour mesh, label mesh), one primitive each. Meshes that
    share texture arrays (a chunk and its reflections beyond the layout's edge) share one pyrender texture
    each through ``textures`` (keyed by the arrays' identity, alive while the caller holds the meshes), so it
    is uploaded once."""
    from satloc_env.render.gl import pyrender

    key = (id(tm.texture), id(tm.labels), tm.repeat)
    if textures is not None and key in textures:
        color_tex, label_tex = textures[key]
    else:
        wrap = pyrender.GLTF.REPEAT if tm.repeat else pyrender.GLTF.CLAMP_TO_EDGE
        clamp = dict(wrapS=wrap, wrapT=wrap)
        color_tex = pyrender.Texture(source=tm.texture, source_channels="RGB", sampler=pyrender.Sampler(**clamp))
        label_tex = pyrender.Texture(source=tm.labels, source_channels="R", sampler=pyrender.Sampler(
            magFilter=pyrender.GLTF.NEAREST, minFilter=pyrender.GLTF.NEAREST, **clamp))
        if textures is not None:
            textures[key] = (color_tex, label_tex)
    shade = np.repeat(tm.shade[:, None], 4, axis=1)
    shade[:, 3] = 1.0
    prims = []
    for tex, colors in ((color_tex, shade), (label_tex, None)):
        material = pyrender.MetallicRoughnessMaterial(baseColorFactor=np.ones(4), baseColorTexture=tex,
                                                      metallicFactor=0.0, roughnessFactor=1.0)
        prims.append(pyrender.Primitive(positions=tm.positions, texcoord_0=tm.uvs, color_0=colors,
                                        indices=tm.faces, material=material))
    return pyrender.Mesh([prims[0]]), pyrender.Mesh([prims[1]])
