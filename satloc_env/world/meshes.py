"""Renderable 3-D geometry of a scene :class:`~satloc_env.world.layout.Layout` (pure numpy: no GL, picklable).

The ground plane (z = 0) is cut into square chunks of about ``chunk_m`` metres. Each chunk is one
:class:`TexturedMesh` (one draw call): its ground quad plus every building, tree and parked car whose centre
lies in the chunk. The mesh has one colour texture laid out as

* the chunk's region of ``layout.ground_rgb`` at the top, with ``PAD`` texels of the neighbouring ground
  around it (so bilinear and mipmap filtering read real ground across chunk seams), and
* below it an atlas strip of the objects' procedurally generated textures (facades with windows and doors,
  roofs, bark, foliage, car paint), each surrounded by ``PAD`` texels of its own replicated edge to limit
  mipmap bleeding between neighbours,

and one label texture with the same layout holding a class id (:mod:`satloc.labels`) per texel:
``layout.ground_labels`` in the ground region, the object's class in its atlas regions.

With ``pad_m`` > 0 the world goes on beyond the layout for ``pad_m`` metres on every side, so that no view
from the layout ever ends at its edge and shows sky below the horizon. ``beyond`` says with what:

* ``"mirror"`` (the default): the layout reflected across its edges, ground and objects, as a texture
  repeats with GL's mirrored-repeat wrap (x -> -x, x -> 2 W - x, and so on out to ``pad_m``). Each image is a
  whole chunk reflected (positions mirrored, faces turned to keep their winding, :attr:`TexturedMesh.mirror`
  set), sharing its chunk's texture arrays: a road that meets the edge goes on (as its mirror image), a
  block of houses stands beyond the edge, and the seam is continuous because the reflection of the ground
  at the edge is the ground at the edge. Shading and painted shadows are mirrored with the geometry, so the
  reflected world is lit consistently by a reflected sun. The reflections are scenery: no route, object list
  or satellite map knows them.
* ``"neutral"``: flat ground textured with one neutral texture repeated (:func:`pad_texture`: the median
  colour of the layout's outermost ground with a faint, seamless mottle; class ``void``, unknown ground,
  which is not drivable): one mesh of eight flat quads round the layout, one draw call. It shows the camera
  that the ground goes on, not what lies there, and a road meeting the edge ends there in a straight line.

Textures are made deterministically: the random generator of an object is seeded by its kind and its index
in the layout (and a facade's look is chosen by its ``facade`` style index). Object faces carry a baked
shading factor (per face, from its normal and the sun direction) so that unlit rendering still reads as 3-D;
the ground's factor is 1.

UVs follow OpenGL's convention as pyrender uploads textures: ``u`` grows with the image column, ``v = 1`` is
the image's first row. Texture widths are multiples of 4 (GL's default row alignment).
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from satloc.errors import ConfigError
from satloc.labels import CLASS_ID

from .furniture import ROWS, furniture_parts, part_paint, roof_parts
from .layout import Building, Car, Furniture, Layout, Obstacle, Person, Tree
from .paint import fbm as _fbm
from .paint import right_angled
from .terrain import GROUND_STEP_M, Crown, Terrain
from .variety import BODIES, SPECIES, facade_params, facade_texture, leaf_texture

__all__ = ["TexturedMesh", "World", "build_world", "BEYOND", "build_occluders", "sun_direction", "SKY_RGB", "PAD"]

#: Texels of padding around every texture region (real neighbouring ground, or the region's replicated edge).
PAD = 8
#: Background colour of rendered images (a light, hazy blue).
SKY_RGB = (168, 196, 226)
#: neutral ground around the tile (metres): beyond the renderer's default view distance (150 m) along the
#: camera's corner rays, so no view from the tile reaches the padding's edge (a scene's default ground_pad_m)
DEFAULT_GROUND_PAD_M = 250.0
#: Texel size (metres) of the procedural textures.
_FACADE_M, _FOLIAGE_M, _BARK_M, _CAR_M, _PERSON_M, _OBSTACLE_M = 0.1, 0.08, 0.05, 0.04, 0.03, 0.04
#: Largest side (texels) of a chunk's texture: the GL_MAX_TEXTURE_SIZE every OpenGL 4.5 implementation has.
MAX_TEXTURE = 16384
#: Width (texels) of the atlas of an occluder mesh, which has no ground region.
_OCCLUDER_ATLAS_W = 4096  # wide enough that dense occluder sets stay under GL max texture size
#: Baked shading: factor = _AMBIENT + (1 - _AMBIENT) * max(0, normal . sun).
_AMBIENT = 0.55


@dataclass
class TexturedMesh:
    """A triangle mesh with one colour texture and a label texture of the same size and UV layout."""

    positions: np.ndarray  #: (N, 3) float32 vertices, map frame, metres
    uvs: np.ndarray        #: (N, 2) float32 texture coordinates (OpenGL convention, see module docstring)
    shade: np.ndarray      #: (N,) float32 baked shading factor in (0, 1]
    faces: np.ndarray      #: (M, 3) uint32 vertex indices, counter-clockwise seen from outside
    texture: np.ndarray    #: (H, W, 3) uint8 RGB, W % 4 == 0
    labels: np.ndarray     #: (H, W) uint8 class ids
    repeat: bool = False   #: the texture repeats beyond [0, 1] (the padding's); else clamped to its edge
    mirror: bool = False   #: a reflection of a chunk beyond the layout's edge, sharing that chunk's texture arrays
    #: (K + 1,) int64: the faces are grouped in K cells, cell k's are ``faces[cell_faces[k]:cell_faces[k + 1]]``
    #: (the objects standing on one square of :data:`CELL_M` of the ground; the ground itself the last cell);
    #: None: one cell. The renderer draws only the cells whose boxes meet a camera's view.
    cell_faces: np.ndarray | None = None
    #: (K, 2, 3) float32: each cell's axis-aligned bounds (min row, max row); None with ``cell_faces``
    cell_bounds: np.ndarray | None = None
    #: (K, 4) float32: x0, y0, x1, y1 of the square of ground whose objects each cell holds (the level of detail
    #: is chosen by the vehicle's distance to it); None with ``cell_faces``
    cell_squares: np.ndarray | None = None
    #: (K,) int8: each cell's level-of-detail band (:data:`ALWAYS`, :data:`NEAR`, :data:`FAR`, :data:`INSIDE`)
    cell_bands: np.ndarray | None = None

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) axis-aligned bounds of the vertices: the min row and the max row."""
        return np.stack([self.positions.min(axis=0), self.positions.max(axis=0)])


@dataclass
class World:
    """Renderable geometry of a layout: one :class:`TexturedMesh` per ground chunk."""

    width_m: float
    height_m: float
    chunk_m: float              #: side of a chunk, metres (a whole number of ground texels)
    chunks: list[TexturedMesh]
    sun_direction: np.ndarray   #: (3,) unit vector pointing towards the sun (map frame)
    sky_rgb: tuple[int, int, int] = SKY_RGB
    terrain: Terrain = dataclasses.field(default_factory=Terrain)   #: the ground's heights (default: a plane)


WORLD_FORMAT = "satloc-world"


def save_world(world: World, path) -> None:
    """``world`` in one npz (plain arrays; atomic): each chunk's geometry, and each texture once (chunks that share
    a texture, a mirrored chunk and its source, share it again when loaded)."""
    from satloc.persist import save_npz

    arrays: dict[str, np.ndarray] = {}
    textures: dict[int, int] = {}
    tex_of, flags = [], []
    for k, c in enumerate(world.chunks):
        for name in ("positions", "uvs", "shade", "faces"):
            arrays[f"c{k}_{name}"] = getattr(c, name)
        if c.cell_faces is not None:
            for name in ("cell_faces", "cell_bounds", "cell_squares", "cell_bands"):
                arrays[f"c{k}_{name}"] = getattr(c, name)
        t = textures.setdefault(id(c.texture), len(textures))
        if t == len(textures) - 1 and f"t{t}_texture" not in arrays:
            arrays[f"t{t}_texture"], arrays[f"t{t}_labels"] = c.texture, c.labels
        tex_of.append(t)
        flags.append([int(c.repeat), int(c.mirror)])
    arrays["texture_of"] = np.asarray(tex_of, np.int64)
    arrays["flags"] = np.asarray(flags, np.int64).reshape(-1, 2)
    arrays["sun_direction"] = np.asarray(world.sun_direction, np.float64)
    meta = {"width_m": float(world.width_m), "height_m": float(world.height_m), "chunk_m": float(world.chunk_m),
            "sky_rgb": [int(v) for v in world.sky_rgb], "chunks": len(world.chunks),
            "terrain": world.terrain.to_dict()}
    crown = world.terrain.crown
    if crown is not None:
        arrays.update(crown_offset=crown.offset, crown_xlines=crown.xlines, crown_ylines=crown.ylines)
        meta["crown"] = {"mpp": crown.mpp, "height_m": crown.height_m}
    save_npz(path, WORLD_FORMAT, arrays, meta)


def load_world(path) -> World:
    """What :func:`save_world` wrote; :class:`satloc.FormatError` for a damaged or foreign file."""
    from satloc.errors import FormatError
    from satloc.persist import load_npz

    a, m = load_npz(path, WORLD_FORMAT)
    try:
        n = int(m["chunks"])
        tex_of, flags = a["texture_of"], a["flags"]
        chunks = []
        shared: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for k in range(n):
            t = int(tex_of[k])
            if t not in shared:
                shared[t] = (a[f"t{t}_texture"], a[f"t{t}_labels"])
            chunk = TexturedMesh(a[f"c{k}_positions"], a[f"c{k}_uvs"], a[f"c{k}_shade"], a[f"c{k}_faces"],
                                 shared[t][0], shared[t][1], bool(flags[k, 0]), bool(flags[k, 1]))
            if f"c{k}_cell_faces" in a:
                (chunk.cell_faces, chunk.cell_bounds, chunk.cell_squares, chunk.cell_bands) = _checked_cells(
                    *(a[f"c{k}_{name}"] for name in ("cell_faces", "cell_bounds", "cell_squares", "cell_bands")),
                    len(chunk.faces))
            chunks.append(chunk)
        terrain = Terrain(**m["terrain"]) if "terrain" in m else Terrain()
        if "crown" in m:
            terrain = terrain.with_crown(Crown(np.asarray(a["crown_offset"], np.float32), float(m["crown"]["mpp"]),
                                               float(m["crown"]["height_m"]), np.asarray(a["crown_xlines"], np.float64),
                                               np.asarray(a["crown_ylines"], np.float64)))
        return World(float(m["width_m"]), float(m["height_m"]), float(m["chunk_m"]), chunks,
                     np.asarray(a["sun_direction"], np.float64), tuple(int(v) for v in m["sky_rgb"]), terrain)
    except (KeyError, IndexError, TypeError, ValueError, ConfigError) as e:
        raise FormatError(f"{path}: not a complete world ({e})") from None


def _checked_cells(offsets, bounds, squares, bands, faces: int) -> tuple[np.ndarray, ...]:
    """A chunk's cells as saved, or ValueError (read as a damaged file)."""
    offsets, bounds, squares, bands = (np.asarray(x) for x in (offsets, bounds, squares, bands))
    k = len(offsets) - 1
    if (offsets.ndim != 1 or k < 1 or bounds.shape != (k, 2, 3) or squares.shape != (k, 4) or bands.shape != (k,)
            or offsets[0] != 0 or offsets[-1] != faces or (np.diff(offsets) < 0).any()
            or not np.isin(bands, (ALWAYS, NEAR, FAR, INSIDE, GROUND)).all()):
        raise ValueError("cell_faces, cell_bounds, cell_squares and cell_bands do not partition the chunk's faces")
    return offsets.astype(np.int64), bounds.astype(np.float32), squares.astype(np.float32), bands.astype(np.int8)


def sun_direction(azimuth: float, elevation: float) -> np.ndarray:
    """Unit vector towards the sun for an azimuth (counter-clockwise from east) and elevation, radians."""
    ce = math.cos(elevation)
    return np.array([ce * math.cos(azimuth), ce * math.sin(azimuth), math.sin(elevation)])


# --- public builders --------------------------------------------------------------------------------------
#: what lies beyond the layout's edge (see the module docstring)
BEYOND = ("mirror", "neutral")


def build_world(layout: Layout, chunk_m: float = 204.8, pad_m: float = 0.0, beyond: str = "mirror",
                terrain: Terrain | None = None) -> World:
    """Turn ``layout`` into chunked, textured geometry, with ``pad_m`` metres of world around it: the layout
    mirrored across its edges (``beyond="mirror"``) or neutral ground (``"neutral"``); see the module
    docstring. Over a ``terrain`` that is not flat, the ground follows its heights and the objects stand on it
    (:mod:`satloc_env.world.terrain`); a terrain with a ``camber`` gets the crown of ``layout``'s roads."""
    terrain = terrain or Terrain()
    if beyond not in BEYOND:
        raise ConfigError(f"build_world: beyond: expected one of {BEYOND}, got {beyond!r}")
    mpp = float(layout.ground_mpp)
    if float(terrain.camber) > 0.0 and terrain.crown is None:
        terrain = terrain.with_crown(Crown.of(layout.ground_labels, mpp, terrain.camber, layout.height_m))
    rows, cols = layout.ground_labels.shape
    if layout.ground_rgb.shape != (rows, cols, 3):
        raise ConfigError(f"layout: ground_rgb must be (H, W, 3) like ground_labels {(rows, cols)}, "
                          f"got {layout.ground_rgb.shape}")
    if chunk_m <= 0 or mpp <= 0:
        raise ConfigError(f"build_world: chunk_m and ground_mpp must be positive, got {chunk_m}, {mpp}")
    cpx = max(1, round(chunk_m / mpp))            # chunk side in ground texels
    nx, ny = math.ceil(cols / cpx), math.ceil(rows / cpx)
    sun = sun_direction(layout.sun_azimuth, layout.sun_elevation)

    # Assign every object to the chunk holding its centre.
    def chunk_of(x: float, y: float) -> int:
        i = min(max(int(x / mpp // cpx), 0), nx - 1)
        j = min(max(int(y / mpp // cpx), 0), ny - 1)
        return j * nx + i

    def cell_of(x: float, y: float) -> tuple[int, int]:   # the square of CELL_M a centre stands on
        return int(math.floor(x / CELL_M)), int(math.floor(y / CELL_M))

    # per chunk: (square, add, level): a building stands level on a terrain, anything else follows it
    members: list[list[tuple[tuple[int, int], Callable[[_MeshBuilder], None], bool]]] = [[] for _ in range(nx * ny)]
    look = lambda k, o: k if o.look is None else int(o.look)  # noqa: E731  (layout's note on looks)
    for k, b in enumerate(layout.buildings):
        c = np.asarray(b.footprint, dtype=np.float64).mean(axis=0)
        members[chunk_of(*c)].append((cell_of(*c), lambda mb, b=b, k=look(k, b): _add_building(mb, b, k, layout),
                                      True))
    for k, t in enumerate(layout.trees):
        members[chunk_of(*t.center)].append((cell_of(*t.center), lambda mb, t=t, k=look(k, t): _add_tree(mb, t, k),
                                             False))
    for k, c in enumerate(layout.cars):
        members[chunk_of(*c.center)].append((cell_of(*c.center),
                                             lambda mb, c=c, k=look(k, c): _add_car(mb, c, ("parked", k)), False))
    for k, f in enumerate(layout.furniture):
        members[chunk_of(*f.center)].append((cell_of(*f.center),
                                             lambda mb, f=f, k=look(k, f): _add_furniture(mb, f, k), False))

    chunks, extents = [], []
    for j in range(ny):
        for i in range(nx):
            ground = _ground_region(layout, i * cpx, j * cpx, cpx, terrain)
            mb = _MeshBuilder(sun, atlas_width=ground.texture.shape[1])
            for square, add, level in members[j * nx + i]:
                mb.square = square
                first = len(mb._pos)
                add(mb)
                if not terrain.flat:
                    _stand_on(mb, first, terrain, level)
            chunks.append(_in_cells(mb.build(ground), mb.cell_keys()))
            extents.append(ground.extent)
    if pad_m > 0 and beyond == "neutral":
        chunks.append(_pad_mesh(layout, cols * mpp, rows * mpp, float(pad_m), terrain))
    elif pad_m > 0:
        chunks += _mirrored(chunks, extents, cols * mpp, rows * mpp, float(pad_m))
    return World(float(layout.width_m), float(layout.height_m), cpx * mpp, chunks, sun, terrain=terrain)


def _stand_on(mb: "_MeshBuilder", first: int, terrain: Terrain, level: bool = False) -> None:
    """Lift what ``mb`` added from its ``first`` vertex block on onto ``terrain``: with ``level`` (a building,
    its walls ending in vertices at z 0 on its footprint) level, on the lowest ground under its footprint;
    else vertex by vertex by the ground under it."""
    blocks = mb._pos[first:]
    if not blocks:
        return
    p = np.concatenate(blocks)
    h = terrain.height(p[:, 0], p[:, 1])
    if level:
        base = np.abs(p[:, 2]) < 1e-9
        h = np.full(len(p), float(h[base].min() if base.any() else h.min()))
    at = 0
    for k, b in enumerate(blocks):
        q = np.array(b, dtype=np.float64, copy=True)
        q[:, 2] += h[at:at + len(q)]
        mb._pos[first + k] = q
        at += len(q)


#: side (metres) of the squares of ground whose objects make one cell of a chunk's faces (see
#: :attr:`TexturedMesh.cell_faces`): the renderer skips the cells outside a camera's view, so a small cell
#: draws fewer hidden triangles, at one draw call per visible cell
CELL_M = 25.6
#: level-of-detail bands of a cell's triangles: drawn at any distance, only while the cell's square is within
#: :data:`LOD_M` of the vehicle, only beyond it (the distance from the vehicle's position to the square, the
#: same for both cameras of the pair, so the two views always show the same geometry), and at any distance in
#: the layout itself but only within LOD_M in its reflections beyond its edge (the parked cars of the backdrop).
ALWAYS, NEAR, FAR, INSIDE = 0, 1, 2, 3
#: the band of the cells a terrain's ground grid is cut into (squares of :data:`GROUND_CELL_M`): drawn at any
#: distance where they meet the view, after the objects of their chunk (a flat chunk's ground, two triangles,
#: is one cell of band ALWAYS, the chunk's last, drawn whenever the chunk is)
GROUND = 4
#: side (metres) of the squares a terrain's ground grid is cut into: 4 x 4 squares of GROUND_STEP_M, 32
#: triangles a draw range (the grid's squares one by one cost more in draw ranges than culling them saved)
GROUND_CELL_M = 4 * GROUND_STEP_M
#: metres from the vehicle to a square of :data:`CELL_M` beyond which its objects' NEAR triangles give way to
#: their FAR ones: street furniture is left out and species trees are drawn coarse (at 60 m a 12 cm post is
#: 0.7 px wide in a 620-pixel KITTI frame, a 3 m crown 18 px); the renderer's default ``detail_m``
LOD_M = 60.0


def _in_cells(mesh: TexturedMesh, keys: np.ndarray) -> TexturedMesh:
    """``mesh`` (objects' faces in the order added, then the ground's) with its faces grouped by cell, a cell
    being the faces of one band of the objects standing on one square (``keys``: per object face, the square's
    column and row and the band): a stable sort by key, the ground's faces last: a flat ground's two triangles
    a cell of their own, a terrain's ground grid cut into squares of :data:`GROUND_CELL_M` (band
    :data:`GROUND`), so that a view draws only the squares it sees."""
    n_obj = len(keys)
    order = np.lexsort(keys.T[::-1]) if n_obj else np.zeros(0, np.int64)
    ground = mesh.faces[n_obj:]
    gcells = np.zeros(len(ground), np.int64)
    if len(ground) > 2:   # a terrain's grid: its faces by the square of GROUND_CELL_M their centre lies on
        c = mesh.positions[ground].mean(axis=1)
        sq = np.floor(c[:, :2] / GROUND_CELL_M).astype(np.int64)
        sq -= sq.min(axis=0)
        gcells = sq[:, 1] * (int(sq[:, 0].max()) + 1) + sq[:, 0]
        g_order = np.argsort(gcells, kind="stable")
        ground, gcells = ground[g_order], gcells[g_order]
    faces = np.concatenate([mesh.faces[:n_obj][order], ground])
    ks = keys[order]
    starts = np.flatnonzero(np.r_[True, (ks[1:] != ks[:-1]).any(axis=1)]) if n_obj else np.zeros(0, np.int64)
    g_starts = n_obj + np.flatnonzero(np.r_[True, gcells[1:] != gcells[:-1]]) if len(ground) else np.r_[n_obj]
    offsets = np.r_[starts, g_starts, len(faces)].astype(np.int64)
    split = len(g_starts) > 1
    bounds, squares, bands = [], [], []
    for a, b in zip(offsets[:-1], offsets[1:]):
        p = mesh.positions[faces[a:b].ravel()]
        bounds.append(np.stack([p.min(axis=0), p.max(axis=0)]) if len(p) else np.zeros((2, 3), np.float32))
        if a < n_obj:
            (qx, qy, band) = ks[a]
            squares.append([qx * CELL_M, qy * CELL_M, (qx + 1) * CELL_M, (qy + 1) * CELL_M])
            bands.append(band)
        else:   # the ground (a cell of it, on a terrain)
            squares.append([p[:, 0].min(), p[:, 1].min(), p[:, 0].max(), p[:, 1].max()])
            bands.append(GROUND if split else ALWAYS)
    # Vertices renumbered in the order the faces first use them: each cell's vertices one block (a driver
    # that shades an indexed draw's whole index range then shades only the cell's own)
    used, first = np.unique(faces.ravel(), return_index=True)
    vorder = np.r_[used[np.argsort(first)], np.setdiff1d(np.arange(len(mesh.positions)), used)]
    renum = np.empty(len(vorder), np.int64)
    renum[vorder] = np.arange(len(vorder))
    faces = renum[faces].astype(mesh.faces.dtype)
    mesh = dataclasses.replace(mesh, positions=mesh.positions[vorder], uvs=mesh.uvs[vorder],
                               shade=mesh.shade[vorder])
    return dataclasses.replace(mesh, faces=np.ascontiguousarray(faces), cell_faces=offsets,
                               cell_bounds=np.asarray(bounds, np.float32),
                               cell_squares=np.asarray(squares, np.float32),
                               cell_bands=np.asarray(bands, np.int8))


def _images(lo: float, hi: float, size: float, pad: float) -> list[tuple[float, float]]:
    """The reflections (sign, offset) of the interval [lo, hi] of [0, size] under mirrored repetition
    (x -> offset + sign x with offset = 2 m size: sign +1 for an even number of reflections, -1 for an odd one)
    that meet (-pad, size + pad); the identity first."""
    out = []
    reach = math.ceil(pad / size) + 1
    for m in range(-reach, reach + 1):
        for sign in (1.0, -1.0):
            a, b = (2 * m * size + lo, 2 * m * size + hi) if sign > 0 else (2 * m * size - hi, 2 * m * size - lo)
            if b > -pad and a < size + pad:
                out.append((sign, 2 * m * size))
    out.sort(key=lambda t: (t != (1.0, 0.0), t[1], t[0]))
    return out


def _mirrored(chunks: list[TexturedMesh], extents: list[tuple[float, float, float, float]], w_m: float, h_m: float,
              pad_m: float) -> list[TexturedMesh]:
    """The layout's chunks reflected across its edges out to ``pad_m`` (see the module docstring): every
    image of every chunk under the mirrored repetition of [0, w] x [0, h], but the chunk itself."""
    out = []
    for mesh, (x0, x1, y0, y1) in zip(chunks, extents):
        for sx, ax in _images(x0, x1, w_m, pad_m):
            for sy, ay in _images(y0, y1, h_m, pad_m):
                if (sx, ax, sy, ay) == (1.0, 0.0, 1.0, 0.0):
                    continue
                pos = mesh.positions.astype(np.float64)
                pos[:, 0] = ax + sx * pos[:, 0]
                pos[:, 1] = ay + sy * pos[:, 1]
                faces = mesh.faces if sx * sy > 0 else np.ascontiguousarray(mesh.faces[:, ::-1])
                bounds = squares = None
                if mesh.cell_bounds is not None:   # the boxes reflected: a min becomes a max where the sign is -1
                    bounds = mesh.cell_bounds.astype(np.float64)
                    squares = mesh.cell_squares.astype(np.float64).reshape(-1, 2, 2)
                    for axis, sign, off in ((0, sx, ax), (1, sy, ay)):
                        for box in (bounds, squares):
                            ends = off + sign * box[:, :, axis]
                            box[:, 0, axis], box[:, 1, axis] = ends.min(axis=1), ends.max(axis=1)
                    bounds, squares = bounds.astype(np.float32), squares.reshape(-1, 4).astype(np.float32)
                out.append(TexturedMesh(pos.astype(np.float32), mesh.uvs, mesh.shade, faces, mesh.texture,
                                        mesh.labels, repeat=mesh.repeat, mirror=True, cell_faces=mesh.cell_faces,
                                        cell_bounds=bounds, cell_squares=squares, cell_bands=mesh.cell_bands))
    return out


#: texels on a side of the padding's repeated texture
_PAD_TEXELS = 512


def pad_texture(layout: Layout, texels: int = _PAD_TEXELS) -> np.ndarray:
    """(texels, texels, 3) uint8 seamless neutral ground: the median colour of the layout's outermost
    ``PAD`` texels of ground, mottled by a few percent (low-pass noise on a torus, so it tiles)."""
    g = layout.ground_rgb
    ring = np.concatenate([g[:PAD].reshape(-1, 3), g[-PAD:].reshape(-1, 3), g[:, :PAD].reshape(-1, 3),
                           g[:, -PAD:].reshape(-1, 3)])
    base = np.median(ring, axis=0)
    rng = np.random.default_rng(20240521)
    f = np.fft.fftfreq(texels)
    r2 = f[:, None] ** 2 + f[None, :] ** 2
    field = np.zeros((texels, texels))
    for sigma, amp in ((0.004, 1.0), (0.02, 0.5), (0.12, 0.25)):   # broad blotches to fine grain
        noise = np.fft.fft2(rng.standard_normal((texels, texels)))
        layer = np.real(np.fft.ifft2(noise * np.exp(-r2 / (2 * sigma ** 2))))
        field += amp * layer / max(float(layer.std()), 1e-12)
    field /= max(float(field.std()), 1e-12)
    tex = base[None, None, :] * (1.0 + 0.06 * field[..., None])
    return np.clip(np.round(tex), 0, 255).astype(np.uint8)


def _pad_mesh(layout: Layout, w_m: float, h_m: float, pad_m: float, terrain: Terrain | None = None) -> TexturedMesh:
    """One mesh covering [-pad, w + pad] x [-pad, h + pad] outside [0, w] x [0, h] (eight quads; grids over a
    ``terrain`` that is not flat, at the height of the layout's nearest edge, so it meets the layout's ground)
    with the repeated :func:`pad_texture` at the layout's ground resolution."""
    tex = pad_texture(layout)
    labels = np.full(tex.shape[:2], CLASS_ID["void"], np.uint8)
    period = tex.shape[0] * float(layout.ground_mpp)
    xs = [(-pad_m, 0.0), (0.0, w_m), (w_m, w_m + pad_m)]
    ys = [(-pad_m, 0.0), (0.0, h_m), (h_m, h_m + pad_m)]
    edge = None if terrain is None or terrain.flat else (
        lambda x, y: terrain.height(np.clip(x, 0.0, w_m), np.clip(y, 0.0, h_m)))
    parts = [_grid_quad(a, b, c, d, terrain, edge)
             for i, (a, b) in enumerate(xs) for j, (c, d) in enumerate(ys) if (i, j) != (1, 1)]
    starts = np.cumsum([0] + [len(p) for p, _ in parts[:-1]])
    pos = np.concatenate([p for p, _ in parts])
    faces = np.concatenate([f + k for (_, f), k in zip(parts, starts)])
    uv = pos[:, :2] / period                 # anchored to the map: the texture runs on across the quads
    return TexturedMesh(pos.astype(np.float32), uv.astype(np.float32), np.ones(len(pos), np.float32),
                        faces.astype(np.uint32), tex, labels, repeat=True)


def build_occluders(cars: Sequence[Car], persons: Sequence[Person], obstacles: Sequence[Obstacle],
                    sun: np.ndarray, terrain: Terrain | None = None) -> TexturedMesh | None:
    """One textured mesh of an episode's extra objects (``sun``: see :func:`sun_direction`), standing on
    ``terrain`` where it is not flat; None if there are none."""
    if not (cars or persons or obstacles):
        return None
    mb = _MeshBuilder(np.asarray(sun, dtype=np.float64), atlas_width=_OCCLUDER_ATLAS_W)
    for k, c in enumerate(cars):
        _add_car(mb, c, ("occluder", k))
    for k, p in enumerate(persons):
        _add_person(mb, p, k)
    for k, o in enumerate(obstacles):
        _add_obstacle(mb, o, k)
    if terrain is not None and not terrain.flat:
        _stand_on(mb, 0, terrain)
    return mb.build(None)


# --- mesh assembly ----------------------------------------------------------------------------------------
@dataclass
class _Ground:
    """A chunk's padded ground region and its surface (one quad, or a grid over a terrain)."""

    texture: np.ndarray   # (H, W, 3), W % 4 == 0
    labels: np.ndarray    # (H, W)
    positions: np.ndarray  # (n, 3) the surface's vertices
    texel_rc: np.ndarray  # (n, 2) (column, row) of the vertices in the region, texel-edge units
    faces: np.ndarray     # (m, 3) its triangles, counter-clockwise from above
    extent: tuple         # x0, x1, y0, y1


def _ground_region(layout: Layout, c0: int, rb0: int, cpx: int, terrain: Terrain | None = None) -> _Ground:
    """Ground of the chunk whose lower-left texel is column ``c0``, row ``rb0`` counted from the south edge:
    one quad, or over a ``terrain`` that is not flat a grid of about :data:`GROUND_STEP_M` on its heights."""
    mpp = float(layout.ground_mpp)
    rows, cols = layout.ground_labels.shape
    c1, rb1 = min(c0 + cpx, cols), min(rb0 + cpx, rows)
    r0, r1 = rows - rb1, rows - rb0                        # numpy rows (north-up)
    width = _round_up(c1 - c0 + 2 * PAD, 4)
    rr = np.clip(np.arange(r0 - PAD, r1 + PAD), 0, rows - 1)
    cc = np.clip(np.arange(c0 - PAD, c0 - PAD + width), 0, cols - 1)
    x0, x1 = c0 * mpp, c1 * mpp
    y0, y1 = layout.height_m - r1 * mpp, layout.height_m - r0 * mpp
    u0, u1, t0, t1 = PAD, PAD + c1 - c0, PAD, PAD + r1 - r0
    pos, faces = _grid_quad(x0, x1, y0, y1, terrain)
    texel_rc = np.stack([u0 + (pos[:, 0] - x0) / (x1 - x0) * (u1 - u0),
                         t1 + (pos[:, 1] - y0) / (y1 - y0) * (t0 - t1)], axis=1)
    return _Ground(np.ascontiguousarray(layout.ground_rgb[rr][:, cc]),
                   np.ascontiguousarray(layout.ground_labels[rr][:, cc]).astype(np.uint8), pos, texel_rc, faces,
                   (x0, x1, y0, y1))


def _grid_quad(x0: float, x1: float, y0: float, y1: float, terrain: Terrain | None,
               height=None) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) and triangles (m, 3), counter-clockwise from above, of the rectangle [x0, x1] x [y0, y1]:
    its four corners at z 0 (two triangles) where ``terrain`` is None or flat, else a grid of squares of about
    :data:`GROUND_STEP_M` whose vertices lie on ``height(x, y)`` (default: the terrain's), with more lines of
    vertices along those of the terrain's road crown (:class:`satloc_env.world.terrain.Crown`)."""
    if terrain is None or terrain.flat:
        return (np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]]),
                np.array([[0, 1, 2], [0, 2, 3]]))

    def axis(a: float, b: float, lines) -> np.ndarray:
        ticks = np.linspace(a, b, max(1, math.ceil((b - a) / GROUND_STEP_M - 1e-9)) + 1)
        if lines is None or height is not None:
            return ticks
        inner = np.asarray(lines, np.float64)
        inner = inner[(inner > a + 1e-3) & (inner < b - 1e-3)]
        if not len(inner):
            return ticks
        # the grid's own lines give way to the crown's within half a step of one (the hills between lines up
        # to 1.5 steps apart depart from their chords by about 2 cm at relief 1 m), so that a street adds about
        # two lines, not three
        keep = np.ones(len(ticks), bool)
        keep[1:-1] = np.abs(ticks[1:-1, None] - inner[None, :]).min(axis=1) >= GROUND_STEP_M / 2
        ticks = np.unique(np.r_[ticks[keep], inner])
        return ticks[np.r_[True, np.diff(ticks) > 1e-3]]   # a line within a millimetre of a tick: the tick

    crown = terrain.crown
    xs = axis(x0, x1, None if crown is None else crown.xlines)
    ys = axis(y0, y1, None if crown is None else crown.ylines)
    nx, ny = len(xs) - 1, len(ys) - 1
    gx, gy = np.meshgrid(xs, ys)   # (ny + 1, nx + 1)
    gz = (height or terrain.height)(gx, gy)
    pos = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)
    a = (np.arange(ny)[:, None] * (nx + 1) + np.arange(nx)[None, :]).ravel()          # lower-left corners
    b, c, d = a + 1, a + nx + 2, a + nx + 1
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return pos, faces


class _MeshBuilder:
    """Collects triangles whose UVs are fractions of a texture *patch*, then packs the patches into an atlas
    (shelf packing, ``PAD`` texels of replicated edge around each) and emits one :class:`TexturedMesh`."""

    def __init__(self, sun: np.ndarray, atlas_width: int):
        self.sun = sun
        self.atlas_width = atlas_width
        self.max_patch_width = atlas_width - 2 * PAD
        self._patches: list[tuple[np.ndarray, np.ndarray]] = []
        self._pos: list[np.ndarray] = []
        self._st: list[np.ndarray] = []
        self._patch_of: list[np.ndarray] = []
        self._shade: list[np.ndarray] = []
        self._faces: list[np.ndarray] = []
        self._n = 0
        #: the square of CELL_M (column, row) and the level-of-detail band (ALWAYS, NEAR, FAR, INSIDE) of the
        #: triangles added next
        self.square: tuple[int, int] = (0, 0)
        self.band = ALWAYS
        self._keys: list[np.ndarray] = []   # per call that added triangles: (square column, row, band) per face

    def add_patch(self, rgb: np.ndarray, label: int) -> int:
        """Register a texture patch (H, W, 3) whose texels all have class ``label``; returns its id. A patch wider
        than the atlas (an object on a narrow chunk at the ground's edge) widens it: the ground's region keeps its
        top left corner, its last column repeated to the right."""
        h, w = rgb.shape[:2]
        if w > self.max_patch_width:
            if w + 2 * PAD > MAX_TEXTURE:
                raise ValueError(f"patch of width {w} does not fit a {MAX_TEXTURE}-texel atlas")
            self.atlas_width, self.max_patch_width = w + 2 * PAD, w
        self._patches.append((np.ascontiguousarray(rgb, dtype=np.uint8), np.full((h, w), label, np.uint8)))
        return len(self._patches) - 1

    def add_polygon_faces(self, pos: np.ndarray, st: np.ndarray, faces: np.ndarray, patch: int,
                          shade: float | None = None) -> None:
        """Add triangles (``faces`` into ``pos``) sharing one flat normal; ``st`` are (column, row) fractions
        of ``patch``. The shading factor is ``shade``, else it comes from the first triangle's normal."""
        p = np.asarray(pos, dtype=np.float64)
        if shade is None:
            a, b, c = p[faces[0]]
            n = np.cross(b - a, c - a)
            norm = np.linalg.norm(n)
            shade = _AMBIENT + (1 - _AMBIENT) * max(0.0, float(n @ self.sun) / norm) if norm > 0 else _AMBIENT
        self._append(p, st, faces, patch, np.full(len(p), shade))

    def add_quads(self, quads: np.ndarray, st: np.ndarray, patch: int) -> None:
        """Add quads (K, 4, 3), corners counter-clockwise seen from outside, with patch fractions (K, 4, 2);
        each quad gets its own flat shading factor."""
        q = np.asarray(quads, dtype=np.float64)
        n = np.cross(q[:, 2] - q[:, 0], q[:, 3] - q[:, 1])   # diagonals: robust to one degenerate edge
        norm = np.linalg.norm(n, axis=1)
        cos = np.where(norm > 0, (n @ self.sun) / np.maximum(norm, 1e-12), 0.0)
        shade = _AMBIENT + (1 - _AMBIENT) * np.maximum(cos, 0.0)
        k = len(q)
        faces = (np.arange(k)[:, None, None] * 4 + np.array([[0, 1, 2], [0, 2, 3]])).reshape(-1, 3)
        # a quad on a ring collapsed to a point (a crown's tip) is one triangle: its other one has no area and
        # would only cost the rasterizer its setup
        p = q.reshape(-1, 3)
        area = np.linalg.norm(np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]]), axis=1)
        self._append(p, np.asarray(st).reshape(-1, 2), faces[area > 1e-12], patch, np.repeat(shade, 4))

    def _append(self, pos, st, faces, patch, shade) -> None:
        self._pos.append(pos)
        self._st.append(np.asarray(st, dtype=np.float64))
        self._patch_of.append(np.full(len(pos), patch))
        self._shade.append(shade)
        self._faces.append(np.asarray(faces) + self._n)
        self._n += len(pos)
        self._keys.append(np.tile(np.array([*self.square, self.band], np.int64), (len(self._faces[-1]), 1)))

    def cell_keys(self) -> np.ndarray:
        """(faces added, 3) int64: each face's square (column, row) and band, in the order added."""
        return np.concatenate(self._keys + [np.zeros((0, 3), np.int64)])

    def build(self, ground: _Ground | None) -> TexturedMesh:
        """Pack the atlas below ``ground``'s region (if any) and emit the mesh; the ground quad's triangles
        come last so that, drawn in order, objects in front of the ground get depth-tested first."""
        top = 0 if ground is None else ground.texture.shape[0]
        sizes = [t.shape[:2] for t, _ in self._patches]
        width = self.atlas_width
        offsets, strip_h = _pack_shelves(sizes, width)
        while top + strip_h > MAX_TEXTURE and width < MAX_TEXTURE:   # too tall for GL: a wider atlas, the
            width = min(MAX_TEXTURE, width + self.atlas_width)          # ground in its top left corner
            offsets, strip_h = _pack_shelves(sizes, width)
        if top + strip_h > MAX_TEXTURE:
            raise ValueError(f"a chunk's textures do not fit a {MAX_TEXTURE} x {MAX_TEXTURE} atlas")
        height = top + strip_h
        tex = np.zeros((height, width, 3), np.uint8)
        lab = np.zeros((height, width), np.uint8)
        if ground is not None:   # (right of a narrower ground: its last column, as the narrow atlas's clamp gave)
            gw = ground.texture.shape[1]
            tex[:top] = np.pad(ground.texture, ((0, 0), (0, width - gw), (0, 0)), mode="edge")
            lab[:top] = np.pad(ground.labels, ((0, 0), (0, width - gw)), mode="edge")
        for (rgb, labels), (r, c) in zip(self._patches, offsets):
            h, w = labels.shape
            r0, c0 = top + r, c
            tex[r0:r0 + h + 2 * PAD, c0:c0 + w + 2 * PAD] = cv2.copyMakeBorder(
                rgb, PAD, PAD, PAD, PAD, cv2.BORDER_REPLICATE)
            lab[r0:r0 + h + 2 * PAD, c0:c0 + w + 2 * PAD] = np.pad(labels, PAD, mode="edge")

        pos = self._pos + ([ground.positions] if ground is not None else [])
        faces = self._faces + ([ground.faces + self._n] if ground is not None else [])
        shade = self._shade + ([np.ones(len(ground.positions))] if ground is not None else [])
        if self._patches:
            sizes = np.array([lb.shape for _, lb in self._patches], dtype=np.float64)       # (P, 2): h, w
            origin = np.array(offsets, dtype=np.float64) + PAD + np.array([top, 0.0])      # (P, 2): row, col
            pid = np.concatenate(self._patch_of)
            st = np.concatenate(self._st)
            col = origin[pid, 1] + st[:, 0] * sizes[pid, 1]
            row = origin[pid, 0] + st[:, 1] * sizes[pid, 0]
            cr = [np.stack([col, row], axis=1)]
        else:
            cr = []
        if ground is not None:
            cr.append(ground.texel_rc)
        cr = np.concatenate(cr)
        uvs = np.stack([cr[:, 0] / width, 1.0 - cr[:, 1] / height], axis=1)
        return TexturedMesh(
            positions=np.concatenate(pos).astype(np.float32),
            uvs=uvs.astype(np.float32),
            shade=np.concatenate(shade).astype(np.float32),
            faces=np.concatenate(faces).astype(np.uint32),
            texture=tex,
            labels=lab,
        )


def _pack_shelves(sizes: list[tuple[int, int]], width: int) -> tuple[list[tuple[int, int]], int]:
    """Shelf-pack rectangles (h, w), each grown by ``PAD`` on all sides, into a strip ``width`` wide.
    Returns the (row, col) of each padded rectangle and the strip height (a multiple of 4)."""
    order = sorted(range(len(sizes)), key=lambda i: -sizes[i][0])
    offsets: list[tuple[int, int]] = [(0, 0)] * len(sizes)
    shelf_top, shelf_h, x = 0, 0, 0
    for i in order:
        h, w = sizes[i][0] + 2 * PAD, sizes[i][1] + 2 * PAD
        if x + w > width:
            shelf_top, shelf_h, x = shelf_top + shelf_h, 0, 0
        offsets[i] = (shelf_top, x)
        x += w
        shelf_h = max(shelf_h, h)
    return offsets, _round_up(shelf_top + shelf_h, 4)


def _round_up(n: int, k: int) -> int:
    return -(-n // k) * k


# --- geometry primitives ----------------------------------------------------------------------------------
def _ccw(poly: np.ndarray) -> np.ndarray:
    """The polygon (N, 2) in counter-clockwise order."""
    x, y = poly[:, 0], poly[:, 1]
    area2 = float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
    return poly if area2 >= 0 else poly[::-1]


def _triangulate(poly: np.ndarray) -> np.ndarray:
    """Ear-clipping triangulation (M, 3) of a simple counter-clockwise polygon (N, 2)."""
    idx = list(range(len(poly)))
    tris = []

    def cross(o, a, b) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    while len(idx) > 3:
        for k in range(len(idx)):
            i0, i1, i2 = idx[k - 1], idx[k], idx[(k + 1) % len(idx)]
            a, b, c = poly[i0], poly[i1], poly[i2]
            if cross(a, b, c) <= 1e-12:
                continue
            if any(cross(a, b, poly[j]) >= 0 and cross(b, c, poly[j]) >= 0 and cross(c, a, poly[j]) >= 0
                   for j in idx if j not in (i0, i1, i2)):
                continue
            tris.append((i0, i1, i2))
            del idx[k]
            break
        else:  # no ear: a degenerate (collinear or self-touching) remainder, closed with a fan
            tris.extend((idx[0], idx[m], idx[m + 1]) for m in range(1, len(idx) - 1))
            return np.array(tris, dtype=np.int64)
    tris.append(tuple(idx))
    return np.array(tris, dtype=np.int64)


def _bbox_st(poly: np.ndarray) -> np.ndarray:
    """Patch fractions (column, row) of polygon points mapped onto their bounding box, north up."""
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    span = np.maximum(hi - lo, 1e-9)
    return np.stack([(poly[:, 0] - lo[0]) / span[0], (hi[1] - poly[:, 1]) / span[1]], axis=1)


def _add_prism(mb: _MeshBuilder, footprint: np.ndarray, z0: float, z1: float, texel: float, label: int,
               wall_texture: Callable[[list[tuple[int, float]], int], np.ndarray],
               top_texture: Callable[[int, int], np.ndarray] | None, top_shade: float | None = None) -> None:
    """Vertical walls of ``footprint`` (made counter-clockwise) from ``z0`` to ``z1`` plus an optional flat top.

    The walls are unrolled into strips of texture ``texel`` metres per texel: walls longer than an atlas row
    are split, consecutive walls are grouped into strips that fit a row, and ``wall_texture(walls, height_px)``
    paints each strip, ``walls`` being its segments as (footprint edge index, length in metres), left to right;
    the strip is ``ceil(total length / texel)`` texels wide. ``top_texture(h_px, w_px)`` paints the top,
    shaded by the sun unless ``top_shade`` gives its factor.
    """
    fp = _ccw(np.asarray(footprint, dtype=np.float64))
    max_len = (mb.max_patch_width - 1) * texel
    pts, edge_of = [], []
    for e, (a, b) in enumerate(zip(fp, np.roll(fp, -1, axis=0))):
        n = max(1, math.ceil(np.linalg.norm(b - a) / max_len))
        pts.extend(a + (b - a) * (k / n) for k in range(n))
        edge_of.extend([e] * n)
    pts = np.array(pts)
    ends = np.roll(pts, -1, axis=0)
    lengths = np.linalg.norm(ends - pts, axis=1)
    h_px = _round_px(z1 - z0, texel)
    start = 0
    while start < len(pts):
        stop, total = start, 0.0
        while stop < len(pts) and (stop == start or total + lengths[stop] <= max_len):
            total += lengths[stop]
            stop += 1
        segs = lengths[start:stop]
        if total <= 0:
            start = stop
            continue
        rgb = wall_texture([(edge_of[i], float(lengths[i])) for i in range(start, stop)], h_px)
        patch = mb.add_patch(rgb, label)
        s = np.concatenate([[0.0], np.cumsum(segs)]) / total
        a, b = pts[start:stop], ends[start:stop]
        quads = np.stack([np.c_[a, np.full(len(a), z0)], np.c_[b, np.full(len(a), z0)],
                          np.c_[b, np.full(len(a), z1)], np.c_[a, np.full(len(a), z1)]], axis=1)
        st = np.stack([np.c_[s[:-1], np.ones(len(a))], np.c_[s[1:], np.ones(len(a))],
                       np.c_[s[1:], np.zeros(len(a))], np.c_[s[:-1], np.zeros(len(a))]], axis=1)
        mb.add_quads(quads, st, patch)
        start = stop
    if top_texture is not None:
        span = fp.max(axis=0) - fp.min(axis=0)
        h, w = (max(2, min(math.ceil(v / texel), mb.max_patch_width)) for v in (span[1], span[0]))
        patch = mb.add_patch(top_texture(h, w), label)
        mb.add_polygon_faces(np.c_[fp, np.full(len(fp), z1)], _bbox_st(fp), _triangulate(fp), patch, top_shade)


def _add_loft(mb: _MeshBuilder, rings: list[np.ndarray], patch: int, top_patch: int | None = None) -> None:
    """Surface through ``rings`` (each (n, 3), CCW from above, bottom to top); a ring may collapse to a point.
    The patch is unrolled around the rings (column) and from the top ring (row 0) down to the bottom one;
    ``top_patch`` closes the top ring with a flat cap."""
    r = np.asarray(rings, dtype=np.float64)                     # (R, n, 3)
    nr, n = r.shape[:2]
    ref = r[np.argmax(np.ptp(r[:, :, 0], axis=1))]             # the widest ring sets the column fractions
    seg = np.linalg.norm(np.roll(ref, -1, axis=0) - ref, axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)]) / seg.sum()
    slant = np.linalg.norm(np.diff(r.mean(axis=1), axis=0), axis=1) + np.abs(
        np.diff(np.linalg.norm(r - r.mean(axis=1, keepdims=True), axis=2).mean(axis=1)))
    t = 1.0 - np.concatenate([[0.0], np.cumsum(slant)]) / slant.sum()
    j0, j1 = np.arange(n), (np.arange(n) + 1) % n
    quads, st = [], []
    for i in range(nr - 1):
        lo, hi = r[i], r[i + 1]
        quads.append(np.stack([lo[j0], lo[j1], hi[j1], hi[j0]], axis=1))
        st.append(np.stack([np.c_[s[:-1], np.full(n, t[i])], np.c_[s[1:], np.full(n, t[i])],
                            np.c_[s[1:], np.full(n, t[i + 1])], np.c_[s[:-1], np.full(n, t[i + 1])]], axis=1))
    mb.add_quads(np.concatenate(quads), np.concatenate(st), patch)
    if top_patch is not None:
        cap = r[-1]
        mb.add_polygon_faces(cap, _bbox_st(cap[:, :2]), _triangulate(cap[:, :2]), top_patch)


def _rect(center: Sequence[float], yaw: float, length: float, width: float, dx: float = 0.0) -> np.ndarray:
    """Corners (4, 2) of a ``length`` x ``width`` rectangle centred ``dx`` ahead of ``center`` along ``yaw``,
    CCW starting at the rear right corner (so the edges are: right side, front, left side, rear)."""
    c, s = math.cos(yaw), math.sin(yaw)
    local = np.array([[-length / 2, -width / 2], [length / 2, -width / 2],
                      [length / 2, width / 2], [-length / 2, width / 2]]) + [dx, 0.0]
    return local @ np.array([[c, s], [-s, c]]) + np.asarray(center, dtype=np.float64)


def _ring(center: Sequence[float], z: float, radius: np.ndarray | float, n: int, phase: float = 0.0) -> np.ndarray:
    """``n`` points (n, 3) on a horizontal circle (radii may vary per point), CCW from above."""
    a = phase + 2 * math.pi * np.arange(n) / n
    rad = np.broadcast_to(np.asarray(radius, dtype=np.float64), (n,))
    return np.stack([center[0] + rad * np.cos(a), center[1] + rad * np.sin(a), np.full(n, z)], axis=1)


# --- objects ----------------------------------------------------------------------------------------------
def _rng(*key) -> np.random.Generator:
    """Deterministic generator for an object identified by ``key`` (strings and ints)."""
    return np.random.default_rng([sum(map(ord, k)) if isinstance(k, str) else int(k) for k in key])


def _add_building(mb: _MeshBuilder, b: Building, index: int, layout: Layout | None = None) -> None:
    """A building: walls from the facade painters, from ``base`` up; its roof painted in ``roof_rgb``, or,
    with ``roof_from_ground``, the layout's ground image over the footprint's bounding box (the roof as the
    imagery shows it, unshaded: the imagery has its light already). ``roof`` ``gabled`` on a rectangular
    footprint: walls to the eaves, two slopes up to a ridge along the long axis at ``height``, and the gable
    ends (:func:`_add_gable_roof`); any other footprint keeps a flat roof, with the furniture
    :func:`satloc_env.world.furniture.roof_parts` puts on it."""
    rng = _rng("building", index, b.facade)
    style = _FACADE_STYLES[b.facade % len(_FACADE_STYLES)]
    roof = np.asarray(b.roof_rgb, dtype=np.float32)
    fp = np.asarray(b.footprint, dtype=np.float64)
    top = lambda h, w: _paint(rng, roof, h, w)  # noqa: E731
    if b.roof_from_ground and layout is not None:
        top = lambda h, w: _ground_crop(layout, fp, h, w)  # noqa: E731
    base, height = float(b.base), float(b.height)
    # a roof from the imagery stays flat: the picture shows it from above already, light and all
    gable = _gable(fp, base, height) if b.roof == "gabled" and not b.roof_from_ground else None
    walls = lambda segs, h: _facade_texture(rng, style, [length for _, length in segs], h, _FACADE_M)  # noqa: E731
    if b.style_seed is not None:         # a facade of its own (satloc_env.world.variety)
        own = facade_params(int(b.style_seed), city=height - base > 10.0)
        walls = lambda segs, h: facade_texture(rng, own, [length for _, length in segs], h, _FACADE_M)  # noqa: E731
    if gable is None:
        _add_prism(mb, fp, base, height, _FACADE_M, CLASS_ID["building"], walls, top,
                   top_shade=1.0 if b.roof_from_ground and layout is not None else None)
        unit_rng = _rng("roof furniture", index)   # its own: the building's textures stay as they were
        for part in roof_parts(b):
            rgb = np.asarray(part.rgb, np.float32)
            _add_prism(mb, part.footprint, part.z0, part.z1, part.texel, CLASS_ID["building"],
                       lambda segs, h, part=part: part_paint(unit_rng, part, segs, h),
                       lambda h, w, rgb=rgb: _paint(unit_rng, rgb, h, w))
        return
    _add_prism(mb, fp, base, gable[0], _FACADE_M, CLASS_ID["building"], walls, None)
    _add_gable_roof(mb, gable, top, walls)


def _gable(fp: np.ndarray, base: float, height: float):
    """(eave height, ridge height, the rectangle's corners CCW starting on a long side) of a gabled roof
    over the footprint ``fp`` when it is a rectangle (4 corners, right angles within 5 degrees) and high
    enough; else None. The rise is 0.4 x the short side, at most half of the building's height above its
    base."""
    p = _ccw(fp)
    if len(p) != 4:
        return None
    e = np.roll(p, -1, axis=0) - p
    lengths = np.linalg.norm(e, axis=1)
    if lengths.min() <= 0.5:
        return None
    if not right_angled(p):
        return None
    if lengths[0] < lengths[1]:          # start on a long side
        p = np.roll(p, -1, axis=0)
    rise = min(0.4 * float(lengths.min()), 0.5 * (height - base))
    if rise < 0.5:
        return None
    return height - rise, height, p


def _add_gable_roof(mb: _MeshBuilder, gable, top, walls) -> None:
    """The two slopes (painted by ``top``) and the two gable ends (by ``walls``) of :func:`_gable`'s roof."""
    eave, ridge, (a, b, c, d) = gable      # a-b and c-d the eaves, b-c and d-a the gable ends
    r_bc, r_da = np.r_[(b + c) / 2, ridge], np.r_[(d + a) / 2, ridge]
    a3, b3, c3, d3 = (np.r_[q, eave] for q in (a, b, c, d))
    slope_len = float(np.linalg.norm(r_bc - b3))
    long_len = float(np.linalg.norm(b - a))
    h_px = max(2, min(math.ceil(slope_len / _FACADE_M), mb.max_patch_width))
    w_px = max(2, min(math.ceil(long_len / _FACADE_M), mb.max_patch_width))
    st = np.array([[[0, 1], [1, 1], [1, 0], [0, 0]]] * 2, np.float64)
    mb.add_quads(np.array([[a3, b3, r_bc, r_da], [c3, d3, r_da, r_bc]]), st,
                 mb.add_patch(top(h_px, w_px), CLASS_ID["building"]))
    for p, q, r in ((b3, c3, r_bc), (d3, a3, r_da)):
        width = float(np.linalg.norm(q - p))
        patch = mb.add_patch(walls([(0, width)], max(2, math.ceil((ridge - eave) / _FACADE_M))), CLASS_ID["building"])
        mb.add_polygon_faces(np.array([p, q, r]), np.array([[0, 1], [1, 1], [0.5, 0]], np.float64),
                             np.array([[0, 1, 2]]), patch)


def _ground_crop(layout: Layout, poly: np.ndarray, h: int, w: int) -> np.ndarray:
    """(h, w, 3) the layout's ground image over ``poly``'s bounding box (north up), resampled bilinearly."""
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    mpp = float(layout.ground_mpp)
    # pixel-centre coordinates of the (h, w) texels' centres in the ground raster
    cols = (lo[0] + (np.arange(w) + 0.5) * (hi[0] - lo[0]) / w) / mpp - 0.5
    rows = (layout.height_m - (hi[1] - (np.arange(h) + 0.5) * (hi[1] - lo[1]) / h)) / mpp - 0.5
    mx, my = np.meshgrid(cols.astype(np.float32), rows.astype(np.float32))
    return cv2.remap(layout.ground_rgb, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _add_tree(mb: _MeshBuilder, t: Tree, index: int) -> None:
    rng = _rng("tree", index)
    r, zb, zt = float(t.canopy_radius), float(t.canopy_bottom), float(t.canopy_top)
    hc = max(zt - zb, 0.1)
    trunk_r = 0.08 + 0.05 * r
    trunk = np.array(_ring(t.center, 0.0, trunk_r, 6)[:, :2])
    species = SPECIES.get(int(t.species))          # a species of its own (satloc_env.world.variety), else None
    if species is not None:
        mb.band = NEAR                             # this detail near the camera, the coarse tree below beyond
    _add_prism(mb, trunk, 0.0, zb + 0.3 * hc, _BARK_M, CLASS_ID["tree"],
               lambda walls, h: _bark_texture(rng, h, _round_px(sum(ln for _, ln in walls), _BARK_M)), None)
    n = 10
    profile = [(0.0, 0.0), (0.12, 0.75), (0.4, 1.0), (0.72, 0.85), (0.92, 0.45), (1.0, 0.0)]
    if species is not None:
        n, profile = 8, species["profile"]
    bark = len(mb._patches) - 1                    # the trunk's walls made one patch (a short strip)
    phase = rng.uniform(0, 2 * math.pi)
    rings = [_ring(t.center, zb + f * hc, r * k * rng.uniform(0.85, 1.1, n), n, phase) for f, k in profile]
    rows, cols = _round_px(hc * 1.6, _FOLIAGE_M), _patch_cols(mb, 2 * math.pi * r, _FOLIAGE_M)
    if species is None:
        leaves = _foliage_texture(rng, rows, cols, t.shade)
    else:
        leaves = leaf_texture(rng, rows, cols, species["leaf"][int(t.shade) % len(species["leaf"])])
    crown = mb.add_patch(leaves, CLASS_ID["tree"])
    _add_loft(mb, rings, crown)
    if species is not None:
        # Beyond LOD_M (where a crown is a few tens of pixels wide): the same textures on a three-sided trunk and a
        # four-sided crown through the profile's base, widest ring and top two rings
        mb.band = FAR
        _add_loft(mb, [_ring(t.center, 0.0, trunk_r, 3, phase), _ring(t.center, zb + 0.3 * hc, trunk_r, 3, phase)],
                  bark)
        widest = max(range(len(profile)), key=lambda i: profile[i][1])
        keep = sorted({0, widest, len(profile) - 2, len(profile) - 1})
        _add_loft(mb, [_ring(t.center, zb + profile[i][0] * hc, r * profile[i][1], 4, phase) for i in keep], crown)
        mb.band = ALWAYS


def _add_car(mb: _MeshBuilder, c: Car, key: tuple) -> None:
    rng = _rng("car", *key)
    length, width, height = float(c.length), float(c.width), float(c.height)
    paint = np.asarray(c.rgb, dtype=np.float32)
    shape = BODIES.get(int(c.body))
    if shape is None:                          # variety 0's one shape
        shape, roof_dx = {"cab": 0.52, "dx": 0.06, "roof": 0.7, "body": 0.55}, 0.09
    else:                                      # a body of its own (satloc_env.world.variety): the roof set back as
        roof_dx = shape["dx"] + 0.1 * (1 - shape["roof"])     # much as the windscreen slopes
        mb.band = INSIDE                       # in the reflections beyond the layout's edge only near the car
    z_body = shape["body"] * height
    body = _rect(c.center, c.yaw, length, width)
    own = c.body in BODIES
    _add_prism(mb, body, 0.12, z_body, _CAR_M, CLASS_ID["car"],
               lambda walls, h: _car_body_texture(rng, paint, walls, h, z_body - 0.12, own),
               lambda h, w: _paint(rng, paint, h, w))
    cab_len, cab_w = shape["cab"] * length, 0.88 * width
    lower = _rect(c.center, c.yaw, cab_len, cab_w, dx=-shape["dx"] * length)
    upper = _rect(c.center, c.yaw, cab_len * shape["roof"], cab_w * 0.92,
                  dx=-roof_dx * length)
    rings = [np.c_[lower, np.full(4, z_body)], np.c_[upper, np.full(4, height)]]
    side = _car_cabin_texture(rng, paint, _round_px(height - z_body, _CAR_M),
                              _patch_cols(mb, 2 * (cab_len + cab_w), _CAR_M), [cab_len, cab_w, cab_len, cab_w])
    top = _paint(rng, paint, _round_px(cab_w, _CAR_M), _patch_cols(mb, cab_len, _CAR_M))
    _add_loft(mb, rings, mb.add_patch(side, CLASS_ID["car"]), mb.add_patch(top, CLASS_ID["car"]))
    mb.band = ALWAYS


def _add_furniture(mb: _MeshBuilder, f: Furniture, index: int) -> None:
    """Street furniture (:mod:`satloc_env.world.furniture`): its parts as prisms, class ``obstacle``; no top
    on a part above 2 m (the camera, 1.65 m up, never sees it)."""
    rng = _rng("furniture", index)
    # beyond LOD_M a post or a bin is a pixel or two wide: not drawn; a hedge, metres long, is drawn
    mb.band = ALWAYS if f.kind in ROWS else NEAR
    for part in furniture_parts(f):
        top = None if part.z1 > 2.0 else (lambda h, w, part=part: _paint(rng, np.asarray(part.rgb, np.float32), h, w))
        if part.leaves:
            top = lambda h, w, part=part: leaf_texture(rng, h, w, part.rgb)  # noqa: E731
        _add_prism(mb, part.footprint, part.z0, part.z1, part.texel, CLASS_ID["tree" if part.leaves else "obstacle"],
                   lambda walls, h, part=part: part_paint(rng, part, walls, h), top)
    mb.band = ALWAYS


def _add_person(mb: _MeshBuilder, p: Person, index: int) -> None:
    rng = _rng("person", index)
    r, h = float(p.radius), float(p.height)
    profile = [(0.0, 0.55), (0.45, 0.6), (0.55, 0.85), (0.8, 0.9), (0.84, 0.4), (0.87, 0.45), (0.97, 0.4),
               (1.0, 0.0)]
    rings = [_ring(p.center, f * h, r * k, 8) for f, k in profile]
    rows, cols = _round_px(h, _PERSON_M), _patch_cols(mb, 2 * math.pi * r, _PERSON_M)
    tex = _person_texture(rng, np.asarray(p.rgb, dtype=np.float32), rows, cols)
    _add_loft(mb, rings, mb.add_patch(tex, CLASS_ID["person"]))


def _add_obstacle(mb: _MeshBuilder, o: Obstacle, index: int) -> None:
    rng = _rng("obstacle", index)
    rgb = np.asarray(o.rgb, dtype=np.float32)
    _add_prism(mb, _rect(o.center, o.yaw, float(o.length), float(o.width)), 0.0, float(o.height), _OBSTACLE_M,
               CLASS_ID["obstacle"],
               lambda walls, h: _stripes(rng, rgb, h, _round_px(sum(ln for _, ln in walls), _OBSTACLE_M)),
               lambda h, w: _paint(rng, rgb, h, w))


# --- procedural textures ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class _FacadeStyle:
    wall: tuple[int, int, int]
    brick: bool
    floor_h: float
    win_w: float
    win_h: float
    spacing: float
    glass: tuple[int, int, int]
    frame: tuple[int, int, int]
    door: tuple[int, int, int]
    shopfront: bool


_FACADE_STYLES = (
    _FacadeStyle((196, 186, 170), False, 3.2, 1.3, 1.6, 3.0, (70, 90, 110), (235, 235, 230), (90, 60, 40), False),
    _FacadeStyle((150, 80, 60), True, 3.0, 1.1, 1.5, 2.6, (60, 75, 90), (220, 215, 200), (60, 45, 35), False),
    _FacadeStyle((215, 205, 180), False, 3.4, 1.6, 1.8, 3.4, (85, 105, 125), (90, 90, 95), (70, 70, 75), True),
    _FacadeStyle((120, 125, 130), False, 3.6, 2.4, 2.2, 3.0, (50, 70, 95), (60, 62, 66), (40, 40, 45), True),
    _FacadeStyle((175, 120, 85), True, 3.0, 1.2, 1.5, 2.8, (65, 80, 95), (240, 240, 235), (110, 40, 35), False),
    _FacadeStyle((228, 222, 200), False, 3.1, 1.0, 1.4, 2.4, (75, 85, 100), (120, 80, 50), (80, 50, 30), False),
)


def _to_u8(img: np.ndarray) -> np.ndarray:
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def _round_px(length_m: float, texel: float) -> int:
    """Texels (at least 2) covering ``length_m`` metres at ``texel`` metres per texel."""
    return max(2, math.ceil(length_m / texel))


def _patch_cols(mb: _MeshBuilder, length_m: float, texel: float) -> int:
    """Width in texels of a patch unrolled along ``length_m`` metres, capped to fit ``mb``'s atlas rows."""
    return min(_round_px(length_m, texel), mb.max_patch_width)


def _paint(rng: np.random.Generator, rgb: np.ndarray, h: int, w: int) -> np.ndarray:
    """A surface of colour ``rgb`` with mild mottling."""
    return _to_u8(rgb * (1 + 0.08 * _fbm(rng, h, w, (6, 1), (0.6, 0.4)))[..., None])


def _facade_texture(rng: np.random.Generator, style: _FacadeStyle, segs: list[float], h: int,
                    texel: float) -> np.ndarray:
    """A building facade strip: plaster or brick noise, rows of framed windows per floor on every wall
    segment, a door (or shop windows) on the ground floor of long walls and a darker parapet band."""
    cuts = np.round(np.concatenate([[0.0], np.cumsum(segs)]) / texel).astype(int)
    w = max(2, int(cuts[-1]))
    wall = np.asarray(style.wall, dtype=np.float32)
    shade = 0.14 * _fbm(rng, h, w, (24, 6, 1), (0.45, 0.3, 0.25))
    if style.brick:
        shade += 0.10 * rng.uniform(-1, 1, (h, w)).astype(np.float32)
        shade += 0.06 * np.repeat(rng.uniform(-1, 1, (h // 2 + 1, 1)), 2, axis=0)[:h].astype(np.float32)
    img = wall * (1 + shade)[..., None]
    wall_h = h * texel

    def px_rows(z_lo: float, z_hi: float) -> tuple[int, int]:
        return max(0, int(round((wall_h - z_hi) / texel))), min(h, int(round((wall_h - z_lo) / texel)))

    def fill(r: tuple[int, int], c0: int, c1: int, rgb, frame=None, gain: float = 1.0) -> None:
        r0, r1 = r
        if r1 - r0 < 2 or c1 - c0 < 2:
            return
        g = np.linspace(1.15, 0.8, r1 - r0, dtype=np.float32)[:, None, None] * gain
        img[r0:r1, c0:c1] = np.asarray(rgb, np.float32) * g * (1 + 0.05 * rng.uniform(-1, 1, (r1 - r0, c1 - c0, 1)))
        if frame is not None:
            f = np.asarray(frame, np.float32)
            img[r0, c0:c1] = img[r1 - 1, c0:c1] = f
            img[r0:r1, c0] = img[r0:r1, c1 - 1] = f
            if c1 - c0 >= 8:                                   # mullion
                img[r0:r1, (c0 + c1) // 2] = f

    n_floors = max(1, int((wall_h - 0.5) // style.floor_h))
    for k, seg in enumerate(segs):
        a, b = cuts[k], cuts[k + 1]
        n_win = int(seg // style.spacing)
        centres = a + (np.arange(n_win) + 0.5) * (b - a) / max(n_win, 1)
        half = style.win_w / texel / 2
        for f in range(n_floors):
            z = f * style.floor_h + 0.9
            if z + style.win_h > wall_h - 0.4:
                break
            if f == 0 and style.shopfront and seg > 4.0:
                fill(px_rows(0.3, min(2.8, wall_h - 0.5)), a + 3, b - 3, style.glass, style.frame, 0.8)
                continue
            for cx in centres:
                fill(px_rows(z, z + style.win_h), int(cx - half), int(cx + half), style.glass, style.frame,
                     rng.uniform(0.75, 1.2))
        if seg > 6.0 and not style.shopfront:
            cx = (a + b) // 2 + int(rng.integers(-2, 3)) * int(style.spacing / texel / 2)
            dw = int(0.6 / texel)
            fill(px_rows(0.0, 2.2), cx - dw, cx + dw, style.door, style.frame)
    band = px_rows(wall_h - 0.35, wall_h)
    img[band[0]:band[1]] *= 0.75
    return _to_u8(img)


def _bark_texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Brown bark with vertical streaks."""
    streaks = cv2.resize(rng.uniform(-1, 1, (max(2, h // 10), w)).astype(np.float32), (w, h),
                         interpolation=cv2.INTER_LINEAR)
    v = 1 + 0.25 * streaks + 0.1 * rng.uniform(-1, 1, (h, w)).astype(np.float32)
    return _to_u8(np.array([92, 70, 52], np.float32) * v[..., None])


_FOLIAGE = ((62, 104, 44), (48, 92, 50), (84, 118, 52), (56, 96, 66))


def _foliage_texture(rng: np.random.Generator, h: int, w: int, shade: int) -> np.ndarray:
    """Leafy canopy: strong multi-scale mottling with dark gaps and sunlit clumps."""
    base = np.asarray(_FOLIAGE[shade % len(_FOLIAGE)], np.float32)
    v = _fbm(rng, h, w, (12, 4, 1), (0.5, 0.3, 0.2))
    img = base * (1 + 0.45 * v)[..., None]
    img[v > 0.35] += np.array([25, 30, 5], np.float32)            # sunlit clumps, yellower
    return _to_u8(img)


def _car_body_texture(rng: np.random.Generator, paint: np.ndarray, walls: list[tuple[int, float]], h: int,
                      body_h: float, own: bool = False) -> np.ndarray:
    """Car body walls (edges of :func:`_rect`: 0 right side, 1 front, 2 left side, 3 rear): paint, a dark
    rocker band, wheels on the sides, head and tail lights. ``own`` (a body of its own, variety): what makes
    one real car's flank unlike another's of the same colour, too: the lacquer's reflections (the sky bright
    above the shoulder line, the street dark below it, blotches of reflected trees and buildings), door
    seams and handles, dirt, and number plates front and rear."""
    texel = body_h / h
    cuts = np.round(np.concatenate([[0.0], np.cumsum([ln for _, ln in walls])]) / texel).astype(int)
    w = max(2, int(cuts[-1]))
    img = paint * (1 + 0.07 * _fbm(rng, h, w, (8, 1), (0.6, 0.4)))[..., None]
    if own:
        _car_body_detail(rng, img, walls, cuts, texel)
    img[int(0.78 * h):] *= 0.45                                   # rocker / bumper band
    rr, cc = np.mgrid[0:h, 0:w]
    wheel_r = 0.32 / texel
    wheel_row = h + (0.12 - 0.32) / texel                          # axle at 0.32 m, body bottom at 0.12 m
    lamp_rows = slice(int(0.15 * h), int(0.35 * h))
    for (edge, _), a, b in zip(walls, cuts[:-1], cuts[1:]):
        if edge in (0, 2):                                         # sides
            for f in (0.2, 0.8):
                d2 = (cc - (a + f * (b - a))) ** 2 + (rr - wheel_row) ** 2
                img[d2 < wheel_r ** 2] = (28, 28, 30)
                img[d2 < (0.55 * wheel_r) ** 2] = (120, 120, 125)
        else:                                                      # front: head lights, rear: tail lights
            rgb = (245, 240, 210) if edge == 1 else (200, 30, 30)
            lw = max(1, int(0.18 * (b - a)))
            img[lamp_rows, a + 1:a + 1 + lw] = rgb
            img[lamp_rows, b - 1 - lw:b - 1] = rgb
    return _to_u8(img)


def _car_body_detail(rng: np.random.Generator, img: np.ndarray, walls: list[tuple[int, float]], cuts: np.ndarray,
                     texel: float) -> None:
    """The detail of :func:`_car_body_texture` for a body of its own, painted into ``img`` (h, w, 3) float."""
    h, w = img.shape[:2]
    rows = (np.arange(h, dtype=np.float32) + 0.5) / h                # 0 at the shoulder line, 1 at the sill
    shoulder = float(rng.uniform(0.2, 0.4))
    light = np.where(rows < shoulder, 0.18 * (1 - rows / shoulder), -0.22 * (rows - shoulder) / (1 - shoulder))
    light[np.abs(rows - shoulder) < 1.5 / h] += 0.3                  # the crease catches the sky
    reflect = _fbm(rng, h, w, (max(2, int(0.9 / texel)), max(2, int(0.3 / texel))), (0.7, 0.3))
    dirt = np.clip(_fbm(rng, h, w, (max(2, int(0.4 / texel)), 1), (0.7, 0.3)), 0, None) * rows[:, None] ** 2
    img *= (1 + light[:, None] + 0.22 * reflect - float(rng.uniform(0.1, 0.5)) * dirt)[..., None]
    seam = max(1, int(round(0.012 / texel)))
    for (edge, length), a, b in zip(walls, cuts[:-1], cuts[1:]):
        if edge in (0, 2):                                            # door seams and handles on the flanks
            doors = 2 if length > 3.9 and rng.random() < 0.7 else 1
            fronts = np.linspace(0.32, 0.72, doors + 1)
            for f in fronts:
                c = int(a + f * (b - a)) if edge == 0 else int(b - f * (b - a))
                img[: int(0.8 * h), c:c + seam] *= 0.55
            for f0, f1 in zip(fronts[:-1], fronts[1:]):
                f = f0 + 0.7 * (f1 - f0)
                c = int(a + f * (b - a)) if edge == 0 else int(b - f * (b - a))
                r0 = int((shoulder + 0.08) * h)
                img[r0:r0 + max(1, int(0.04 / texel)), c:c + max(2, int(0.18 / texel))] *= 0.6
        else:                                                         # a number plate, white or yellow
            pw, ph = int(0.52 / texel), max(2, int(0.11 / texel))
            c0, r0 = (a + b - pw) // 2, int(0.5 * h)
            if pw > 2 and c0 >= a:
                img[r0:r0 + ph, c0:c0 + pw] = (235, 235, 230) if rng.random() < 0.8 else (240, 200, 40)
                chars = rng.random(max(1, pw // 3)) < 0.6
                for k, on in enumerate(chars):
                    if on and ph > 2:
                        img[r0 + 1:r0 + ph - 1, c0 + 1 + 3 * k:c0 + 2 + 3 * k] = (30, 30, 35)


def _car_cabin_texture(rng: np.random.Generator, paint: np.ndarray, h: int, w: int,
                       segs: list[float]) -> np.ndarray:
    """Cabin: dark windows with reflections between paint pillars and a paint band at the roof line."""
    img = np.empty((h, w, 3), np.float32)
    glass = np.array([40, 48, 58], np.float32) * (1 + 0.35 * _fbm(rng, h, w, (10, 2), (0.7, 0.3)))[..., None]
    img[:] = glass
    img[: max(1, h // 8)] = paint
    img[h - max(1, h // 10):] = paint
    cuts = np.round(np.concatenate([[0.0], np.cumsum(segs)]) / sum(segs) * w).astype(int)
    pillar = max(1, w // 40)
    for c in cuts[:-1]:
        img[:, max(0, c - pillar):c + pillar] = paint
    for k in (0, 2):                                               # B pillars
        m = (cuts[k] + cuts[k + 1]) // 2
        img[:, m - pillar:m + pillar] = paint
    return _to_u8(img)


def _person_texture(rng: np.random.Generator, shirt: np.ndarray, h: int, w: int) -> np.ndarray:
    """Head (skin, dark hair on top), shirt and trousers, top to bottom."""
    img = np.empty((h, w, 3), np.float32)
    head, waist = int(0.16 * h), int(0.55 * h)
    img[:head] = (200, 160, 130)
    img[: max(1, head // 3)] = (45, 35, 30)
    img[head:waist] = shirt
    img[waist:] = (52, 54, 66)
    return _to_u8(img * (1 + 0.12 * _fbm(rng, h, w, (4, 1), (0.5, 0.5)))[..., None])


def _stripes(rng: np.random.Generator, rgb: np.ndarray, h: int, w: int) -> np.ndarray:
    """Diagonal warning stripes of ``rgb`` and white, 0.2 m wide."""
    rr, cc = np.mgrid[0:h, 0:w]
    white = ((rr + cc) * _OBSTACLE_M / 0.2).astype(int) % 2 == 0
    img = np.where(white[..., None], np.float32(235), rgb)
    return _to_u8(img * (1 + 0.08 * _fbm(rng, h, w, (6, 1), (0.5, 0.5)))[..., None])
