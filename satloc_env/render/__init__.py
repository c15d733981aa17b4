"""Rendering: the GL entry point and the stereo renderers.

* :mod:`~satloc_env.render.gl`: the only place pyrender and OpenGL are imported (EGL, headless, no viewer),
  the GL context and the layered framebuffer;
* :mod:`~satloc_env.render.stereo`: :class:`StereoRenderer` (one car) and :class:`BatchStereoRenderer`
  (N cars in one framebuffer) drawing a :class:`~satloc_env.world.meshes.World` into colour, metric depth
  and class labels.

It may import :mod:`satloc` and :mod:`satloc_env.world`; never the environments or anything above them
(an import-linter contract in ``pyproject.toml`` checks it). The names of the former module
``satloc_env.render`` (now :mod:`satloc_env.render.stereo`) are re-exported here.
"""
from .stereo import BatchStereoRenderer, StereoRenderer, StereoSlot

__all__ = ["BatchStereoRenderer", "StereoRenderer", "StereoSlot"]

from satloc._moved import forward_names as _forward_names  # noqa: E402

# the former module's other names (satloc_env.render.<name>), with a FutureWarning naming their home
__getattr__ = _forward_names(__name__, ("satloc_env.render.stereo",))
