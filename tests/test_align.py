"""Bird's-eye alignment (satloc.tracking.align): geometry against a ground image synthesised from the map itself."""
import math

import cv2
import numpy as np
import pytest

from satloc import ConfigError, Pose2, StereoCamera
from satloc.tracking.align import AlignConfig, BevAligner, posterior_peaks


def textured_map(size_px=600, mpp=0.2, seed=3):
    """A (H, W, 3) float feature map of smooth random texture plus a few bright 'markings'."""
    rng = np.random.default_rng(seed)
    g = cv2.GaussianBlur(rng.standard_normal((size_px, size_px)).astype(np.float32), (0, 0), 2.0)
    g = (g - g.min()) / (g.max() - g.min())
    g[200:204, 100:500] = 1.0
    g[300:302, :] = 1.0
    return np.repeat(g[..., None], 3, axis=2), mpp, (0.0, size_px * mpp)


def render_ground(cam, feats, mpp, origin, pose, occluder=False):
    """The left image (features) and z-depth a camera at ``pose`` sees of the flat textured map."""
    v, u = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
    ray = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1)
    t = cam.map_from_camera(pose)
    d = ray @ t[:3, :3].T                       # ray directions in the map frame
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(d[..., 2] < -1e-6, -t[2, 3] / d[..., 2], 0.0)     # camera z-depth where the ray meets z=0
    wx, wy = t[0, 3] + z * d[..., 0], t[1, 3] + z * d[..., 1]
    mu = ((wx - origin[0]) / mpp - 0.5).astype(np.float32)
    mv = ((origin[1] - wy) / mpp - 0.5).astype(np.float32)
    img = cv2.remap(np.ascontiguousarray(feats), mu, mv, cv2.INTER_LINEAR)
    depth = z.astype(np.float32)
    if occluder:  # a box standing in front of the car: near depth over a patch of the image
        depth[cam.height // 2:, cam.width // 3: cam.width // 2] = 4.0
        img[cam.height // 2:, cam.width // 3: cam.width // 2] = 0.9
    return img, depth


@pytest.mark.parametrize("occluder", [False, True])
def test_alignment_recovers_the_pose_from_an_offset_seed(occluder):
    cam = StereoCamera.kitti_half()
    feats, mpp, origin = textured_map()
    truth = Pose2(60.0, 55.0, math.radians(20.0))
    img, depth = render_ground(cam, feats, mpp, origin, truth, occluder)
    al = BevAligner(cam, feats, mpp, origin, AlignConfig(search_m=2.0))
    seed = Pose2(truth.x + 0.9, truth.y - 0.7, truth.yaw + math.radians(1.0))
    a = al.align(img, depth, [seed])
    assert a is not None and a.correlation > 0.8
    assert a.pose.distance(truth) < 0.1
    assert abs(math.degrees(a.pose.yaw - truth.yaw)) < 0.6
    if occluder:   # the box is masked out of the bird's-eye view
        chans, mask = al.bev(img, depth)
        assert 0 < mask.sum() < mask.size


def test_alignment_prefers_the_matching_seed_and_weighs_the_prior():
    cam = StereoCamera.kitti_half()
    feats, mpp, origin = textured_map()
    truth = Pose2(60.0, 55.0, 0.3)
    img, depth = render_ground(cam, feats, mpp, origin, truth)
    far = Pose2(30.0, 80.0, 0.3)
    al = BevAligner(cam, feats, mpp, origin, AlignConfig())
    a = al.align(img, depth, [far, truth], np.array([0.0, -1.0]))
    assert a.peak == 1 and a.pose.distance(truth) < 0.1
    # an overwhelming prior against the matching seed wins
    strong = BevAligner(cam, feats, mpp, origin, AlignConfig(prior_weight=10.0))
    assert strong.align(img, depth, [far, truth], np.array([0.0, -1.0])).peak == 0


def test_alignment_needs_ground_and_valid_config():
    cam = StereoCamera.kitti_half()
    feats, mpp, origin = textured_map()
    al = BevAligner(cam, feats, mpp, origin, AlignConfig())
    wall = np.full((cam.height, cam.width), 3.0, np.float32)          # a wall 3 m ahead fills the view
    img = np.zeros((cam.height, cam.width, 3), np.float32)
    assert al.align(img, wall, [Pose2(60, 55, 0)]) is None
    with pytest.raises(ConfigError, match="forward_m"):
        AlignConfig(forward_m=(5.0, 2.0))
    with pytest.raises(ConfigError, match="channels"):
        AlignConfig(channels="depth")


def test_posterior_peaks_are_separated():
    cands = np.array([[0, 0, 0], [1, 0, 0], [10, 0, 0], [20, 0, 0]], float)
    post = np.array([0.4, 0.3, 0.2, 0.1])
    assert posterior_peaks(cands, post, 2, 6.0) == [0, 2]
    assert posterior_peaks(cands, post, 5, 6.0) == [0, 2, 3]
    assert posterior_peaks(cands, np.zeros(4), 3, 6.0) == []


def test_scan_is_the_correlation_at_every_candidate():
    cam = StereoCamera.kitti_half()
    feats, mpp, origin = textured_map()
    truth = Pose2(60.0, 55.0, math.radians(20.0))     # on a 2-degree bin centre: the scan's crop is truth's
    img, depth = render_ground(cam, feats, mpp, origin, truth)
    al = BevAligner(cam, feats, mpp, origin, AlignConfig(search_m=6.0))   # its crop covers the whole grid
    # candidates on a grid of (ahead, left) offsets from the truth, at its heading
    c, s = math.cos(truth.yaw), math.sin(truth.yaw)
    ahead, left = (g.ravel() for g in np.meshgrid(np.arange(-4.8, 4.81, 0.4), np.arange(-3.2, 3.21, 0.4),
                                                  indexing="ij"))
    cands = np.stack([truth.x + ahead * c - left * s, truth.y + ahead * s + left * c, np.full_like(ahead, truth.yaw)], 1)
    # the reference: the aligner's own correlation map around the truth (cell (margin, margin) = no offset)
    chans, mask = al.bev(img, depth)
    ref = sum(cv2.matchTemplate(cr, t, cv2.TM_CCOEFF_NORMED, mask=mask) for cr, t in zip(al._crop(truth), chans))
    ref /= len(chans)
    i = np.round(ahead / mpp).astype(int) + al.margin
    j = np.round(left / mpp).astype(int) + al.margin
    exact = al.scan(img, depth, cands, search_m=0.0)
    np.testing.assert_allclose(exact, ref[i, j], atol=1e-4)
    assert np.hypot(*(cands[int(np.argmax(exact)), :2] - [truth.x, truth.y])) < 1e-6 and exact.max() > 0.8
    # with a search window: the best correlation within +-1 m (5 cells) of each candidate
    m = 5
    win = al.scan(img, depth, cands, search_m=1.0)
    inner = (i >= m) & (i < ref.shape[0] - m) & (j >= m) & (j < ref.shape[1] - m)
    assert inner.sum() > 100
    np.testing.assert_allclose(win[inner], [ref[a - m:a + m + 1, b - m:b + m + 1].max()
                                            for a, b in zip(i[inner], j[inner])], atol=1e-4)


def test_scan_prefers_the_true_path():
    cam = StereoCamera.kitti_half()
    feats, mpp, origin = textured_map()
    truth = Pose2(60.0, 55.0, math.radians(20.0))
    img, depth = render_ground(cam, feats, mpp, origin, truth)
    al = BevAligner(cam, feats, mpp, origin, AlignConfig())
    # candidates along two paths: one through the truth (heading 20 deg), one elsewhere (heading 110 deg)
    s = np.arange(-20.0, 20.01, 0.5)
    h1, h2 = math.radians(20.0), math.radians(110.0)
    path1 = np.stack([truth.x + s * math.cos(h1), truth.y + s * math.sin(h1), np.full_like(s, h1)], 1)
    path2 = np.stack([40.0 + s * math.cos(h2), 70.0 + s * math.sin(h2), np.full_like(s, h2)], 1)
    cands = np.concatenate([path2, path1])
    corr = al.scan(img, depth, cands, search_m=1.0)
    assert corr.shape == (len(cands),)
    assert np.hypot(*(cands[int(np.argmax(corr)), :2] - [truth.x, truth.y])) <= 1.0 + 1e-6
    assert corr[: len(path2)].max() < corr.max() - 0.3
    # cached plan: the same answer the second time; a view without ground gives None; bad bins are refused
    assert np.array_equal(al.scan(img, depth, cands, search_m=1.0), corr)
    wall = np.full((cam.height, cam.width), 3.0, np.float32)
    assert al.scan(img, wall, cands) is None
    for bad in (0.0, 30.0):
        with pytest.raises(ConfigError, match="yaw_bin_deg"):
            al.scan(img, depth, cands, yaw_bin_deg=bad)


def render_grade(cam, feats, mpp, origin, pose, grade):
    """As :func:`render_ground`, the ground climbing ahead of the car at ``grade`` (z = grade x in the car's frame,
    the car level on it at x = 0: a road whose grade changes under the car)."""
    v, u = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
    ray = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1)
    t = cam.map_from_camera(pose)
    d = ray @ t[:3, :3].T
    o = t[:3, 3]
    c, s = math.cos(pose.yaw), math.sin(pose.yaw)
    ahead = lambda p: (p[..., 0] - pose.x) * c + (p[..., 1] - pose.y) * s   # noqa: E731
    den = d[..., 2] - grade * (d[..., 0] * c + d[..., 1] * s)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (grade * ahead(o) - o[2]) / den
    z = np.where((z > 0) & np.isfinite(z), z, 0.0)
    wx, wy = o[0] + z * d[..., 0], o[1] + z * d[..., 1]
    mu = ((wx - origin[0]) / mpp - 0.5).astype(np.float32)
    mv = ((origin[1] - wy) / mpp - 0.5).astype(np.float32)
    return cv2.remap(np.ascontiguousarray(feats), mu, mv, cv2.INTER_LINEAR), z.astype(np.float32)


def test_alignment_fits_the_ground_the_stereo_depth_shows():
    """A road that climbs 4 % ahead of a level car: the plane of the camera's mounting puts the ground 0.8 m
    too low at 20 m, so its bird's-eye view is stretched and most of it fails the depth check; the plane fitted
    to the depth (``fit_ground``) finds the grade and aligns as on flat ground."""
    cam = StereoCamera.kitti_half()
    feats, mpp, origin = textured_map()
    truth = Pose2(60.0, 55.0, math.radians(20.0))
    img, depth = render_grade(cam, feats, mpp, origin, truth, 0.04)
    seed = Pose2(truth.x + 0.9, truth.y - 0.7, truth.yaw + math.radians(1.0))
    fit = BevAligner(cam, feats, mpp, origin, AlignConfig(search_m=2.0, fit_ground=True))
    a, b, c = fit.ground_plane(depth)
    assert abs(a - 0.04) < 0.003 and abs(b) < 0.003 and abs(c) < 0.03
    mount = BevAligner(cam, feats, mpp, origin, AlignConfig(search_m=2.0, fit_ground=False))
    assert fit.bev(img, depth)[1].sum() > 1.5 * mount.bev(img, depth)[1].sum()
    got = fit.align(img, depth, [seed])
    assert got is not None and got.correlation > 0.8 and got.pose.distance(truth) < 0.15
    old = mount.align(img, depth, [seed])
    assert old is None or old.pose.distance(truth) > 2 * got.pose.distance(truth)
    # on flat ground the fitted plane is the mounting's
    img0, depth0 = render_ground(cam, feats, mpp, origin, truth)
    assert np.allclose(fit.ground_plane(depth0), 0.0, atol=5e-3)


def test_shift_penalty_holds_the_alignment_near_its_seed():
    """``shift_penalty`` (per m^2, 0.01 by default) charges a translation for its distance from the seed: a small one
    still lets a 1.1 m correction through (the correlation gains far more), a large one keeps the pose near the
    seed; a negative one is refused."""
    cam = StereoCamera.kitti_half()
    feats, mpp, origin = textured_map()
    truth = Pose2(60.0, 55.0, math.radians(20.0))
    img, depth = render_ground(cam, feats, mpp, origin, truth)
    seed = Pose2(truth.x + 0.9, truth.y - 0.7, truth.yaw)
    small = BevAligner(cam, feats, mpp, origin, AlignConfig(search_m=2.0, shift_penalty=0.01)).align(img, depth, [seed])
    assert small is not None and small.pose.distance(truth) < 0.1
    large = BevAligner(cam, feats, mpp, origin, AlignConfig(search_m=2.0, shift_penalty=1.0)).align(img, depth, [seed])
    assert large is not None and large.pose.distance(seed) < 0.5 and large.pose.distance(truth) > 0.6
    with pytest.raises(ConfigError, match="shift_penalty"):
        AlignConfig(shift_penalty=-0.1)
