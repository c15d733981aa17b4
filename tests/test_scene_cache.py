"""The scenes' disk cache (satloc_env.world.scene.load_scene): a scene built once is read back the same, world
and renders included, in another process; a damaged entry is built again; an edited scene file, other knobs or
another version of the world code miss; SATLOC_SCENE_CACHE=0 builds every time."""
import shutil

import numpy as np
import pytest

from satloc.geometry import StereoCamera
from satloc_env.world import scene as S


@pytest.fixture
def fresh(tmp_path, monkeypatch):
    monkeypatch.setenv("SATLOC_CACHE", str(tmp_path / "cache"))
    S._cached_scene.cache_clear()
    yield tmp_path
    S._cached_scene.cache_clear()


def _render(scene):
    from satloc_env.render.stereo import StereoRenderer

    r = StereoRenderer(scene.world, StereoCamera.preset("half"))
    try:
        route = scene.routes[scene.spec.database_route]
        return r.render(route.pose_at(30.0, -1.75), "left", True)
    finally:
        r.close()


def test_a_cached_scene_is_the_scene_it_was(fresh):
    built = S.load_scene("loop")
    d = built.cache_dir
    assert d is not None and (d / "scene.json").is_file() and d.parent == fresh / "cache" / "scenes"
    a = _render(built)                                   # builds the world and keeps it beside the scene
    assert (d / "world.npz").is_file()
    S._cached_scene.cache_clear()                        # as another process: from the disk cache
    read = S.load_scene("loop")
    assert read is not built and read.cache_dir == d
    assert np.array_equal(read.satmap.image, built.satmap.image) and np.array_equal(read.satmap.labels,
                                                                                    built.satmap.labels)
    assert np.array_equal(read.layout.ground_rgb, built.layout.ground_rgb) and read.spec == built.spec
    assert {k: r.length for k, r in read.routes.items()} == {k: r.length for k, r in built.routes.items()}
    wa, wb = built.world, read.world
    assert len(wa.chunks) == len(wb.chunks)
    for ca, cb in zip(wa.chunks, wb.chunks):
        for name in ("positions", "uvs", "shade", "faces", "texture", "labels"):
            x, y = getattr(ca, name), getattr(cb, name)
            assert x.dtype == y.dtype and np.array_equal(x, y), name
    b = _render(read)
    for k in ("left", "right", "depth_left", "labels_left"):
        assert np.array_equal(a[k], b[k]), k
    # a damaged entry is built again and saved over
    (d / "layout.npz").write_bytes(b"not an npz")
    S._cached_scene.cache_clear()
    again = S.load_scene("loop")
    assert again.cache_dir == d and np.array_equal(again.satmap.image, built.satmap.image)
    S._cached_scene.cache_clear()
    assert np.array_equal(S.load_scene("loop").layout.ground_rgb, built.layout.ground_rgb)   # readable again


def test_what_the_cache_key_holds(fresh, monkeypatch):
    def key(path="loop", aliasing=0.0, gap=0.5):
        path = str(S.scene_path(path))
        spec, base = S.load_spec(path)
        return S.scene_cache_path(path, spec, base, aliasing, gap)

    first = key()
    assert first == key() and first.parent == fresh / "cache" / "scenes"
    assert key(aliasing=0.5) != first and key(gap=0.0) != first                 # other knobs
    yaml = fresh / "loop.yaml"                                                  # the same file elsewhere: the same
    shutil.copy(S.scene_path("loop"), yaml)
    assert key(str(yaml)) == first
    yaml.write_text(yaml.read_text().replace("seed:", "# edited\nseed:", 1))    # an edited file misses
    assert key(str(yaml)) != first
    from satloc_env.world import cache

    monkeypatch.setattr(cache, "code_digest", lambda d, recursive=True: "other code")
    assert key() != first                                                       # other world code misses
    monkeypatch.undo()
    monkeypatch.setenv("SATLOC_CACHE", str(fresh / "cache"))
    assert key() == first
    # off: built every time, never kept
    monkeypatch.setenv("SATLOC_SCENE_CACHE", "0")
    built = []
    monkeypatch.setattr(S, "build_scene", lambda *a, **k: built.append(1) or type("Stub", (), {"footprints": None})())
    S._cached_scene.cache_clear()
    s = S.load_scene("loop")
    assert built == [1] and getattr(s, "cache_dir", None) is None
    assert not (fresh / "cache" / "scenes").exists()
