"""Odometry from the sensors: stereo visual odometry (satloc.tracking.vo) on a simulated drive, the drifting wheel-odometry
model (satloc.tracking.track.noisy_odometry's bias and scale error), and KITTI's OXTS odometry
(satloc.datasets.kitti.oxts_odometry) on our synthetic drive and, when present, the real excerpt in
../shared/realdata."""
import math

import numpy as np
import pytest
from kittifixture import DEFAULT_FRAME, SynthRig, write_kitti_drive
from realfixtures import REAL

from satloc import ConfigError, Frame, Pose2, Sequence
from satloc.config import from_dict
from satloc.datasets.kitti import OXTS_FIELDS, load_kitti, oxts_odometry
from satloc.geometry import wrap_angle
from satloc.tracking.track import noisy_odometry, relative_motion
from satloc.tracking.vo import StereoVO, VOConfig, integrate_odometry, odometry_drift, visual_odometry

needs_real = pytest.mark.skipif(not REAL.is_dir(), reason="shared KITTI fixture absent")


def true_odometry(poses):
    poses = np.asarray(poses, np.float64)
    out = np.full((len(poses), 3), np.nan)
    for i in range(1, len(poses)):
        out[i] = relative_motion(Pose2(*poses[i - 1]), Pose2(*poses[i]))
    return out


# --- visual odometry on a simulated drive ----------------------------------------------------------------

@pytest.fixture(scope="module")
def drive():
    """60 frames of residential's database route from 140 m, one per simulator step, through its 94-degree
    left turn (28 m: the autopilot slows for the turn); seeded, in memory."""
    from satloc_env.envs.record import make_env

    env = make_env(scene="residential", localizer=None, depth=True)
    try:
        obs, info = env.reset(seed=0, options={"start_s_m": 140.0})
        frames = []
        for i in range(60):
            frames.append(Frame(obs["left"], obs["right"], Pose2.from_array(info["pose"]), 0.1 * i, obs["depth"]))
            obs, _, _, _, info = env.step(env.unwrapped.autopilot_action())
        camera = env.unwrapped.camera
    finally:
        env.close()
    return Sequence(camera, frames, "vo_drive")


@pytest.fixture(scope="module")
def drive_vo(drive):
    return visual_odometry(drive)


def test_visual_odometry_recovers_the_motion_of_a_drive(drive, drive_vo):
    # measured: largest step error 0.021 m and 0.036 degrees (steps 0.3-0.8 m), 0.15 % / 0.03 degrees at the end
    poses, odo = drive.poses, drive_vo
    truth = true_odometry(poses)
    turn = math.degrees(np.unwrap(poses[:, 2])[-1] - poses[0, 2])
    assert turn > 80 and drive.path_length() > 25                      # the drive turns a corner
    assert np.all(np.isnan(odo[0])) and np.all(np.isfinite(odo[1:]))    # no previous frame for row 0
    step = np.hypot(truth[1:, 0], truth[1:, 1])
    err = np.hypot(*(odo[1:, :2] - truth[1:, :2]).T)
    assert step.min() > 0.25 and err.max() < 0.1                         # well under the step, every step
    assert np.degrees(np.abs(wrap_angle(odo[1:, 2] - truth[1:, 2]))).max() < 0.3
    assert math.degrees(np.sum(odo[1:, 2])) == pytest.approx(turn, abs=1.0)
    d = odometry_drift(odo, poses, (20.0,))
    assert d["failed_steps"] == 0 and d["end_error_pct"] < 1.5 and d["end_heading_deg"] < 1.0
    assert d["segments"]["20"]["trans_pct"] < 1.5 and d["segments"]["20"]["rot_deg_per_100m"] < 5.0


def test_step_by_step_is_the_sequence_run_and_deterministic(drive, drive_vo):
    vo = StereoVO(drive.camera)
    steps = np.array([vo.step(f.left, f.right) for f in drive])
    assert np.array_equal(steps, drive_vo, equal_nan=True)
    assert vo.last["failure"] is None and vo.last["inliers"] >= VOConfig().min_inliers
    vo.reset()                                                           # forgets the previous frame
    assert np.all(np.isnan(vo.step(drive[5].left, drive[5].right)))
    assert np.all(np.isfinite(vo.step(drive[6].left, drive[6].right)))


def test_blank_frame_gives_nan_and_the_next_steps_recover(drive, drive_vo):
    frames = [drive[i] for i in range(40)]
    grey = np.full_like(frames[20].left, 128)
    frames[20] = Frame(grey, grey.copy(), frames[20].pose, frames[20].timestamp, frames[20].depth)
    vo = StereoVO(drive.camera)
    odo = []
    for i, f in enumerate(frames):
        odo.append(vo.step(f.left, f.right))
        if i in (20, 21):
            assert vo.last["failure"]                                    # says why, never raises
    odo = np.array(odo)
    bad = np.flatnonzero(~np.isfinite(odo).all(axis=1))
    assert bad.tolist() == [0, 20, 21]                                   # into the blank frame and out of it
    assert np.array_equal(odo[:20], drive_vo[:20], equal_nan=True)
    truth = true_odometry(drive.poses[:40])
    assert np.hypot(*(odo[22:, :2] - truth[22:, :2]).T).max() < 0.1      # measuring again from the next frame
    d = odometry_drift(odo, drive.poses[:40], ())
    assert d["failed_steps"] == 2


def test_frame_depth_is_an_explicit_option(drive):
    frames = Sequence(drive.camera, [drive[i] for i in range(8)])
    odo = visual_odometry(frames, VOConfig(depth_source="frame", depth_edge_px=1.0))
    truth = true_odometry(frames.poses)
    assert np.hypot(*(odo[1:, :2] - truth[1:, :2]).T).max() < 0.1
    vo = StereoVO(drive.camera, VOConfig(depth_source="frame"))
    with pytest.raises(ConfigError, match="depth_source 'frame' but no depth"):
        vo.step(frames[0].left, frames[0].right)


def test_vo_config_and_input_errors(drive):
    assert from_dict(VOConfig, {"detector": "orb", "max_features": 500}) == VOConfig(detector="orb", max_features=500)
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['window'\]"):
        from_dict(VOConfig, {"window": 9}, "vo")
    with pytest.raises(ConfigError, match="detector: expected one of"):
        from_dict(VOConfig, {"detector": "sift"}, "vo")
    with pytest.raises(ConfigError, match="lk_window_px: expected an odd number"):
        from_dict(VOConfig, {"lk_window_px": 8}, "vo")
    with pytest.raises(ConfigError, match="block_size must be odd"):
        from_dict(VOConfig, {"stereo": {"block_size": 4}}, "vo")
    for bad in ({"ransac_px": 0.0}, {"min_inliers": 3}, {"gftt_quality": 1.5}, {"depth_edge_px": float("nan")}):
        with pytest.raises(ConfigError):
            VOConfig(**bad)
    with pytest.raises(ConfigError, match="expected a VOConfig"):
        StereoVO(drive.camera, {"detector": "orb"})
    f = drive[0]
    with pytest.raises(ConfigError, match="the left image is uint8"):
        StereoVO(drive.camera).step(f.left[:100], f.right)


def test_orb_features_also_track(drive):
    frames = Sequence(drive.camera, [drive[i] for i in range(6)])
    odo = visual_odometry(frames, VOConfig(detector="orb"))
    truth = true_odometry(frames.poses)
    ok = np.isfinite(odo[1:]).all(axis=1)
    assert ok.sum() >= 3 and np.hypot(*(odo[1:][ok, :2] - truth[1:][ok, :2]).T).max() < 0.2


# --- drifting wheel odometry and the drift measure -------------------------------------------------------

#: noisy_odometry(OLD_POSES, (0.02, 0.01), seed=3) as it was before its bias parameters (float.hex, bit for bit)
OLD_POSES = np.array([[0, 0, 0], [5, 0, 0.1], [9, 1, 0.5], [np.nan] * 3, [12, 3, 0.6], [14, 7, 1.2], [15, 11, 1.5]])
OLD_ODOMETRY = [
    ("nan", "nan", "nan"),
    ("0x1.4d0fd78600d5bp+2", "-0x1.05b339b39c2efp-2", "0x1.aab9af254f288p-4"),
    ("0x1.021d2c5d0f478p+2", "0x1.1ddf4686cd558p-1", "0x1.97646ccb044a8p-2"),
    ("nan", "nan", "nan"),
    ("nan", "nan", "nan"),
    ("0x1.f129996ffc1ddp+1", "0x1.0e6007ea82e23p+1", "0x1.2dcc316d011d5p-1"),
    ("0x1.03bafcdaa9eb5p+2", "0x1.1d40b083b4b3ep-1", "0x1.30c1d895a82fcp-2"),
]


def _arc_poses(n=201, step=1.0, turn=0.004):
    yaw = 0.3 + turn * np.arange(n)
    xy = np.cumsum(np.stack([step * np.cos(yaw), step * np.sin(yaw)], 1), axis=0)
    return np.column_stack([xy, wrap_angle(yaw)])


def test_noisy_odometry_without_bias_is_unchanged():
    old = np.array([[float.fromhex(v) for v in row] for row in OLD_ODOMETRY])
    for new in (noisy_odometry(OLD_POSES, (0.02, 0.01), 3),
                noisy_odometry(OLD_POSES, (0.02, 0.01), 3, scale_error=0.0, yaw_bias=0.0)):
        assert new.tobytes() == old.tobytes()                            # bit for bit, NaN rows included
    poses = _arc_poses(50)
    assert noisy_odometry(poses, (0.05, 0.003), 7).tobytes() == noisy_odometry(
        poses, (0.05, 0.003), 7, scale_error=0.0, yaw_bias=0.0).tobytes()


def test_scale_error_and_yaw_bias_drift_as_specified():
    poses = _arc_poses()
    dist = float(np.sum(np.hypot(*np.diff(poses[:, :2], axis=0).T)))          # 200 m
    scaled = noisy_odometry(poses, (0.0, 0.0), scale_error=0.03)
    assert np.sum(np.hypot(scaled[1:, 0], scaled[1:, 1])) == pytest.approx(1.03 * dist, rel=1e-9)
    d = odometry_drift(scaled, poses, (50.0, 100.0))
    assert 2.95 < d["segments"]["100"]["trans_pct"] <= 3.0                 # 3 % of the chord of a 100 m arc
    assert d["segments"]["100"]["rot_deg_per_100m"] == pytest.approx(0.0, abs=1e-6)
    curled = noisy_odometry(poses, (0.0, 0.0), yaw_bias=1e-3)                  # 1 mrad per metre
    assert np.sum(curled[1:, 2]) - np.sum(true_odometry(poses)[1:, 2]) == pytest.approx(1e-3 * dist, rel=1e-9)
    d = odometry_drift(curled, poses, (100.0,))
    assert d["end_heading_deg"] == pytest.approx(math.degrees(0.2), abs=1e-3)
    assert d["segments"]["100"]["rot_deg_per_100m"] == pytest.approx(math.degrees(0.1), rel=0.02)
    # with noise the bias adds to the same draws: the noise is the same for the same seed
    noisy = noisy_odometry(poses, (0.02, 0.01), seed=4)
    both = noisy_odometry(poses, (0.02, 0.01), seed=4, scale_error=0.03, yaw_bias=1e-3)
    truth = true_odometry(poses)
    assert np.allclose(both[1:] - noisy[1:], np.column_stack([0.03 * truth[1:, :2], 1e-3 * np.hypot(*truth[1:, :2].T)]))
    for bad in ({"scale_error": -1.0}, {"yaw_bias": float("inf")}, {"scale_error": float("nan")}):
        with pytest.raises(ConfigError, match="odometry bias"):
            noisy_odometry(poses, (0.0, 0.0), **bad)


def test_integrate_odometry_and_drift_errors():
    poses = _arc_poses(20)
    odo = true_odometry(poses)
    assert np.allclose(integrate_odometry(odo, poses[0]), poses)
    odo[5] = np.nan                                                      # unknown motion: counted as none
    assert np.allclose(integrate_odometry(odo, poses[0])[5], poses[4])
    assert odometry_drift(odo, poses, ())["failed_steps"] == 1
    with pytest.raises(ConfigError, match="same shape"):
        odometry_drift(odo[:5], poses, ())


# --- KITTI: odometry from the OXTS motion sensors --------------------------------------------------------

RIG = SynthRig()


def _imu_arc_drive(root, n=8, keep=None, radius=80.0, step=1.0, dt=0.1):
    """A synthetic KITTI drive whose IMU drives a circular arc at constant speed and yaw rate (no side slip),
    with vf and wu written to match; returns (drive folder, the vehicle poses)."""
    turn = step / radius
    th = 0.6 + turn * np.arange(n)
    imu = np.column_stack([3.0 + radius * (np.sin(th) - math.sin(0.6)), -2.0 - radius * (np.cos(th) - math.cos(0.6)),
                           th])
    off = Pose2(*RIG.camera_in_imu()[:2], RIG.yaw)                      # the vehicle frame in the IMU frame
    poses = np.array([(Pose2(*p) @ off).as_array() for p in imu])
    drv = write_kitti_drive(root, n, poses=poses, keep=keep, dt=dt)
    for f in sorted((drv / "oxts" / "data").glob("*.txt")):
        vals = f.read_text().split()
        vals[OXTS_FIELDS.index("vf")] = repr(step / dt)
        vals[OXTS_FIELDS.index("wu")] = repr(turn / dt)
        f.write_text(" ".join(vals) + "\n")
    return drv, poses


def test_oxts_odometry_recovers_a_synthetic_drive(tmp_path):
    drv, poses = _imu_arc_drive(tmp_path / "a")
    seq = load_kitti(drv, DEFAULT_FRAME)
    want = true_odometry(poses)
    for clock in ("image", "oxts"):
        odo = oxts_odometry(seq, clock)
        assert np.all(np.isnan(odo[0]))
        assert np.abs(odo[1:, :2] - want[1:, :2]).max() < 1e-3, clock  # the arc's motion of the vehicle frame
        assert np.abs(odo[1:, 2] - want[1:, 2]).max() < 1e-6
    view = seq.view([0, 2, 4, 5])                                        # a view: steps over 2, 2 and 1 frames
    odo = oxts_odometry(view)
    assert np.abs(odo[1:, :2] - true_odometry(poses[[0, 2, 4, 5]])[1:, :2]).max() < 1e-3
    # an excerpt: frames 3 and 4 absent; the 0.3 s between 2 and 5 is interpolated, or NaN beyond max_gap_s
    drv, poses = _imu_arc_drive(tmp_path / "b", keep=[0, 1, 2, 5, 6, 7])
    seq = load_kitti(drv, DEFAULT_FRAME)
    assert np.abs(oxts_odometry(seq)[3, :2] - true_odometry(poses[[2, 5]])[1, :2]).max() < 1e-3
    gap = oxts_odometry(seq, "oxts", max_gap_s=0.2)
    assert np.flatnonzero(~np.isfinite(gap).all(axis=1)).tolist() == [0, 3]
    # on the image clock frame 5's image comes 6.6 ms before its OXTS sample: inside the gap too
    gap = oxts_odometry(seq, "image", max_gap_s=0.2)
    assert np.flatnonzero(~np.isfinite(gap).all(axis=1)).tolist() == [0, 3, 4]


def test_oxts_odometry_errors(tmp_path, drive):
    with pytest.raises(ConfigError, match="was not read by load_kitti"):
        oxts_odometry(drive)
    drv, _ = _imu_arc_drive(tmp_path, n=3)
    seq = load_kitti(drv, DEFAULT_FRAME)
    with pytest.raises(ConfigError, match="clock: expected one of"):
        oxts_odometry(seq, "gps")
    with pytest.raises(ConfigError, match="max_gap_s > 0"):
        oxts_odometry(seq, max_gap_s=0)


@needs_real
def test_oxts_and_visual_odometry_on_real_kitti():
    seq = load_kitti(REAL)
    poses = seq.poses
    oxts = oxts_odometry(seq)
    assert np.all(np.isfinite(oxts[1:]))
    # measured on drive 0023 (6 steps, 5.6 m): OXTS speed integrates to 2.3 % less than the OXTS positions
    # move; heading within 0.03 degrees; per step 0.05 m (the positions step 0.89 / 0.98 m alternately)
    d = odometry_drift(oxts, poses, ())
    assert d["end_error_pct"] < 4.0 and d["end_heading_deg"] < 0.2 and d["step_yaw_rmse_deg"] < 0.1
    # VO at half resolution: measured 0.4-0.7 % of the distance and 0.06-0.11 degrees from the poses
    half = seq.view(camera=seq.camera.resized(621, 188, 0.5))
    odo = visual_odometry(half)
    assert np.all(np.isfinite(odo[1:]))
    d = odometry_drift(odo, poses, ())
    assert d["end_error_pct"] < 2.5 and d["end_heading_deg"] < 0.5
    assert np.abs(odo[1:, 2] - oxts[1:, 2]).max() < math.radians(0.2)    # per step against the yaw rate


# --- the benchmark command -------------------------------------------------------------------------------

def test_bench_vo_prints_drift_rows(tmp_path, capsys):
    import json

    from satloc_env.cli import main

    assert main(["bench", "vo", "--frames", "12", "--work", str(tmp_path), "--kitti", str(tmp_path / "none"),
                 "--quiet"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [(r["data"], r.get("depth_source")) for r in rows] == [("sim", "stereo"), ("sim", "frame"), ("kitti", None)]
    for r in rows[:2]:
        assert r["frames"] == 12 and r["failed_steps"] == 0 and r["end_error_pct"] < 2.0 and r["ms_per_frame"] > 0
        assert r["scene"] == "residential" and "segments" in r and "end_heading_deg_per_100m" in r
    assert "no KITTI drive at" in rows[2]["skipped"]
    if REAL.is_dir():
        assert main(["bench", "vo", "--frames", "12", "--work", str(tmp_path), "--quiet"]) == 0  # recording reused
        rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
        assert [(r["data"], r.get("clock"), r.get("resolution")) for r in rows[2:]] == [
            ("kitti_oxts", "image", None), ("kitti_oxts", "oxts", None), ("kitti", None, "full"),
            ("kitti", None, "half")]
        assert all(r["vs_poses"]["failed_steps"] == 0 and r["vs_oxts"]["end_error_pct"] < 6 for r in rows[4:])


def test_the_environment_observes_visual_odometry_on_request():
    """odometry="visual": the observation is the stereo VO of the rendered pairs, close to the true motion;
    the default stays the noisy truth; the key is an episode option."""
    import gymnasium as gym

    import satloc_env  # noqa: F401

    env = gym.make("satloc/SatLoc-v0", scene="residential", localizer=None, odometry="visual")
    obs, info = env.reset(seed=0)
    errs = []
    for _ in range(12):
        obs, _, _, _, info = env.step(env.unwrapped.autopilot_action())
        assert obs["odometry"].dtype == np.float32
        errs.append(np.abs(obs["odometry"].astype(np.float64) - info["odometry_true"]))
    errs = np.array(errs)
    assert np.isfinite(errs).all() and errs[:, 0].max() < 0.15 and errs[:, 2].max() < 0.01   # 2 m steps
    # the default, and the option per episode
    obs, info = env.reset(seed=0, options={"odometry": "noisy_truth"})
    obs, _, _, _, info = env.step(env.unwrapped.autopilot_action())
    assert env.unwrapped._vo is None and np.isfinite(obs["odometry"]).all()
    env.close()
