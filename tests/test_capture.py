"""The satellite map as a capture of the world (satloc_env.world.capture): at satellite_gap 0 the tile is the
ground's copy, at the default it shares no texture below the sensor's resolution with the rendered ground."""
import cv2
import numpy as np
import pytest

from satloc import ConfigError
from satloc.labels import CLASS_ID as C
from satloc_env.world.capture import DEFAULT_GAP, PARTS, capture_params, capture_tile, class_lowpass
from satloc_env.world.scene import load_scene
from satloc_env.world.tile import paint_tile

GROUND = [C[k] for k in ("road", "sidewalk", "grass", "parking", "soil")]


SMALL = """
name: small_city
seed: 3
generator: {type: grid, style: city, blocks: [2, 2], pitch_m: 80, road_width_m: 12, sidewalk_m: 3, margin_m: 20}
meters_per_pixel: 0.2
ground_mpp: 0.1
routes:
  main: {waypoints: [[20, 20], [180, 20], [180, 180]]}
"""


@pytest.fixture(scope="module")
def city(tmp_path_factory):
    """A 2 x 2 block city (200 m x 200 m): the capture's cost grows with the ground's pixels."""
    p = tmp_path_factory.mktemp("scene") / "small_city.yaml"
    p.write_text(SMALL)
    sc = load_scene(p)
    return sc.layout, sc.spec.meters_per_pixel, sc.spec.seed, sc.satmap


def _interior(labels):
    out = np.zeros(labels.shape, bool)
    for c in GROUND:
        out |= cv2.erode((labels == c).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    return out


def fine_texture_correlation(ground_tile, ground_labels, tile, labels, sigma_px):
    """Correlation of the texture below ``sigma_px`` (within each class, away from class edges) of the
    ground as rendered (its copy at the tile's resolution) and of a tile, over ground pixels both agree on."""
    m = _interior(ground_labels) & _interior(labels) & (ground_labels == labels)
    a = (ground_tile.astype(np.float32) - class_lowpass(ground_tile, ground_labels, sigma_px)).mean(axis=2)[m]
    b = (tile.astype(np.float32) - class_lowpass(tile, ground_labels, sigma_px)).mean(axis=2)[m]
    return float(np.corrcoef(a, b)[0, 1]), int(m.sum())


def test_gap_zero_is_the_copy_and_the_default_shares_no_fine_texture(city):
    lay, mpp, seed, satmap = city
    copy, copy_labels = paint_tile(lay, mpp, seed)
    assert not np.array_equal(copy, satmap.image)        # a scene file without the knob: the default capture
    assert np.array_equal(satmap.image, capture_tile(lay, mpp, seed, DEFAULT_GAP)[0])
    t0, l0 = capture_tile(lay, mpp, seed, 0.0)
    assert np.array_equal(t0, copy) and np.array_equal(l0, copy_labels)
    sigma = capture_params(DEFAULT_GAP, mpp).gsd_m / mpp   # the sensor's resolution, in tile pixels
    r0, n0 = fine_texture_correlation(copy, copy_labels, t0, l0, sigma)
    assert r0 == pytest.approx(1.0) and n0 > 100_000
    t, lab = capture_tile(lay, mpp, seed, DEFAULT_GAP)
    r, n = fine_texture_correlation(copy, copy_labels, t, lab, sigma)
    assert n > 100_000
    assert abs(r) < 0.1, r
    # in between, some of it survives
    tq, lq = capture_tile(lay, mpp, seed, 0.25)
    rq, _ = fine_texture_correlation(copy, copy_labels, tq, lq, sigma)
    assert 0.2 < rq < 0.8


def test_capture_is_deterministic_and_its_parts_are_independent(city):
    lay, mpp, seed, _ = city
    a = capture_tile(lay, mpp, seed, 0.5)
    b = capture_tile(lay, mpp, seed, 0.5)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    other = capture_tile(lay, mpp, seed + 1, 0.5)
    assert not np.array_equal(a[0], other[0])
    # each part draws from its own generator: the warp moves the labels the same with or without the texture
    _, a_lab = capture_tile(lay, mpp, seed, 0.5, parts=("registration",))
    _, b_lab = capture_tile(lay, mpp, seed, 0.5, parts=("texture", "registration"))
    assert np.array_equal(a_lab, b_lab)
    early = ("time", "lean", "texture", "blur")
    x = capture_tile(lay, mpp, seed, 0.5, parts=early)
    y = capture_tile(lay, mpp, seed, 0.5, parts=early + ("jpeg",))
    assert 0 < np.abs(x[0].astype(int) - y[0].astype(int)).mean() < 3    # JPEG at quality 80 moves a little


def test_the_own_texture_has_the_statistics_of_the_ground_s(city):
    """The texture part on the ground texture the tile is painted from: below the sensor's resolution its
    spread and grain are the ground's (within a quarter), its pattern is not; above, the ground is kept."""
    from satloc_env.world.capture import TEXTURE_SCALE, _neighbour_correlation, _own_texture

    lay, mpp, seed, _ = city
    gsd_px = capture_params(DEFAULT_GAP, mpp).gsd_m / lay.ground_mpp
    own = _own_texture(lay.ground_rgb, lay.ground_labels, TEXTURE_SCALE * gsd_px, 1.0, np.random.default_rng(0))
    m = _interior(lay.ground_labels)
    fine = [(im.astype(np.float32) - class_lowpass(im, lay.ground_labels, gsd_px)).mean(axis=2)
            for im in (lay.ground_rgb, own)]
    assert 0.75 < fine[1][m].std() / fine[0][m].std() < 1.25
    assert abs(_neighbour_correlation(fine[1]) - _neighbour_correlation(fine[0])) < 0.15
    assert abs(np.corrcoef(fine[0][m], fine[1][m])[0, 1]) < 0.05
    coarse = [class_lowpass(im, lay.ground_labels, 4 * TEXTURE_SCALE * gsd_px).mean(axis=2)
              for im in (lay.ground_rgb, own)]
    assert np.corrcoef(coarse[0][m], coarse[1][m])[0, 1] > 0.9


def test_each_part_does_what_it_says(city):
    lay, mpp, seed, _ = city
    copy, copy_labels = paint_tile(lay, mpp, seed)
    # lean: roofs displaced, so building labels move off their footprints
    _, lean_labels = capture_tile(lay, mpp, seed, 0.5, parts=("lean",))
    moved = (lean_labels == C["building"]) != (copy_labels == C["building"])
    assert moved.mean() > 0.005
    # registration: a smooth warp of the requested RMS (0.3 m at 0.5): labels move at edges only
    _, warped = capture_tile(lay, mpp, seed, 0.5, parts=("registration",))
    diff = (warped != copy_labels).mean()
    assert 0.005 < diff < 0.2
    # time: other parked cars, another sun (shadows elsewhere)
    timed, timed_labels = capture_tile(lay, mpp, seed, 0.5, parts=("time",))
    assert ((timed_labels == C["car"]) != (copy_labels == C["car"])).sum() > 200
    # blur: less energy at the finest scale
    blurred, _ = capture_tile(lay, mpp, seed, 0.5, parts=("blur",))
    lap = lambda im: float(np.abs(cv2.Laplacian(im.mean(axis=2).astype(np.float32), cv2.CV_32F)).mean())  # noqa: E731
    assert lap(blurred) < 0.7 * lap(copy)


def test_bad_gap_and_parts_are_refused(city):
    lay, mpp, seed, _ = city
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ConfigError, match="satellite_gap"):
            capture_tile(lay, mpp, seed, bad)
    with pytest.raises(ConfigError, match="unknown"):
        capture_tile(lay, mpp, seed, 0.5, parts=("sharpen",))
    assert set(PARTS) == {"time", "lean", "texture", "blur", "registration", "jpeg"}


def test_scene_knob_and_override(tmp_path, city):
    _, _, _, base_map = city
    base = tmp_path / "base.yaml"
    base.write_text(SMALL)
    copy = tmp_path / "copy.yaml"
    copy.write_text(SMALL + "knobs: {satellite_gap: 0.0}\n")
    sc = load_scene(copy)
    assert sc.spec.knobs.satellite_gap == 0.0 and load_scene(base).spec.knobs.satellite_gap == DEFAULT_GAP
    assert sc.satmap.image.shape == base_map.image.shape and not np.array_equal(sc.satmap.image, base_map.image)
    over = load_scene(base, satellite_gap=0.0)
    assert over.spec.knobs.satellite_gap == 0.0 and np.array_equal(over.satmap.image, sc.satmap.image)
    # the ground the camera renders is the same world
    assert np.array_equal(sc.layout.ground_rgb, load_scene(base).layout.ground_rgb)
    bad = tmp_path / "bad.yaml"
    bad.write_text(SMALL + "knobs: {satellite_gap: 2.0}\n")
    with pytest.raises(ConfigError, match="satellite_gap"):
        load_scene(bad)
    with pytest.raises(ConfigError, match="satellite_gap"):
        load_scene(base, satellite_gap=-1)


def test_a_scene_over_an_image_is_captured_without_a_texture_of_its_own():
    """suburb_utm (a GeoTIFF): the camera keeps seeing the image; at 0 the map is the image; at the default it
    is the image captured (another time, blur, warp, JPEG), its own detail kept: an image has no texture below
    its resolution for the capture's ``texture`` to replace, so that part (and ``coarse_texture``) is left out,
    and the image's detail at two sensor GSDs still correlates with the map's, less as the gap grows."""
    from satloc_env.world.capture import IMAGE_SKIPS, capture_image

    base = load_scene("suburb_utm", satellite_gap=0.0)
    cap = load_scene("suburb_utm")   # the default gap
    assert np.array_equal(base.satmap.image, base.layout.ground_rgb)
    assert np.array_equal(cap.layout.ground_rgb, base.layout.ground_rgb)
    assert cap.satmap.image.shape == base.satmap.image.shape
    assert not np.array_equal(cap.satmap.image, base.satmap.image)
    mpp, seed = base.spec.meters_per_pixel, base.spec.seed
    sigma = 2 * capture_params(DEFAULT_GAP, mpp).gsd_m / mpp
    labels = base.layout.ground_labels
    r0, n = fine_texture_correlation(base.satmap.image, labels, base.satmap.image, labels, sigma)
    assert r0 == pytest.approx(1.0) and n > 10_000
    rs = {}
    for gap, sc in ((0.5, cap), (1.0, load_scene("suburb_utm", satellite_gap=1.0))):
        rs[gap], _ = fine_texture_correlation(base.satmap.image, labels, sc.satmap.image, sc.satmap.labels, sigma)
    assert rs[0.5] > 0.3 and rs[1.0] < rs[0.5], rs
    # the texture parts, alone, leave the image as it is; with the others they change nothing
    assert set(IMAGE_SKIPS) >= {"texture", "coarse_texture"}
    alone, _ = capture_image(base.layout, mpp, seed, DEFAULT_GAP, ("texture", "coarse_texture"))
    assert np.array_equal(alone, base.layout.ground_rgb)
    with_texture, _ = capture_image(base.layout, mpp, seed, DEFAULT_GAP, ("time", "texture", "blur", "jpeg"))
    without, _ = capture_image(base.layout, mpp, seed, DEFAULT_GAP, ("time", "blur", "jpeg"))
    assert np.array_equal(with_texture, without)


def test_texture_correlation_by_scale(city):
    from satloc_env.world.capture import texture_correlation

    lay, mpp, seed, satmap = city
    copy, labels = paint_tile(lay, mpp, seed)
    scales = (0.6, 2.4, 9.6)
    same = texture_correlation(copy, labels, copy, labels, scales_m=scales, mpp=mpp)
    for cls in ("road", "grass"):   # an image against itself
        assert all(v == pytest.approx(1.0) for v in same[cls].values()), same
    # the default capture against the copy: the fine texture is its own (coarser scales are issue 46's)
    cap = texture_correlation(copy, labels, satmap.image, satmap.labels, scales_m=scales, mpp=mpp)
    assert cap["road"][0.6] < 0.2 and cap["grass"][0.6] < 0.2, cap
    # the same class edges and markings with a texture of its own at every scale: about 0 (edges do not count)
    rng = np.random.default_rng(0)
    noise = cv2.GaussianBlur(rng.normal(0, 1, labels.shape).astype(np.float32), (0, 0), 3.0)
    own = copy.astype(np.float32)
    for c in GROUND:
        m = labels == c
        own[m] = own[m].mean(axis=0) + 20 * noise[m][:, None] / noise[m].std()
    mark = labels == C["lane_marking"]
    own[mark] = 240
    other = texture_correlation(copy, labels, np.clip(own, 0, 255).astype(np.uint8), labels, scales_m=scales, mpp=mpp)
    for cls in ("road", "grass"):   # at 9.6 m this small city holds few independent patches: chance is wider
        assert abs(other[cls][0.6]) < 0.1 and abs(other[cls][2.4]) < 0.1 and abs(other[cls][9.6]) < 0.35, other
    assert np.isnan(texture_correlation(copy, labels, copy, labels, ("person",), (1.0,), mpp)["person"][1.0])


def test_coarse_texture_makes_the_map_s_texture_its_own_at_every_scale(city):
    from satloc_env.world.capture import OPTIONAL_PARTS, texture_correlation

    lay, mpp, seed, satmap = city
    scales = (0.6, 2.4, 4.8)
    base = texture_correlation(lay.ground_rgb, lay.ground_labels, satmap.image, satmap.labels, scales_m=scales,
                               mpp=mpp)
    img, lab = capture_tile(lay, mpp, seed, DEFAULT_GAP, PARTS + ("coarse_texture",))
    own = texture_correlation(lay.ground_rgb, lay.ground_labels, img, lab, scales_m=scales, mpp=mpp)
    for cls in ("road", "grass"):
        assert all(abs(v) < 0.15 for v in own[cls].values()), own
        assert base[cls][4.8] > own[cls][4.8] + 0.15, (base, own)   # the default capture keeps the coarse texture
    # an optional part is not in the default capture, and a capture with it is deterministic
    assert np.array_equal(satmap.image, capture_tile(lay, mpp, seed, DEFAULT_GAP)[0])
    assert "coarse_texture" in OPTIONAL_PARTS
    assert np.array_equal(img, capture_tile(lay, mpp, seed, DEFAULT_GAP, PARTS + ("coarse_texture",))[0])


def test_a_scene_names_its_capture_parts(tmp_path, city):
    from satloc_env.world.scene import Scene

    lay, mpp, seed, satmap = city
    parts = ["time", "lean", "texture", "blur", "registration", "jpeg", "traffic", "deep_shadows"]
    p = tmp_path / "parts.yaml"
    p.write_text(SMALL.replace("name: small_city", f"name: small_city\ncapture_parts: [{', '.join(parts)}]"))
    sc = load_scene(p)
    assert sc.spec.parts == tuple(parts)
    assert np.array_equal(sc.satmap.image, capture_tile(lay, mpp, seed, DEFAULT_GAP, parts)[0])
    assert not np.array_equal(sc.satmap.image, satmap.image)
    sc.save(tmp_path / "saved")
    assert Scene.load(tmp_path / "saved").spec.capture_parts == parts
    for bad in ("[time, wobble]", "[time, time]", "blur"):
        p.write_text(SMALL.replace("name: small_city", f"name: small_city\ncapture_parts: {bad}"))
        with pytest.raises(ConfigError, match="capture_parts"):
            load_scene(p)
