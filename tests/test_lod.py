"""A world chunk's cells and levels of detail (satloc_env.world.meshes: CELL_M, LOD_M and the bands ALWAYS, NEAR,
FAR, INSIDE) and the renderer's use of them: what they leave out, and what they do not change."""
from __future__ import annotations

import numpy as np
import pytest
import yaml

from satloc.errors import FormatError
from satloc.geometry import StereoCamera
from satloc_env.world.meshes import ALWAYS, FAR, GROUND, INSIDE, LOD_M, NEAR, load_world, save_world
from satloc_env.world.scene import load_scene

SMALL = {
    "name": "small_lod", "seed": 3,
    "generator": {"type": "grid", "style": "city", "blocks": [2, 2], "pitch_m": 60, "margin_m": 10, "variety": 1.0},
    "meters_per_pixel": 0.2, "ground_mpp": 0.2,
    "routes": {"main": {"waypoints": [[10, 10], [130, 10], [130, 130], [10, 130]], "closed": True}},
}


def _scene(tmp_path, variety: float = 1.0, name: str = "s.yaml", terrain: dict | None = None):
    d = {**SMALL, "generator": {**SMALL["generator"], "variety": variety}}
    if terrain:
        d["terrain"] = terrain
    p = tmp_path / name
    p.write_text(yaml.safe_dump(d))
    return load_scene(p)


def test_cells_partition_each_chunk_and_hold_their_faces(tmp_path):
    s = _scene(tmp_path)
    world = s.world
    assert any(c.mirror for c in world.chunks) and any(not c.mirror for c in world.chunks)
    for c in world.chunks:
        f = c.cell_faces
        assert f[0] == 0 and f[-1] == len(c.faces) and (np.diff(f) >= 0).all()
        for k in range(len(f) - 1):   # every cell's box holds its triangles' vertices (reflected ones too)
            p = c.positions[c.faces[f[k]:f[k + 1]].ravel()]
            assert (p >= c.cell_bounds[k, 0] - 1e-4).all() and (p <= c.cell_bounds[k, 1] + 1e-4).all()
        assert c.cell_bands[-1] == ALWAYS     # the ground, last
    bands = set(np.concatenate([c.cell_bands for c in world.chunks]).tolist())
    assert bands == {ALWAYS, NEAR, FAR, INSIDE}
    # variety 0: one look of each kind, all drawn at every distance, as before the bands
    plain = _scene(tmp_path, 0.0, "plain.yaml").world
    assert set(np.concatenate([c.cell_bands for c in plain.chunks if c.cell_bands is not None]).tolist()) == {ALWAYS}
    assert [c.cell_faces is None for c in plain.chunks] == [c.repeat for c in plain.chunks]   # the neutral pad: one


def test_cells_round_trip_and_a_damaged_partition_is_named(tmp_path):
    world = _scene(tmp_path).world
    save_world(world, tmp_path / "w.npz")
    back = load_world(tmp_path / "w.npz")
    for a, b in zip(world.chunks, back.chunks):
        for name in ("faces", "cell_faces", "cell_bounds", "cell_squares", "cell_bands"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
    with np.load(tmp_path / "w.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["c0_cell_faces"] = arrays["c0_cell_faces"][:-1]
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(FormatError, match=r"bad\.npz"):
        load_world(tmp_path / "bad.npz")


def _drive(world, route, poses: int = 10):
    from satloc_env.render.stereo import StereoRenderer

    r = StereoRenderer(world, StereoCamera.preset("half"))
    try:
        return [r.render(route.pose_at(t, -1.75), depth=True, labels=True)
                for t in np.linspace(0, route.length * 0.97, poses)]
    finally:
        r.close()


@pytest.mark.parametrize("terrain", [None, {"relief_m": 1.5, "wavelength_m": 150}], ids=["flat", "hills"])
def test_culling_cells_changes_no_pixel_on_a_mirrored_world(tmp_path, monkeypatch, terrain):
    """Cells outside a camera's view volume or reach are skipped; the images (colour, depth, labels) are the same
    as when every cell of every chunk in view is drawn, beyond the layout's edge as within it, and over hills,
    whose ground grid is cut into cells of its own (band GROUND) that are skipped likewise."""
    import satloc_env.render.stereo as render

    s = _scene(tmp_path, terrain=terrain)
    route = s.routes["main"]
    if terrain:
        for c in s.world.chunks:
            ground = np.flatnonzero(c.cell_bands == GROUND)
            assert len(ground) > 1 and ground[-1] == len(c.cell_bands) - 1     # several, after the objects
            assert (np.diff(ground) == 1).all()
    culled = _drive(s.world, route)
    monkeypatch.setattr(render, "_box_in_view", lambda boxes, *a, **k: np.ones(len(boxes), bool))
    near = render._near
    monkeypatch.setattr(render, "_near", lambda rects, pose, reach: near(   # no reach; the level of detail kept
        rects, pose, reach if reach == LOD_M else np.inf))
    whole = _drive(s.world, route)
    for a, b in zip(culled, whole):
        for key in a:
            assert np.array_equal(a[key], b[key]), key


@pytest.mark.parametrize("terrain", [None, {"relief_m": 1.5, "wavelength_m": 150}], ids=["flat", "hills"])
def test_a_chunk_with_cells_is_never_drawn_whole(tmp_path, monkeypatch, terrain):
    """A chunk cut into cells is drawn by its cells' runs, none when no cell is kept: never whole (every cell, in
    reach or not, at every level of detail at once). Over hills the ground is cells too, so a chunk in view whose
    cells are all culled had no runs, and was drawn whole: four times the triangles, the same pixels."""
    import satloc_env.render.gl as gl
    from satloc_env.render.stereo import StereoRenderer

    s = _scene(tmp_path, terrain=terrain)
    route = s.routes["main"]
    seen = {"runs": 0, "none": 0}
    draw = gl._MultiViewRenderer._draw

    def checked(self, draws, view, proj, ranges=None):
        for *_, node in draws:
            if id(node) in cut:
                seen["runs" if ranges is not None and id(node) in ranges else "none"] += 1
        return draw(self, draws, view, proj, ranges)

    monkeypatch.setattr(gl._MultiViewRenderer, "_draw", checked)
    cut: set[int] = set()
    r = StereoRenderer(s.world, StereoCamera.preset("half"))
    try:
        r.render(route.pose_at(0.0, -1.75), depth=False)     # adds the world's nodes
        nodes = r._slot.batch._world_nodes(s.world).nodes
        cut |= {id(n) for c, pair in zip(s.world.chunks, nodes) if c.cell_faces is not None and len(c.cell_faces) >= 3
                for n in pair}
        assert cut
        for t in np.linspace(0, route.length * 0.97, 12):
            r.render(route.pose_at(t, -1.75), depth=True, labels=True)
    finally:
        r.close()
    assert seen["runs"] > 0 and seen["none"] == 0, seen


def test_level_of_detail_follows_the_distance_and_the_edge(tmp_path):
    """Street furniture and detailed trees (NEAR) within LOD_M of the car, coarse trees (FAR) beyond it, in the
    layout and its reflections beyond its edge alike; parked cars (INSIDE) at any distance in the layout, within
    LOD_M in the reflections."""
    from satloc_env.render.stereo import StereoRenderer

    s = _scene(tmp_path)
    route = s.routes["main"]
    r = StereoRenderer(s.world, StereoCamera.preset("half"))
    try:
        seen = {NEAR: 0, FAR: 0}
        for t in np.linspace(0, route.length * 0.97, 8):
            pose = route.pose_at(t, -1.75)
            out = r.render(pose, depth=False, labels=True)
            slot = r._slot
            cells = slot.batch._world_nodes(slot.world).cells
            by_first = {(int(c), int(f)): i for i, (c, f) in enumerate(zip(cells.chunk, cells.first))}
            for side in (0, 1):
                for chunk, runs in slot._runs[side].items():
                    for first, _ in runs:
                        i = by_first[(chunk, first)]
                        sq = cells.squares[i]
                        d = np.hypot(max(sq[0] - pose.x, pose.x - sq[2], 0.0), max(sq[1] - pose.y, pose.y - sq[3], 0.0))
                        band = int(cells.bands[i])
                        if band == NEAR:
                            assert d <= LOD_M
                        elif band == FAR:
                            assert d > LOD_M
                        elif band == INSIDE:
                            assert d <= LOD_M or not cells.mirror[i]
                        seen[band] = seen.get(band, 0) + 1
            assert out["labels_left"].shape == (188, 620)
        assert seen[NEAR] > 0 and seen[FAR] > 0
    finally:
        r.close()


def test_detail_m_none_draws_every_object_at_every_distance(tmp_path):
    """``detail_m``: 0 leaves out the street furniture (class obstacle) beyond the car's own square, the default
    beyond LOD_M, None nowhere; the env takes it as a setting, checked."""
    from satloc.labels import CLASS_ID
    from satloc_env.render.stereo import StereoRenderer

    s = _scene(tmp_path)
    route = s.routes["main"]
    poses = [route.pose_at(t, -1.75) for t in np.linspace(0, route.length * 0.97, 6)]
    furniture = {}
    for detail in (0.0, LOD_M, None):
        r = StereoRenderer(s.world, StereoCamera.preset("half"), detail_m=detail)
        try:
            furniture[detail] = sum(int((r.render(p, depth=False, labels=True)["labels_left"]
                                         == CLASS_ID["obstacle"]).sum()) for p in poses)
        finally:
            r.close()
    assert furniture[0.0] < furniture[LOD_M] < furniture[None]
    with pytest.raises(Exception, match="detail_m must be a finite number >= 0 or None"):
        StereoRenderer(s.world, StereoCamera.preset("half"), detail_m=-1.0)


def test_a_copied_block_looks_the_same_to_the_camera(tmp_path):
    """At aliasing 1 every block is a copy of one: the camera, facing the same spot of two blocks, sees the
    same picture down to the window panes (the copies' objects draw their textures from the original's)."""
    import math

    from satloc.geometry import Pose2
    from satloc_env.render.stereo import StereoRenderer

    diffs = {}
    for aliasing in (0.0, 1.0):
        p = tmp_path / f"a{aliasing}.yaml"
        p.write_text(yaml.safe_dump({**SMALL, "knobs": {"aliasing": aliasing}}))
        s = load_scene(p)
        r = StereoRenderer(s.world, StereoCamera.kitti_half())
        a, b = (r.render(Pose2(x, 70.0, math.pi / 2), depth=False)["left"].astype(int) for x in (40.0, 100.0))
        diffs[aliasing] = np.abs(a - b).mean()
    assert diffs[1.0] < 0.5 and diffs[0.0] > 20, diffs
    # a saved scene keeps whose looks its objects copy
    from satloc_env.world.scene import Scene

    s.save(tmp_path / "saved")
    r = Scene.load(tmp_path / "saved")
    for what in ("buildings", "trees", "cars", "furniture"):
        looks = [o.look for o in getattr(s.layout, what)]
        assert [o.look for o in getattr(r.layout, what)] == looks and any(k is not None for k in looks)


def test_a_chunk_too_tall_for_gl_gets_a_wider_atlas(tmp_path, monkeypatch):
    """A chunk whose objects' textures would stack taller than GL's largest texture (loop at variety 1: 17,772
    rows, and glTexImage2D failed) packs them into a wider atlas, the ground in its top left corner. The views
    are those of the narrow atlas but for mipmapping (coarse levels average other neighbours in another layout:
    measured 0.29-0.52 of 255 apart on average, 0.7-1.8 % of values more than 8) and for labels on class edges
    where a texel coordinate rounds the other way (2-9 pixels a view); depth exactly."""
    import satloc_env.world.meshes as meshes

    s = _scene(tmp_path)
    route = s.routes["main"]
    narrow = s.spec.build_world(s.layout)
    tallest = max(c.texture.shape[0] for c in narrow.chunks)
    widths = {c.texture.shape[1] for c in narrow.chunks}
    monkeypatch.setattr(meshes, "MAX_TEXTURE", tallest - 8)
    wide = s.spec.build_world(s.layout)
    assert max(c.texture.shape[0] for c in wide.chunks) <= tallest - 8
    grown = [(a, b) for a, b in zip(narrow.chunks, wide.chunks) if b.texture.shape[1] > a.texture.shape[1]]
    assert grown and {c.texture.shape[1] for c in wide.chunks} - widths
    for a, b in grown:   # the same triangles, the ground's texels in the top left corner
        assert np.array_equal(a.faces, b.faces) and np.array_equal(a.positions, b.positions)
        ga = a.texture.shape[1]
        assert np.array_equal(b.texture[:64, :ga], a.texture[:64])   # rows of the ground's region
    monkeypatch.setattr(meshes, "MAX_TEXTURE", 16384)
    for x, y in zip(_drive(narrow, route, 6), _drive(wide, route, 6)):
        for key in ("left", "right"):
            d = np.abs(x[key].astype(int) - y[key].astype(int))
            assert d.mean() < 1.0 and (d > 8).mean() < 0.03, (key, d.mean(), (d > 8).mean())
        assert np.array_equal(x["depth_left"], y["depth_left"])
        assert (x["labels_left"] != y["labels_left"]).mean() < 0.001    # measured: 2-9 texels on class edges
