import numpy as np
import pytest
import yaml

from satloc import ConfigError
from satloc.errors import FormatError
from satloc.labels import CLASS_ID
from satloc_env.world.generator import GridParams, alias_sources, generate_grid
from satloc_env.world.route import Route
from satloc_env.world.scene import Scene, available_scenes, build_scene, load_scene, load_spec

SMALL = {
    "name": "small", "seed": 3,
    "generator": {"type": "grid", "style": "city", "blocks": [2, 2], "pitch_m": 60, "margin_m": 10},
    "meters_per_pixel": 0.2, "ground_mpp": 0.2,
    "routes": {"main": {"waypoints": [[10, 10], [130, 10], [130, 130], [10, 130]], "closed": True}},
}


def write(tmp_path, data, name="s.yaml"):
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data))
    return p


def test_shipped_scenes_are_valid():
    assert {"city", "residential", "loop"} <= set(available_scenes())
    for name in available_scenes():
        spec, _ = load_spec(name)
        assert spec.name == name


def test_loop_scene_has_3km_driven_twice_and_a_branch():
    spec, _ = load_spec("loop")
    main = Route(spec.routes["main"].waypoints, spec.routes["main"].closed, 1)
    assert main.length >= 3000 and spec.routes["main"].laps == 2
    db = {tuple(p) for p in spec.routes["main"].waypoints}
    assert any(tuple(p) not in db for p in spec.routes[spec.query_route].waypoints)


def test_generation_is_deterministic_and_consistent(tmp_path):
    a = load_scene(write(tmp_path, SMALL))
    spec, base = load_spec(tmp_path / "s.yaml")
    b = build_scene(spec, base)
    assert np.array_equal(a.satmap.image, b.satmap.image)
    assert np.array_equal(a.layout.ground_rgb, b.layout.ground_rgb)
    assert len(a.layout.buildings) == len(b.layout.buildings) > 0
    # the tile shows roofs where the buildings are and road along the route
    bld = a.layout.buildings[0].footprint.mean(0)
    assert a.satmap.labels[tuple(np.round(a.satmap.world_to_pixel(bld)).astype(int)[::-1])] == CLASS_ID["building"]
    assert a.is_drivable(70, 10 - 1.75) and not a.is_drivable(*bld)


def test_scene_save_load_round_trip(tmp_path):
    s = load_scene(write(tmp_path, SMALL))
    s.save(tmp_path / "saved")
    r = Scene.load(tmp_path / "saved")
    assert np.array_equal(r.satmap.image, s.satmap.image)
    assert np.array_equal(r.layout.ground_labels, s.layout.ground_labels)
    assert [b.height for b in r.layout.buildings] == [b.height for b in s.layout.buildings]
    assert [t.center for t in r.layout.trees] == [t.center for t in s.layout.trees]
    assert [c.rgb for c in r.layout.cars] == [c.rgb for c in s.layout.cars]
    assert r.routes["main"].length == s.routes["main"].length
    assert load_scene(tmp_path / "saved").name == "small"


def test_aliasing_copies_blocks_exactly():
    p = GridParams(blocks=(3, 3), pitch_m=40, margin_m=10)
    lay, src = generate_grid(p, 5, 0.5, 0.2)
    copies = [(i, s) for i, s in enumerate(src) if s != i]
    assert len(copies) == round(0.5 * 9)
    n, m = int(40 / 0.2), int(10 / 0.2)
    H = lay.ground_rgb.shape[0]

    def cell(k):
        i, j = k % 3, k // 3
        return lay.ground_rgb[H - m - (j + 1) * n: H - m - j * n, m + i * n: m + (i + 1) * n]

    for i, s in copies:
        assert np.array_equal(cell(i), cell(s))
    orig = [i for i, s in enumerate(src) if s == i]
    assert not np.array_equal(cell(orig[0]), cell(orig[1]))
    assert np.array_equal(alias_sources(9, 0.0, np.random.default_rng(0)), np.arange(9))
    assert len(set(alias_sources(9, 1.0, np.random.default_rng(0)))) == 1  # all copies of one original


@pytest.mark.parametrize("mutate, message", [
    (lambda d: d.update(colour="red"), r"unknown key\(s\) \['colour'\]"),
    (lambda d: d.update(seed="seven"), r"s\.yaml: seed: expected an integer"),
    (lambda d: d["generator"].update(blocks="many"), r"generator\.blocks: expected a list"),
    (lambda d: d["generator"].update(type="fractal"), r"generator\.type: expected 'grid', 'image' or 'vectors'"),
    (lambda d: d["routes"]["main"]["waypoints"].append([500, 10]),
     r"routes\.main\.waypoints\[4\] = \[500(\.0)?, 10(\.0)?\] lies outside the tile"),
    (lambda d: d.update(query_route="nope"), r"query_route: route 'nope' is not in routes"),
    (lambda d: d.update(knobs={"aliasing": 2.0}), r"knobs\.aliasing: expected a value in \[0, 1\]"),
    (lambda d: d.update(generator={"type": "image", "image": "missing.png"}), r"generator\.image: image file .*missing\.png not found"),
])
def test_bad_scene_files_name_the_field(tmp_path, mutate, message):
    import copy
    d = copy.deepcopy(SMALL)
    mutate(d)
    p = write(tmp_path, d)
    with pytest.raises(ConfigError, match=message) as e:
        load_scene(p)
    assert str(p) in str(e.value) or "scene" in str(e.value)


def test_unknown_scene_name():
    with pytest.raises(ConfigError, match="not a shipped scene"):
        load_scene("atlantis")


def test_image_scene(tmp_path):
    import cv2
    img = np.full((200, 300, 3), 90, np.uint8)
    cv2.imwrite(str(tmp_path / "tile.png"), img)
    d = {"name": "img", "generator": {"type": "image", "image": "tile.png"}, "meters_per_pixel": 0.2,
         "ground_mpp": 0.2, "routes": {"main": {"waypoints": [[5, 20], [55, 20]]}}}
    s = load_scene(write(tmp_path, d))
    assert s.layout.width_m == pytest.approx(60) and s.layout.height_m == pytest.approx(40)
    assert s.satmap.image.shape == (200, 300, 3)


def test_route_sampling_and_projection():
    r = Route([[0, 0], [10, 0], [10, 10]], name="r")
    assert r.length == 20
    x, y, yaw = r.sample(np.array([15.0]), offset=1.0)[0]
    assert (x, y, yaw) == pytest.approx((9.0, 5.0, np.pi / 2))
    s, off = r.project((9.0, 5.0))
    assert s == pytest.approx(15.0) and off == pytest.approx(1.0)
    loop = Route([[0, 0], [10, 0], [10, 10], [0, 10]], closed=True, laps=2)
    assert loop.length == 80
    assert loop.project((5.0, 0.0), s_hint=42.0)[0] == pytest.approx(45.0)
    with pytest.raises(ValueError, match="laps > 1 needs a closed route"):
        Route([[0, 0], [1, 0]], laps=2)


def _objects(lay):
    return ([b.footprint.tolist() for b in lay.buildings], [t.center for t in lay.trees],
            [c.center for c in lay.cars])


def test_variety_gives_objects_their_own_looks_and_moves_nothing():
    p0 = GridParams(blocks=(2, 2), pitch_m=60, margin_m=10)
    p1 = GridParams(blocks=(2, 2), pitch_m=60, margin_m=10, variety=1.0)
    lay0, _ = generate_grid(p0, 3, 0.0, 0.2)
    lay1, _ = generate_grid(p1, 3, 0.0, 0.2)
    # variety 0: the one look of each kind, as before the knob
    assert all(b.style_seed is None for b in lay0.buildings)
    assert {t.species for t in lay0.trees} == {0} and {c.body for c in lay0.cars} == {0}
    # variety 1: every object its own, all of variety 0's objects where they stood, more cars and trees
    b0, t0, c0 = _objects(lay0)
    b1, t1, c1 = _objects(lay1)
    assert b1 == b0
    assert set(map(tuple, t0)) <= set(map(tuple, t1)) and set(map(tuple, c0)) <= set(map(tuple, c1))
    assert len(c1) > len(c0) and len(t1) > len(t0)
    seeds = [b.style_seed for b in lay1.buildings]
    assert None not in seeds and len(set(seeds)) == len(seeds)
    assert {t.species for t in lay1.trees} <= {1, 2, 3, 4} and len({t.species for t in lay1.trees}) >= 2
    assert {c.body for c in lay1.cars} <= {1, 2, 3, 4, 5} and len({c.body for c in lay1.cars}) >= 3
    # street furniture on the sidewalks: none at variety 0, most kinds at 1, off the tree trunks
    assert lay0.furniture == [] and {f.kind for f in lay1.furniture} >= {1, 2, 3}
    sidewalk = lay1.ground_labels == CLASS_ID["sidewalk"]
    street = [f for f in lay1.furniture if f.kind <= 8]          # not the greenery of yards, parks and margins
    rc = np.round(lay1.world_to_raster(np.array([f.center for f in street]))).astype(int)
    assert sidewalk[rc[:, 1], rc[:, 0]].mean() > 0.9
    trunks = np.array([t.center for t in lay1.trees])
    assert all(np.hypot(*(trunks - f.center).T).min() > 0.5 for f in lay1.furniture)
    # the worn road: the same labels (but the paths variety lays across the parks' grass), other pixels on the road
    changed = lay0.ground_labels != lay1.ground_labels
    assert (lay0.ground_labels[changed] == CLASS_ID["grass"]).all()
    assert (lay1.ground_labels[changed] == CLASS_ID["sidewalk"]).all()
    road = lay0.ground_labels == CLASS_ID["road"]
    assert not np.array_equal(lay0.ground_rgb[road], lay1.ground_rgb[road])
    # deterministic per seed
    again, _ = generate_grid(p1, 3, 0.0, 0.2)
    assert np.array_equal(again.ground_rgb, lay1.ground_rgb)
    assert [b.style_seed for b in again.buildings] == seeds
    assert [(c.body, c.rgb, c.length) for c in again.cars] == [(c.body, c.rgb, c.length) for c in lay1.cars]


def test_variety_aliased_blocks_copy_their_looks():
    p = GridParams(blocks=(3, 3), pitch_m=60, margin_m=10, variety=1.0)
    lay, src = generate_grid(p, 5, 0.5, 0.2)
    copies = [(i, s) for i, s in enumerate(src) if s != i]

    def looks(k):
        x0, y0 = 10 + (k % 3) * 60, 10 + (k // 3) * 60
        inside = lambda xy: x0 <= xy[0] < x0 + 60 and y0 <= xy[1] < y0 + 60  # noqa: E731
        return (sorted(b.style_seed for b in lay.buildings if inside(b.footprint.mean(0))),
                sorted((t.species, t.shade) for t in lay.trees if inside(t.center)),
                sorted((c.body, c.rgb) for c in lay.cars if inside(c.center)),
                sorted((f.kind, f.seed) for f in lay.furniture if inside(f.center)))

    for i, s in copies:
        assert looks(i) == looks(s)
    assert sum(len(looks(i)[0]) for i, _ in copies) > 0 and sum(len(looks(i)[2]) for i, _ in copies) > 0
    # every copied object names the original it copies its textures from: the same object, a whole number of
    # pitches away, itself an original
    named = 0
    for objs, where in ((lay.buildings, lambda o: o.footprint.mean(0)), (lay.trees, lambda o: np.array(o.center)),
                        (lay.cars, lambda o: np.array(o.center)), (lay.furniture, lambda o: np.array(o.center))):
        for o in objs:
            if o.look is None:
                continue
            named += 1
            orig = objs[o.look]
            assert orig.look is None and type(orig) is type(o)
            shift = (where(o) - where(orig)) / 60
            assert np.allclose(shift, np.round(shift), atol=1e-9) and np.abs(shift).sum() > 0
    assert named > 0
    again, _ = generate_grid(GridParams(blocks=(3, 3), pitch_m=60, margin_m=10, variety=1.0), 5, 0.0, 0.2)
    assert all(o.look is None for objs in (again.buildings, again.trees, again.cars) for o in objs)


def test_aliasing_copies_the_margins_too():
    """At aliasing 1 an edge road passes the same open land at every block, as it passes the same block."""
    p = GridParams(blocks=(3, 2), pitch_m=40, margin_m=10)
    n, m = int(40 / 0.2), int(10 / 0.2)

    def south(lay, i):
        return lay.ground_rgb[-m:, m + i * n: m + (i + 1) * n]

    def west(lay, j):
        H = lay.ground_rgb.shape[0]
        return lay.ground_rgb[H - m - (j + 1) * n: H - m - j * n, :m]

    one, _ = generate_grid(p, 5, 1.0, 0.2)
    assert np.array_equal(south(one, 0), south(one, 1)) and np.array_equal(south(one, 1), south(one, 2))
    assert np.array_equal(west(one, 0), west(one, 1))
    zero, _ = generate_grid(p, 5, 0.0, 0.2)
    assert not np.array_equal(south(zero, 0), south(zero, 1)) and not np.array_equal(west(zero, 0), west(zero, 1))
    # with variety the margins' trees and shrubs are copied too, looks and all
    q = GridParams(blocks=(3, 2), pitch_m=40, margin_m=20, variety=1.0)
    lay, _ = generate_grid(q, 5, 1.0, 0.2)

    def south_trees(i):
        x0 = 20 + i * 40
        return sorted((round(t.center[0] - x0, 6), round(t.center[1], 6), t.species, t.canopy_radius)
                      for t in lay.trees if x0 <= t.center[0] < x0 + 40 and t.center[1] < 14)

    assert south_trees(0) and south_trees(0) == south_trees(1) == south_trees(2)
    copied = [t for t in lay.trees if t.center[1] < 14 and t.look is not None]
    assert copied and all(lay.trees[t.look].look is None for t in copied)


def test_variety_round_trips_and_builds_its_world(tmp_path):
    import copy

    d = copy.deepcopy(SMALL)
    d["generator"]["variety"] = 1.0
    s = load_scene(write(tmp_path, d))
    assert s.spec.beyond_edge == "mirror"   # a street goes on past the map's edge
    s.save(tmp_path / "saved")
    r = Scene.load(tmp_path / "saved")
    assert [b.style_seed for b in r.layout.buildings] == [b.style_seed for b in s.layout.buildings]
    assert [t.species for t in r.layout.trees] == [t.species for t in s.layout.trees]
    assert [c.body for c in r.layout.cars] == [c.body for c in s.layout.cars]
    assert r.layout.furniture == s.layout.furniture and len(s.layout.furniture) > 0
    assert s.summary()["furniture"] == len(s.layout.furniture)
    world = s.spec.build_world(s.layout)
    assert sum(len(c.faces) for c in world.chunks) > 0
    # the camera's ground shows the world's cast shadows (variety's default), darker than the layout's ground;
    # a revisit moves the sun and the world casts at it, once
    assert s.spec.casts_shadows and not load_scene(write(tmp_path, SMALL, "plain.yaml")).spec.casts_shadows
    import dataclasses

    flat = dataclasses.replace(s.spec, ground_shadows=False).build_world(s.layout)
    ground = lambda w: w.chunks[0].texture[:600].astype(np.float64)  # noqa: E731  (the ground region: 716 rows)
    assert ground(world).mean() < ground(flat).mean() - 2.0
    from satloc_env.world.revisit import changed_layout

    moved = changed_layout(s.layout, 0.5, 3, parts=("shadows",), cast=False)
    assert np.array_equal(moved.ground_rgb, s.layout.ground_rgb) and moved.sun_azimuth != s.layout.sun_azimuth
    # the furniture is in the world (class obstacle: nothing else of a scene's own is) and on the tile
    assert any((c.labels == CLASS_ID["obstacle"]).any() for c in world.chunks)
    from satloc_env.world.tile import paint_tile
    bare = dataclasses.replace(s.layout, furniture=[])
    assert not np.array_equal(paint_tile(s.layout, 0.2, 0)[0], paint_tile(bare, 0.2, 0)[0])
    # a damaged furniture array is named
    import zipfile

    with zipfile.ZipFile(tmp_path / "saved" / "layout.npz") as z:
        arrays = {n[:-4]: np.load(z.open(n)) for n in z.namelist()}
    bad = arrays["furniture"].copy()
    bad[0, 3] = 99
    np.savez(tmp_path / "saved" / "layout.npz", **{**arrays, "furniture": bad})
    with pytest.raises(FormatError, match=r"layout\.npz: array 'furniture': every kind"):
        Scene.load(tmp_path / "saved")
    d["generator"]["variety"] = 1.5
    with pytest.raises(ConfigError, match=r"generator\.variety: expected a number from 0 to 1"):
        load_scene(write(tmp_path, d, "bad.yaml"))


def test_variety_plants_hedges_shrubs_and_planters():
    """Residential front yards get hedges (2 m segments of one seed, none across a driveway) and shrubs, city
    sidewalks planters; their foliage is labelled tree in the world and on the tile; none at variety 0."""
    from satloc_env.world.furniture import furniture_parts
    from satloc_env.world.tile import paint_tile

    res, _ = generate_grid(GridParams(style="residential", blocks=(2, 2), pitch_m=60, margin_m=10, variety=1.0),
                           4, 0.0, 0.2)
    kinds = [f.kind for f in res.furniture]
    assert kinds.count(9) >= 4 and kinds.count(10) >= 4
    hedges = [f for f in res.furniture if f.kind == 9]
    assert len({f.seed for f in hedges}) < len(hedges)          # a hedge's segments share their look
    for f in hedges:
        (part,) = furniture_parts(f)
        assert part.leaves and 0.9 <= part.z1 <= 1.8
    gh = res.ground_labels.shape[0]                               # in the yard's grass: not on the sidewalk,
    under = [res.ground_labels[int(gh - f.center[1] / 0.2), int(f.center[0] / 0.2)] for f in hedges]
    assert all(u == CLASS_ID["grass"] for u in under)             # nor across a driveway
    img, labels = paint_tile(res, 0.2, 1)
    h = labels.shape[0]
    on = [labels[int(h - f.center[1] / 0.2), int(f.center[0] / 0.2)] for f in hedges]
    assert np.mean(np.array(on) == CLASS_ID["tree"]) > 0.9
    city, _ = generate_grid(GridParams(blocks=(2, 2), pitch_m=60, margin_m=10, variety=1.0), 4, 0.0, 0.2)
    assert any(f.kind == 11 for f in city.furniture)
    plain, _ = generate_grid(GridParams(style="residential", blocks=(2, 2), pitch_m=60, margin_m=10), 4, 0.0, 0.2)
    assert not plain.furniture


def test_variety_fences_and_walls_some_front_yards():
    """Yards without a hedge get a fence (pickets on both faces) or a low garden wall (a coping on top) for
    some: 2 m segments of one seed along the sidewalk, in the yard, class obstacle; the hedges stay as they
    were (the fences draw from the yard's own seed)."""
    from satloc_env.world.furniture import furniture_parts

    p = GridParams(style="residential", blocks=(3, 3), pitch_m=60, margin_m=10, variety=1.0)
    res, _ = generate_grid(p, 4, 0.0, 0.2)
    rows = {k: [f for f in res.furniture if f.kind == k] for k in (9, 12, 13)}
    assert len(rows[12]) >= 4 and len(rows[13]) >= 4
    for f in rows[12] + rows[13]:
        parts = furniture_parts(f)
        assert not any(q.leaves for q in parts) and parts[0].z1 <= 1.3
        assert len(parts[0].faces) == 2                       # both faces pictured
    assert all(len(furniture_parts(f)) == 2 for f in rows[13])   # the wall's coping
    gh = res.ground_labels.shape[0]
    under = [res.ground_labels[int(gh - f.center[1] / 0.2), int(f.center[0] / 0.2)] for f in rows[12] + rows[13]]
    assert all(u == CLASS_ID["grass"] for u in under)
    import dataclasses

    import satloc_env.world.generator as gen

    class NoFences(gen.CellPainter):
        def _hedge(self, *a, kind=9, **k):
            if kind == 9:
                super()._hedge(*a, **k)

    orig = gen.CellPainter
    gen.CellPainter = NoFences
    try:
        bare, _ = generate_grid(dataclasses.replace(p), 4, 0.0, 0.2)
    finally:
        gen.CellPainter = orig
    assert [f for f in bare.furniture] == [f for f in res.furniture if f.kind not in (12, 13)]


def test_variety_paves_the_sidewalks():
    """The ground's finest detail: at variety 1 the sidewalk (slab joints, kerb stones, grain) and the grass
    (blades and tufts) vary from texel to texel several times as much as at variety 0."""
    import cv2

    def fine(lay, cls):
        g = lay.ground_rgb.astype(np.float32).mean(-1)
        inside = cv2.erode((lay.ground_labels == CLASS_ID[cls]).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        return float(np.abs(cv2.Laplacian(g, cv2.CV_32F))[inside].mean())

    a, _ = generate_grid(GridParams(blocks=(2, 2), pitch_m=60, margin_m=10), 4, 0.0, 0.1)
    b, _ = generate_grid(GridParams(blocks=(2, 2), pitch_m=60, margin_m=10, variety=1.0), 4, 0.0, 0.1)
    for cls in ("sidewalk", "grass"):
        assert fine(b, cls) > 2 * fine(a, cls), cls


def test_variety_wears_the_markings():
    """At variety 1 every stripe and dash of paint is worn by its own amount, so two crossings of the same
    design differ; the labels stay markings, the draw is deterministic, and variety 0 paints them as new."""
    import cv2

    def pieces(lay):
        m = (lay.ground_labels == CLASS_ID["lane_marking"]).astype(np.uint8)
        n, comp = cv2.connectedComponents(m, connectivity=4)
        g = lay.ground_rgb.astype(np.float32).mean(-1)
        sizes = np.bincount(comp.ravel(), minlength=n)
        means = np.bincount(comp.ravel(), weights=g.ravel(), minlength=n) / np.maximum(sizes, 1)
        return means[1:][sizes[1:] >= 20], m

    a, _ = generate_grid(GridParams(blocks=(2, 2), pitch_m=60, margin_m=10), 4, 0.0, 0.1)
    b, _ = generate_grid(GridParams(blocks=(2, 2), pitch_m=60, margin_m=10, variety=1.0), 4, 0.0, 0.1)
    again, _ = generate_grid(GridParams(blocks=(2, 2), pitch_m=60, margin_m=10, variety=1.0), 4, 0.0, 0.1)
    new, mask_a = pieces(a)
    worn, mask_b = pieces(b)
    assert np.array_equal(mask_a, mask_b)                      # the same paint, where it was
    assert len(worn) > 50
    assert new.std() < 4 and worn.std() > 3 * new.std()      # each piece its own age
    assert worn.mean() < new.mean() - 15                      # worn towards the asphalt
    assert np.array_equal(again.ground_rgb, b.ground_rgb)


def test_variety_paints_balconies_and_fire_escapes():
    """Half the houses and a third of the plaster, brick and concrete blocks downtown have balconies (whole
    columns, floor above floor), a quarter of the brick ones downtown a fire escape; drawn from generators of
    their own, so the rest of a facade is as it was, and the ground floor is untouched."""
    import dataclasses

    from satloc_env.world.variety import facade_params, facade_texture

    houses = [facade_params(s, city=False) for s in range(300)]
    blocks = [facade_params(s, city=True) for s in range(300)]
    assert 0.35 < np.mean([f.balcony_p > 0 for f in houses]) < 0.65
    assert not any(f.fire_escape for f in houses)
    brick = [f for f in blocks if f.material == "brick"]
    assert 0.1 < np.mean([f.fire_escape for f in brick]) < 0.4
    assert not any(f.fire_escape or f.balcony_p > 0 for f in blocks if f.material == "glass")
    for f in [next(f for f in houses if f.balcony_p > 0.5), next(f for f in brick if f.fire_escape)]:
        texel, h = 0.1, 140
        with_ = facade_texture(np.random.default_rng(1), f, [16.0, 8.0], h, texel)
        bare = facade_texture(np.random.default_rng(1), dataclasses.replace(f, balcony_p=0.0, fire_escape=False),
                              [16.0, 8.0], h, texel)
        changed = np.abs(with_.astype(int) - bare.astype(int)).sum(-1) > 0
        ground = h - int((f.floor_h + 0.2) / texel)       # rows below the first floor's slab shadow
        assert changed.mean() > 0.01 and not changed[ground:].any()


def test_a_door_on_a_short_wall_stays_on_its_facade():
    """A wall's door is shifted from the middle by up to a window spacing; on a wall of 5-7 m at the texture's
    end the shift once put its frame past the texture (IndexError while building a scene) or wrapped it round to
    the other end. The door now stays whole on the facade strip."""
    import dataclasses

    from satloc_env.world.variety import facade_params, facade_texture

    texel, h = 0.1, 40
    dw = int(0.55 / texel)
    door_rows = slice(h - int(round(0.6 / texel)), h)     # its foot: below any ground-floor window
    for seed in range(60):
        for city in (True, False):
            f = dataclasses.replace(facade_params(seed, city), shopfront=False, drainpipes=False)
            for length in (5.2, 5.6, 6.4):
                img = facade_texture(np.random.default_rng(seed), f, [length], h, texel)
                assert img.shape[:2] == (h, int(round(length / texel)))
                colour = np.clip(np.asarray(f.door) + 0.5, 0, 255).astype(np.uint8)
                door = np.all(img[door_rows] == colour, axis=-1).all(axis=0)
                cols = np.flatnonzero(door)
                assert len(cols) == 2 * dw - 2, (seed, city, length)          # the door's leaf between its frame
                assert cols[-1] - cols[0] == len(cols) - 1 and cols[0] >= 1 and cols[-1] <= img.shape[1] - 2


def test_variety_gives_houses_pitched_roofs():
    """Most houses at variety 1 are gabled (a ridge along the long side, in the world's mesh), none at
    variety 0 or downtown; the roofs draw from a generator of their own, so nothing else moves."""
    import dataclasses

    import satloc_env.world.generator as gen
    from satloc_env.world.meshes import build_world

    p = GridParams(style="residential", blocks=(2, 2), pitch_m=60, margin_m=10, variety=1.0)
    res, _ = generate_grid(p, 4, 0.0, 0.2)
    gabled = [b.roof == "gabled" for b in res.buildings]
    assert 0.6 < np.mean(gabled) < 0.95
    plain, _ = generate_grid(dataclasses.replace(p, variety=0.0), 4, 0.0, 0.2)
    city, _ = generate_grid(dataclasses.replace(p, style="city"), 4, 0.0, 0.2)
    assert not any(b.roof == "gabled" for b in plain.buildings + city.buildings)
    orig = gen.CellPainter._roofed
    gen.CellPainter._roofed = lambda self, b: b
    try:
        flat, _ = generate_grid(p, 4, 0.0, 0.2)
    finally:
        gen.CellPainter._roofed = orig
    key = lambda b: (b.footprint.tobytes(), b.height, b.facade, b.roof_rgb, b.style_seed)  # noqa: E731
    assert [key(b) for b in res.buildings] == [key(b) for b in flat.buildings]
    assert res.trees == flat.trees and res.furniture == flat.furniture
    assert [(c.center, c.body, c.rgb) for c in res.cars] == [(c.center, c.body, c.rgb) for c in flat.cars]
    # a gabled house's mesh reaches its height only along the ridge
    b = next(b for b in res.buildings if b.roof == "gabled")
    w = build_world(dataclasses.replace(res, buildings=[b], trees=[], cars=[], furniture=[]))
    pos = w.chunks[0].positions[w.chunks[0].faces[:w.chunks[0].cell_faces[-2]].ravel()]
    top = pos[np.isclose(pos[:, 2], b.height, atol=1e-3)]
    assert len(top) >= 2 and np.ptp(top[:, :2], axis=0).min() < 1e-3     # a line: the ridge


def test_variety_furnishes_flat_roofs():
    """Downtown blocks at variety 1 carry roof furniture (a stairs housing on most, one to four air-conditioning
    units), drawn from the building's own seed: the same every time, inside the roof 1.5 m from its edge, apart
    from each other; in the world's mesh (class building, up to the unit's top) and on the tile (each top in its
    colour, lit); none at variety 0, on gabled houses or low roofs."""
    import dataclasses

    from shapely.geometry import Polygon

    from satloc_env.world.furniture import ROOF_MIN_HEIGHT_M, roof_parts
    from satloc_env.world.meshes import build_world
    from satloc_env.world.tile import paint_tile

    city, _ = generate_grid(GridParams(blocks=(2, 2), pitch_m=60, margin_m=10, variety=1.0), 4, 0.0, 0.2)
    tall = [b for b in city.buildings if b.height >= ROOF_MIN_HEIGHT_M and len(b.footprint) == 4]
    assert tall and np.mean([bool(roof_parts(b)) for b in tall]) > 0.8
    counts = []
    for b in tall:
        parts = roof_parts(b)
        again = roof_parts(b)
        assert [p.footprint.tobytes() for p in parts] == [p.footprint.tobytes() for p in again]
        roof = Polygon(b.footprint).buffer(-1.5 + 1e-6)
        polys = [Polygon(p.footprint) for p in parts]
        assert all(roof.contains(q) for q in polys)
        assert all(a.distance(c) >= 0.8 - 1e-6 for i, a in enumerate(polys) for c in polys[i + 1:])
        assert all(p.z0 == b.height and 0.8 < p.z1 - p.z0 < 3.2 for p in parts)
        counts.append(len(parts))
    assert max(counts) >= 3
    plain, _ = generate_grid(GridParams(blocks=(2, 2), pitch_m=60, margin_m=10), 4, 0.0, 0.2)
    assert not any(roof_parts(b) for b in plain.buildings)
    houses, _ = generate_grid(GridParams(style="residential", blocks=(2, 2), pitch_m=60, margin_m=10, variety=1.0),
                              4, 0.0, 0.2)
    assert not any(roof_parts(b) for b in houses.buildings if b.roof == "gabled" or b.height < ROOF_MIN_HEIGHT_M)
    # the mesh reaches the units' tops; without them, only the roof
    b = next(b for b in tall if roof_parts(b))
    one = dataclasses.replace(city, buildings=[b], trees=[], cars=[], furniture=[])
    w = build_world(one)
    pos = w.chunks[0].positions[w.chunks[0].faces[:w.chunks[0].cell_faces[-2]].ravel()]
    assert np.isclose(pos[:, 2].max(), max(p.z1 for p in roof_parts(b)), atol=1e-3)
    # the tile shows each unit's top in its own colour, lit
    img, labels = paint_tile(one, 0.2, 1)
    h = img.shape[0]
    for p in roof_parts(b):
        cx, cy = p.footprint.mean(axis=0)
        r, c = int(h - cy / 0.2), int(cx / 0.2)
        assert labels[r, c] == CLASS_ID["building"]
        assert np.allclose(img[r, c], np.minimum(255, np.asarray(p.rgb) * 1.08), atol=2)
