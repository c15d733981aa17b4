"""The KITTI raw reader: our synthetic drive (exact recovery, excerpts, every bad input) and, when present,
the real 7-frame excerpt of 2011_09_26_drive_0023 in ../shared/realdata (calibration, poses, stereo depth)."""
import math
import pickle
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from kittifixture import DEFAULT_FRAME, SynthRig, default_poses, wall_images, write_calibration, write_kitti_drive

from satloc import ConfigError, FormatError
from satloc.datasets.kitti import OXTS_FIELDS, load_kitti, read_oxts_file, read_rig
from satloc.geoframe import GeoFrame
from satloc.geometry import wrap_angle
from satloc.stereo import StereoConfig, StereoDepth, depth_error

REAL = (Path(__file__).resolve().parents[2] / "shared" / "realdata" / "kitti_raw_2011_09_26_drive_0023_7frames"
        / "2011_09_26" / "2011_09_26_drive_0023_sync")
needs_real = pytest.mark.skipif(not REAL.is_dir(), reason="shared KITTI fixture absent")
RIG = SynthRig()


def _camera_equal(a, b, tol=1e-9):
    assert (a.width, a.height) == (b.width, b.height)
    for k in ("fx", "fy", "cx", "cy", "baseline", "mount_height", "pitch"):
        assert getattr(a, k) == pytest.approx(getattr(b, k), abs=tol), k


def _pose_err(got, want):
    return (np.linalg.norm(got[:, :2] - want[:, :2], axis=1).max(),
            np.abs(wrap_angle(got[:, 2] - want[:, 2])).max())


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    return write_kitti_drive(tmp_path_factory.mktemp("kitti"), 8, gray=True)


# --- our own drive: exact recovery ----------------------------------------------------------------------

def test_camera_poses_and_timestamps_recovered(drive):
    seq = load_kitti(drive, DEFAULT_FRAME)
    _camera_equal(seq.camera, RIG.camera())
    pos, ang = _pose_err(seq.poses, default_poses(8))
    assert pos < 0.01 and ang < 1e-9, (pos, ang)
    cal = seq.meta["calibration"]
    assert cal["camera_yaw_rad"] == pytest.approx(RIG.yaw) and cal["camera_roll_rad_dropped"] == pytest.approx(RIG.roll)
    assert np.allclose(cal["camera_in_imu_m"], RIG.camera_in_imu())
    lines = (drive / "image_02" / "timestamps.txt").read_text().splitlines()
    assert seq.meta["time_origin"] == lines[0]
    t = seq.timestamps
    assert t.dtype == np.float64 and t[0] == 0.0 and np.allclose(t, 0.1 * np.arange(8), atol=2e-6)
    # nanosecond digits are kept: frame 1's offset from the stamps' own digits
    ns = [int(s[-9:]) + 10**9 * int(s[17:19]) for s in lines[:2]]
    assert t[1] == pytest.approx((ns[1] - ns[0]) * 1e-9, abs=1e-12)
    assert seq.meta["source"] == "kitti_raw" and seq.meta["drive"] == "2011_09_26_drive_0001_sync"
    assert seq.meta["kitti_indices"] == list(range(8)) and seq.meta["num_listed"] == 8
    assert GeoFrame.from_dict(seq.meta["geo_frame"]) == DEFAULT_FRAME


def test_default_frame_is_the_first_kept_oxts_position(drive):
    seq = load_kitti(drive)
    rec = read_oxts_file(drive / "oxts" / "data" / "0000000000.txt")
    frame = GeoFrame.from_dict(seq.meta["geo_frame"])
    assert (frame.lon0, frame.lat0) == (rec[1], rec[0])
    # the IMU of frame 0 is the origin; the vehicle is the rotated camera offset away from it
    c, s = math.cos(rec[5]), math.sin(rec[5])
    ox, oy = RIG.camera_in_imu()[:2]
    assert np.allclose(seq.poses[0, :2], (c * ox - s * oy, s * ox + c * oy), atol=1e-9)
    back = DEFAULT_FRAME.to_map(frame.to_lonlat(seq.poses[:, :2]))
    assert np.linalg.norm(back - default_poses(8)[:, :2], axis=1).max() < 0.01


def test_gray_camera(drive):
    seq = load_kitti(drive, DEFAULT_FRAME, camera="gray")
    _camera_equal(seq.camera, RIG.camera("gray"))
    truth = default_poses(8)
    imu_yaw = truth[:, 2] - RIG.yaw
    d = RIG.camera_in_imu("gray")[:2] - RIG.camera_in_imu()[:2]
    shift = np.stack([np.cos(imu_yaw) * d[0] - np.sin(imu_yaw) * d[1], np.sin(imu_yaw) * d[0] + np.cos(imu_yaw) * d[1]], 1)
    assert np.abs(seq.poses[:, :2] - (truth[:, :2] + shift)).max() < 0.01
    f = seq[3]
    assert f.left.shape == (RIG.height, RIG.width, 3) and f.left.dtype == np.uint8
    assert np.array_equal(f.left[..., 0], f.left[..., 2])


def test_frames_read_on_demand_with_stereo_depth(tmp_path):
    drv = write_kitti_drive(tmp_path, 4)
    seq = load_kitti(drv)
    want_left, want_right = wall_images(RIG)(2, None)
    f = seq[2]
    assert np.array_equal(f.left, want_left) and np.array_equal(f.right, want_right)
    assert np.allclose(f.pose.as_array(), seq.poses[2]) and f.timestamp == seq.timestamps[2]
    depth = StereoDepth(seq.camera, StereoConfig(min_depth_m=2.0))(f.left, f.right)
    ok = depth > 0
    assert ok.mean() > 0.5 and np.median(depth[ok]) == pytest.approx(RIG.wall_depth, rel=0.01)
    again = pickle.loads(pickle.dumps(seq))  # a plain reader: the sequence can go to a worker process
    assert np.array_equal(again[2].right, want_right) and again.meta == seq.meta
    # images are read when asked for: changed after loading, they are checked again then
    (drv / "image_03" / "data" / "0000000001.png").unlink()
    with pytest.raises(FormatError, match=r"image_03/data/0000000001\.png: image file not found"):
        seq[1]
    _png(drv / "image_02" / "data" / "0000000003.png", 100, 48)
    with pytest.raises(FormatError, match=r"image_02/data/0000000003\.png: image is 100x48, expected 160x48"):
        seq[3]


@settings(max_examples=25, deadline=None)
@given(yaw=st.floats(-0.1, 0.1), pitch=st.floats(-0.1, 0.1), roll=st.floats(-0.1, 0.1),
       x=st.floats(-2, 2), y=st.floats(-1, 1), h=st.floats(1.0, 2.5), b=st.floats(0.1, 1.0))
def test_calibration_chain_round_trip(tmp_path_factory, yaw, pitch, roll, x, y, h, b):
    rig = SynthRig(yaw=yaw, pitch=pitch, roll=roll, camera_xy=(x, y), mount_height=h, baseline=b)
    d = tmp_path_factory.mktemp("calib")
    write_calibration(d, rig)
    for kind in ("color", "gray"):
        got = read_rig(d, kind)
        _camera_equal(got.camera, rig.camera(kind), tol=1e-9)
        assert np.allclose(got.camera_in_imu, rig.camera_in_imu(kind), atol=1e-9)
        assert got.yaw == pytest.approx(yaw, abs=1e-9) and got.roll == pytest.approx(roll, abs=1e-9)


# --- excerpts and missing frames ------------------------------------------------------------------------

def test_missing_frames_skipped_or_named(tmp_path):
    drv = write_kitti_drive(tmp_path, 8)
    (drv / "image_02" / "data" / "0000000002.png").unlink()
    (drv / "image_03" / "data" / "0000000004.png").unlink()
    (drv / "oxts" / "data" / "0000000005.txt").unlink()
    seq = load_kitti(drv, DEFAULT_FRAME)
    kept = [0, 1, 3, 6, 7]
    assert seq.meta["kitti_indices"] == kept and len(seq) == 5
    pos, _ = _pose_err(seq.poses, default_poses(8)[kept])
    assert pos < 0.01
    assert np.allclose(seq.timestamps, 0.1 * np.array(kept), atol=2e-6)
    assert np.array_equal(seq[2].left, wall_images(RIG)(3, None)[0])
    with pytest.raises(FormatError, match=r"image_02/data/0000000002\.png: missing \(frame 2, listed on line 3"):
        load_kitti(drv, missing="error")


def test_excerpt_of_a_drive(tmp_path):
    drv = write_kitti_drive(tmp_path, 10, keep=range(3, 6))
    seq = load_kitti(drv)
    assert seq.meta["kitti_indices"] == [3, 4, 5] and seq.meta["num_listed"] == 10
    assert seq.timestamps[0] == 0.0 and seq.timestamps[2] == pytest.approx(0.2, abs=2e-6)
    rec = read_oxts_file(drv / "oxts" / "data" / "0000000003.txt")
    assert seq.meta["geo_frame"]["lat0"] == rec[0] and seq.meta["geo_frame"]["lon0"] == rec[1]
    lines = (drv / "image_02" / "timestamps.txt").read_text().splitlines()
    assert seq.meta["time_origin"] == lines[3]


# --- bad input ------------------------------------------------------------------------------------------

def _replace_line(path: Path, key: str, new: str | None):
    lines = path.read_text().splitlines()
    out = [ln if not ln.startswith(key + ":") else new for ln in lines]
    path.write_text("\n".join(ln for ln in out if ln is not None) + "\n")


def _png(path: Path, w: int, h: int):
    cv2.imwrite(str(path), np.zeros((h, w, 3), np.uint8))


BAD = {
    "oxts short line": (lambda d: (d / "oxts/data/0000000001.txt").write_text(
        " ".join((d / "oxts/data/0000000001.txt").read_text().split()[:29]) + "\n"),
        r"oxts/data/0000000001\.txt line 1: expected 30 numbers .* got 29"),
    "oxts not a number": (lambda d: (d / "oxts/data/0000000002.txt").write_text(
        " ".join(w if i != 5 else "east" for i, w in enumerate((d / "oxts/data/0000000002.txt").read_text().split()))),
        r"0000000002\.txt line 1, field 6 \(yaw\): expected a number, got 'east'"),
    "oxts empty": (lambda d: (d / "oxts/data/0000000000.txt").write_text("\n"),
                   r"0000000000\.txt line 1: expected 30 numbers .* the file is empty"),
    "oxts nan latitude": (lambda d: (d / "oxts/data/0000000000.txt").write_text(
        "nan " + " ".join((d / "oxts/data/0000000000.txt").read_text().split()[1:])),
        r"field 1 \(lat\): expected a finite number"),
    "no P_rect_02": (lambda d: _replace_line(d.parent / "calib_cam_to_cam.txt", "P_rect_02", None),
                     r"calib_cam_to_cam\.txt: no 'P_rect_02:' line \(expected 12 numbers\)"),
    "short P_rect_03": (lambda d: _replace_line(d.parent / "calib_cam_to_cam.txt", "P_rect_03",
                                                "P_rect_03: " + " ".join(["1.0"] * 11)),
                        r"calib_cam_to_cam\.txt line \d+ \(P_rect_03\): expected 12 numbers, got 11"),
    "P_rect_02 not a matrix": (lambda d: _replace_line(d.parent / "calib_cam_to_cam.txt", "P_rect_02",
                                                       "P_rect_02: 1 0 0 0 0 1 0 0 0 0 one 0"),
                               r"line \d+ \(P_rect_02\): expected 12 numbers, got '1 0 0"),
    "R_rect_00 not a rotation": (lambda d: _replace_line(d.parent / "calib_cam_to_cam.txt", "R_rect_00",
                                                         "R_rect_00: 1 0 0 0 2 0 0 0 1"),
                                 r"\(R_rect_00\): expected a rotation matrix"),
    "no velo_to_cam": (lambda d: (d.parent / "calib_velo_to_cam.txt").unlink(),
                       r"calib_velo_to_cam\.txt: calibration file not found"),
    "imu_to_velo without T": (lambda d: _replace_line(d.parent / "calib_imu_to_velo.txt", "T", None),
                              r"calib_imu_to_velo\.txt: no 'T:' line \(expected 3 numbers\)"),
    "left and right of different sizes": (lambda d: _png(d / "image_03/data/0000000003.png", 150, 48),
                                          r"image_03/data/0000000003\.png: right image is 150x48, the left image "
                                          r"0000000003\.png is 160x48"),
    "not the S_rect size": (lambda d: (_png(d / "image_02/data/0000000001.png", 150, 40),
                                       _png(d / "image_03/data/0000000001.png", 150, 40)),
                            r"image_02/data/0000000001\.png: image is 150x40, expected 160x48 \(S_rect_02"),
    "not a png": (lambda d: (d / "image_02/data/0000000002.png").write_bytes(b"GIF89a" + bytes(40)),
                  r"image_02/data/0000000002\.png: not a PNG image"),
    "malformed timestamp": (lambda d: (d / "image_02/timestamps.txt").write_text(
        (d / "image_02/timestamps.txt").read_text().replace("\n", "\n2011-09-26 13:17\n", 1)
        .rsplit("\n", 2)[0] + "\n"),
        r"image_02/timestamps\.txt line 2: expected a timestamp 'YYYY-MM-DD HH:MM:SS\.nnnnnnnnn', got '2011-09-26 13:17'"),
    "impossible date": (lambda d: (d / "image_02/timestamps.txt").write_text(
        "2011-02-30 10:00:00.000000000\n" * 5), r"timestamps\.txt line 1: expected a timestamp"),
    "streams of different lengths": (lambda d: (d / "oxts/timestamps.txt").write_text(
        "".join((d / "oxts/timestamps.txt").read_text().splitlines(True)[:4])),
        r"oxts/timestamps\.txt: 4 timestamps, .*image_02/timestamps\.txt has 5"),
    "empty timestamps": (lambda d: (d / "image_02/timestamps.txt").write_text(""),
                         r"image_02/timestamps\.txt: no timestamps \(an empty drive\)"),
    "no timestamps file": (lambda d: (d / "image_02/timestamps.txt").unlink(),
                           r"image_02/timestamps\.txt: timestamps file not found"),
    "empty drive": (lambda d: [shutil.rmtree(d / s / "data") for s in ("image_02", "image_03", "oxts")],
                    r"no frame has a left image .* 5 frames listed in"),
    "data beyond the timestamps": (lambda d: shutil.copy(d / "oxts/data/0000000000.txt", d / "oxts/data/0000000009.txt"),
                                   r"oxts/data/0000000009\.txt: frame 9 has no line in .*timestamps\.txt \(5 lines\)"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_names_file_and_field(tmp_path, case):
    drv = write_kitti_drive(tmp_path, 5)
    damage, message = BAD[case]
    damage(drv)
    with pytest.raises(FormatError, match=message):
        load_kitti(drv)


def test_bad_options(tmp_path):
    drv = write_kitti_drive(tmp_path, 2)
    for kwargs, message in (({"camera": "infrared"}, "kitti camera: expected one of"),
                            ({"missing": "ignore"}, r"kitti missing: expected one of \['skip', 'error'\]"),
                            ({"frame": (8.4, 49.0)}, "kitti frame: expected a satloc.geoframe.GeoFrame"),
                            ({"imu_height": -1.0}, r"kitti imu_height: expected metres in \(0, 10\)")):
        with pytest.raises(ConfigError, match=message):
            load_kitti(drv, **kwargs)
    with pytest.raises(FormatError, match="KITTI drive directory not found"):
        load_kitti(tmp_path / "nowhere")
    with pytest.raises(FormatError, match=r"image_00/timestamps\.txt: timestamps file not found"):
        load_kitti(drv, camera="gray")  # written without the grey pair


def test_a_folder_that_is_not_a_drive_says_what_a_drive_is(tmp_path):
    """The date folder (which holds the calibration), a folder above it, an empty folder and a drive copied
    without its calibration: each says what was expected, and lists the drive folders it can see."""
    drv = write_kitti_drive(tmp_path / "raw", 2)
    for folder, also in ((drv.parent, [str(drv)]), (drv.parent.parent, [str(drv)]), (tmp_path / "empty", [])):
        folder.mkdir(exist_ok=True)
        with pytest.raises(FormatError) as e:
            load_kitti(folder)
        msg = str(e.value)
        assert msg.startswith(f"{folder.resolve()}: not a KITTI drive folder") and "_drive_<nnnn>_sync" in msg
        assert "oxts/ and image_02/" in msg and "calib_cam_to_cam.txt" in msg and "one level up" in msg
        for d in also:
            assert f"drive folders here: {d}" in msg
        if not also:
            assert "drive folders here" not in msg and "holds nothing" in msg
    copied = tmp_path / "copy" / drv.name
    shutil.copytree(drv, copied)
    with pytest.raises(FormatError, match=r"calib_cam_to_cam\.txt: calibration file not found; expected a KITTI "
                                          r"raw drive folder .* copy calib_cam_to_cam\.txt, calib_imu_to_velo\.txt, "
                                          r"calib_velo_to_cam\.txt beside it"):
        load_kitti(copied)


def test_oxts_fields_are_the_documented_thirty():
    assert len(OXTS_FIELDS) == 30 and OXTS_FIELDS[:6] == ("lat", "lon", "alt", "roll", "pitch", "yaw")
    if REAL.is_dir():
        names = [ln.split(":")[0].strip() for ln in (REAL / "oxts" / "dataformat.txt").read_text().splitlines() if ln.strip()]
        assert len(names) == 30
        # KITTI's own file names the 14th field 'ay' again (a typo for az)
        assert [n for i, n in enumerate(names) if i != 13] == [n for i, n in enumerate(OXTS_FIELDS) if i != 13]


# --- the real excerpt -----------------------------------------------------------------------------------

@needs_real
def test_real_calibration():
    seq = load_kitti(REAL)
    cam, cal = seq.camera, seq.meta["calibration"]
    assert (cam.width, cam.height) == (1242, 375)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (721.5377, 721.5377, 609.5593, 172.854)
    assert cam.baseline == pytest.approx(0.533, abs=5e-4)
    assert cam.mount_height == pytest.approx(1.65, abs=0.03)
    assert abs(math.degrees(cam.pitch)) < 1.0
    assert abs(math.degrees(cal["camera_roll_rad_dropped"])) < 0.5 and abs(math.degrees(cal["camera_yaw_rad"])) < 0.2
    assert seq.meta["kitti_indices"] == list(range(7)) and seq.meta["num_listed"] == 474
    with pytest.raises(FormatError, match=r"image_02/data/0000000007\.png: missing \(frame 7"):
        load_kitti(REAL, missing="error")


@needs_real
def test_real_poses_follow_the_motion():
    seq = load_kitti(REAL)
    p, t = seq.poses, seq.timestamps
    step = np.diff(p[:, :2], axis=0)
    dist = np.linalg.norm(step, axis=1)
    heading = np.arctan2(step[:, 1], step[:, 0])
    mid = np.angle(np.exp(1j * p[:-1, 2]) + np.exp(1j * p[1:, 2]))
    assert np.degrees(np.abs(wrap_angle(heading - mid))).max() < 2.0
    # the steps agree with the great-circle distance between the OXTS fixes (sphere of the devkit's radius)
    ox = np.array([read_oxts_file(REAL / "oxts" / "data" / f"{i:010d}.txt") for i in range(7)])
    lat, lon = np.radians(ox[:, 0]), np.radians(ox[:, 1])
    a = np.sin(np.diff(lat) / 2) ** 2 + np.cos(lat[:-1]) * np.cos(lat[1:]) * np.sin(np.diff(lon) / 2) ** 2
    assert np.abs(dist - 2 * 6378137.0 * np.arcsin(np.sqrt(a))).max() < 0.01
    # about a metre a frame at 10 Hz; a steady speed over the image timestamps
    assert 0.85 < dist.min() and dist.max() < 1.05 and 0.9 < dist.mean() < 1.0
    dt = np.diff(t)
    assert t[0] == 0.0 and np.all((0.1 < dt) & (dt < 0.106))
    assert 8.5 < dist.sum() / (t[-1] - t[0]) < 9.5


@needs_real
def test_real_stereo_depth_against_lidar():
    seq = load_kitti(REAL)
    stereo = StereoDepth(seq.camera, StereoConfig(min_depth_m=3.01))
    assert stereo.num_disparities == 128
    errs = []
    for j, i in enumerate(seq.meta["kitti_indices"]):
        f = seq[j]
        with np.load(REAL / "proj_depth" / "velodyne" / "image_02" / f"{i:010d}.npz", allow_pickle=False) as z:
            lidar = z["velodyne_depth"].astype(np.float32)
        errs.append(depth_error(stereo(f.left, f.right), lidar, max_depth=30.0))
    assert np.median([e["median_rel"] for e in errs]) < 0.05, errs
    assert min(e["valid_frac"] for e in errs) > 0.7, errs


@needs_real
def test_real_lidar_road_lies_on_the_camera_ground_plane():
    """An independent check of the mounting from the calibration chain (height, and pitch with its sign): the
    LiDAR returns on the road ahead, taken into the vehicle frame through the camera model, lie flat at z = 0.
    Measured: near (< 10 m) medians 0.01-0.05 m, far (> 15 m) minus near -0.03..+0.02 m per frame; with the
    pitch set to 0 the far road sinks by 0.04-0.10 m, with its sign flipped by 0.13 m."""
    seq = load_kitti(REAL)
    cam = seq.camera
    near_z, slope = [], []
    for i in seq.meta["kitti_indices"]:
        with np.load(REAL / "proj_depth" / "velodyne" / "image_02" / f"{i:010d}.npz", allow_pickle=False) as z:
            d = z["velodyne_depth"].astype(np.float64)
        v, u = np.nonzero((d > 0) & (d < 25))
        road = (v > 250) & (u > 400) & (u < 850)              # the lower middle of the image: the lane ahead
        pc = cam.backproject(np.stack([u[road], v[road]], 1).astype(np.float64), d[v[road], u[road]])
        pv = (cam.vehicle_from_camera() @ np.c_[pc, np.ones(len(pc))].T).T
        near, far = pv[:, 0] < 10, pv[:, 0] > 15
        assert near.sum() > 1000 and far.sum() > 100
        near_z.append(np.median(pv[near, 2]))
        slope.append(np.median(pv[far, 2]) - near_z[-1])
    assert abs(np.median(near_z)) < 0.06, near_z
    assert abs(np.median(slope)) < 0.03, slope
