"""EFM baseline (satloc.baselines.efm): homography recovery, retrieval of the right database image, save/load
and errors, on textured images made here."""
import dataclasses
import math

import cv2
import numpy as np
import pytest

from satloc import ConfigError, FormatError, Frame, Pose2, Sequence, StereoCamera
from satloc.baselines.efm import Efm, EfmConfig, estimate_homography, sift_features
from satloc.persist import save_npz

W, H = 320, 240
CAM = StereoCamera(width=W, height=H, fx=300.0, fy=300.0, cx=W / 2, cy=H / 2, baseline=0.5)


def textured(seed: int, w: int = W, h: int = H) -> np.ndarray:
    """An RGB image with plenty of distinct corners and blobs: random rectangles, discs and lines over
    smoothed noise."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.integers(0, 255, (h, w, 3)).astype(np.uint8), (0, 0), 3)
    for _ in range(60):
        c = tuple(int(v) for v in rng.integers(0, 255, 3))
        kind = rng.integers(0, 3)
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        if kind == 0:
            cv2.rectangle(img, (x, y), (x + int(rng.integers(5, 40)), y + int(rng.integers(5, 40))), c, -1)
        elif kind == 1:
            cv2.circle(img, (x, y), int(rng.integers(3, 20)), c, -1)
        else:
            cv2.line(img, (x, y), (int(rng.integers(0, w)), int(rng.integers(0, h))), c, 2)
    return img


def warp(img: np.ndarray, Hm: np.ndarray) -> np.ndarray:
    return cv2.warpPerspective(img, Hm, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_REFLECT)


# a mild perspective change with a shift, like a few metres of driving
H_TRUE = np.array([[1.06, 0.03, -9.0], [-0.02, 1.04, 5.0], [2e-5, 1e-5, 1.0]])
CORNERS = np.array([[0, 0], [W - 1, 0], [W - 1, H - 1], [0, H - 1]], np.float64)


def apply(Hm: np.ndarray, pts: np.ndarray) -> np.ndarray:
    p = np.c_[pts, np.ones(len(pts))] @ Hm.T
    return p[:, :2] / p[:, 2:]


def test_recovers_known_homography_within_a_pixel():
    a = textured(1)
    b = warp(a, H_TRUE)
    Hest, n = estimate_homography(a, b)
    assert Hest is not None and n >= 50
    err = np.linalg.norm(apply(Hest, CORNERS) - apply(H_TRUE, CORNERS), axis=1)
    assert err.max() < 1.0, err
    # at half scale the keypoints still come back in full-resolution pixels
    Hh, nh = estimate_homography(a, b, EfmConfig(scale=0.5))
    assert Hh is not None and nh >= 20
    assert np.linalg.norm(apply(Hh, CORNERS) - apply(H_TRUE, CORNERS), axis=1).max() < 2.0
    # unrelated images: no homography with many inliers
    _, n_bad = estimate_homography(a, textured(99))
    assert n_bad < 12


def test_sift_features_shapes_and_limits():
    img = textured(2)
    xy, d = sift_features(img, EfmConfig(features=50))
    assert xy.shape == (50, 2) and d.shape == (50, 128) and d.dtype == np.uint8
    assert np.all((xy >= -0.5) & (xy <= np.array([W - 0.5, H - 0.5])))
    xy0, d0 = sift_features(np.full((H, W, 3), 128, np.uint8))
    assert xy0.shape == (0, 2) and d0.shape == (0, 128)
    with pytest.raises(ConfigError, match="uint8"):
        sift_features(img.astype(np.float32))


def database(n: int = 6) -> Sequence:
    frames = [Frame(textured(10 + i), textured(10 + i), Pose2(10.0 * i, 2.0, 0.0), float(i)) for i in range(n)]
    return Sequence(CAM, frames, name="db")


@pytest.fixture(scope="module")
def efm() -> Efm:
    return Efm.build(database(), EfmConfig(features=400), progress=False)


def test_right_database_image_wins(efm):
    assert len(efm) == 6
    q = warp(textured(13), H_TRUE)
    # the revisit is darker too
    q = np.clip(q.astype(np.float32) * 0.7 + 10, 0, 255).astype(np.uint8)
    r = efm.localize(Frame(q, q))
    assert int(np.argmax(r.posterior)) == 3
    assert r.posterior[3] > 0.9 and r.posterior.sum() == pytest.approx(1.0)
    assert math.hypot(r.estimate.x - 30.0, r.estimate.y - 2.0) < 1.0
    assert r.inlier and r.inlier_score >= 50
    assert r.candidates.shape == (6, 3) and r.num_samples > 100
    # an image unlike every database image: declared outside the map, low score
    r2 = efm.localize(textured(77))
    assert not r2.inlier and r2.inlier_score < 30
    # the FLANN matcher and the fundamental-matrix verification find the same image
    for cfg in (dataclasses.replace(efm.config, matcher="flann"),
                dataclasses.replace(efm.config, geometry="fundamental")):
        assert int(np.argmax(efm.with_config(cfg).localize(q).posterior)) == 3


def test_brute_force_matches_the_pairwise_ratio_test(efm):
    """The blocked matcher gives each database image the same ratio-test matches as matching the pair alone."""
    from satloc.baselines.efm import _ratio_matches

    q = textured(12)
    _, qd = sift_features(q, efm.config)
    ok, nearest = efm._match_bf(qd)
    for i in range(len(efm)):
        rows, near = _ratio_matches(qd, efm.desc[efm.offsets[i]:efm.offsets[i + 1]], efm.config.ratio)
        np.testing.assert_array_equal(np.flatnonzero(ok[i]), rows)
        np.testing.assert_array_equal(nearest[i, rows], near)


def test_frames_without_pose_are_left_out():
    frames = [Frame(textured(10 + i), textured(10 + i), Pose2(float(i), 0.0, 0.0) if i != 1 else None, float(i))
              for i in range(3)]
    e = Efm.build(Sequence(CAM, frames), EfmConfig(features=100), progress=False, workers=1)
    assert len(e) == 2 and e.frame_index.tolist() == [0, 2]
    with pytest.raises(ConfigError, match="no frame has a pose"):
        Efm.build(Sequence(CAM, [Frame(textured(1), textured(1))]), progress=False)


def test_save_load_round_trip(efm, tmp_path):
    path = tmp_path / "efm.npz"
    efm.save(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["efm.npz"]   # nothing half-written left over
    back = Efm.load(path)
    assert back.config == efm.config and back.camera == efm.camera and back.name == "db"
    np.testing.assert_array_equal(back.desc, efm.desc)
    np.testing.assert_array_equal(back.offsets, efm.offsets)
    q = warp(textured(11), H_TRUE)
    a, b = efm.localize(q), back.localize(q)
    np.testing.assert_array_equal(a.posterior, b.posterior)
    assert a.estimate == b.estimate and a.inlier_score == b.inlier_score
    # matching settings can change on load, extraction settings cannot
    looser = Efm.load(path, dataclasses.replace(efm.config, ratio=0.9, inlier_threshold=5.0))
    assert looser.config.ratio == 0.9
    with pytest.raises(ConfigError, match="features"):
        Efm.load(path, dataclasses.replace(efm.config, features=10))


def test_damaged_and_foreign_files(efm, tmp_path):
    path = tmp_path / "efm.npz"
    efm.save(path)
    raw = path.read_bytes()
    (tmp_path / "cut.npz").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(FormatError, match="cut.npz"):
        Efm.load(tmp_path / "cut.npz")
    with pytest.raises(FormatError, match="missing.npz"):
        Efm.load(tmp_path / "missing.npz")
    save_npz(tmp_path / "other.npz", "dictionary", {"a": np.zeros(3)})
    with pytest.raises(FormatError, match="efm_database"):
        Efm.load(tmp_path / "other.npz")
    arrays = {"xy": efm.xy, "desc": efm.desc, "offsets": efm.offsets, "poses": efm.poses,
              "frame_index": efm.frame_index}
    meta = {"config": dataclasses.asdict(efm.config), "camera": None, "name": "x"}
    save_npz(tmp_path / "noposes.npz", "efm_database", {k: v for k, v in arrays.items() if k != "poses"}, meta)
    with pytest.raises(FormatError, match="missing array 'poses'"):
        Efm.load(tmp_path / "noposes.npz")
    save_npz(tmp_path / "badoff.npz", "efm_database", dict(arrays, offsets=efm.offsets[::-1].copy()), meta)
    with pytest.raises(FormatError, match="offsets"):
        Efm.load(tmp_path / "badoff.npz")
    save_npz(tmp_path / "floatdesc.npz", "efm_database", dict(arrays, desc=efm.desc.astype(np.float32)), meta)
    with pytest.raises(FormatError, match="'desc'"):
        Efm.load(tmp_path / "floatdesc.npz")
    save_npz(tmp_path / "badcfg.npz", "efm_database", arrays, dict(meta, config={"ratio": 3.0}))
    with pytest.raises(FormatError, match="ratio"):
        Efm.load(tmp_path / "badcfg.npz")


def test_config_and_query_errors(efm):
    with pytest.raises(ConfigError, match="ratio"):
        EfmConfig(ratio=1.5)
    with pytest.raises(ConfigError, match="ransac_px"):
        EfmConfig(ransac_px=0)
    with pytest.raises(ConfigError, match="matcher"):
        EfmConfig(matcher="kd")
    with pytest.raises(FormatError, match="query"):
        efm.localize(textured(1, w=100, h=80))
    with pytest.raises(FormatError, match="query frame"):
        efm.localize(Frame(textured(1, w=100, h=80), textured(1, w=100, h=80)))
    # a blank query: no features, no match, declared outside
    r = efm.localize(np.zeros((H, W, 3), np.uint8))
    assert r.num_samples == 0 and not r.inlier and r.inlier_score == 0
    np.testing.assert_allclose(r.posterior, 1 / 6)
