"""Worlds: everything that turns a scene file into geometry and pixels, with no GL and no environment.

* scenes as data: :mod:`~satloc_env.world.scene` (scene files, loading, the built :class:`Scene`);
* generated places: :mod:`~satloc_env.world.layout` (the vector description both views are made from),
  :mod:`~satloc_env.world.generator` (grids of city or residential blocks), :mod:`~satloc_env.world.paint`
  (procedural textures), :mod:`~satloc_env.world.tile` (the overhead tile painted from a layout);
* real places: :mod:`~satloc_env.world.scene_roads` and :mod:`~satloc_env.world.scene_buildings` (map
  vectors into roads and 3-D objects), :mod:`~satloc_env.world.roadtrace` (a route traced from a road
  mask), :mod:`~satloc_env.world.roadgraph` (the road graph, tours, snapped routes),
  :mod:`~satloc_env.world.route` (polylines driven at a lane offset);
* :mod:`~satloc_env.world.meshes`: the renderable chunks (textured meshes, pure numpy);
* :mod:`~satloc_env.world.revisit`: how a place changes between passes (sun, wear, parked cars).

It may import :mod:`satloc` and nothing else of :mod:`satloc_env` (an import-linter contract in
``pyproject.toml`` checks it). The names of the former module ``satloc_env.world`` (now
:mod:`satloc_env.world.meshes`) are re-exported here.
"""
from .meshes import PAD, SKY_RGB, TexturedMesh, World, build_occluders, build_world, sun_direction

__all__ = ["TexturedMesh", "World", "build_world", "build_occluders", "sun_direction", "SKY_RGB", "PAD"]

from satloc._moved import forward_names as _forward_names  # noqa: E402

# the former module's other names (satloc_env.world.<name>), with a FutureWarning naming their home
__getattr__ = _forward_names(__name__, ("satloc_env.world.meshes",))
