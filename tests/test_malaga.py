"""Malaga Urban extract reader (satloc.datasets.malaga) on extracts written by tests/malagafixture.py."""
import math
import pickle

import cv2
import numpy as np
import pytest
from malagafixture import MALAGA_LAT0, MALAGA_LON0, T0, TurnTrack, synthetic_pair, track_lonlat, write_malaga_extract

from satloc import ConfigError, FormatError, Sequence
from satloc.datasets.malaga import GPS_COLUMNS, MalagaConfig, load_malaga, read_gps_log
from satloc.geoframe import GeoFrame


def drive(tmp_path, track=TurnTrack(), gps_dt=1.0, img_dt=0.2, img_lead=0.42, img_tail=0.5, gps_noise=None,
          **kw):
    """An extract of ``track``: GPS fixes every ``gps_dt`` s on the true track (plus ``gps_noise(t, xy)``),
    images every ``img_dt`` s from ``img_lead`` s before the first fix to ``img_tail`` s after the last."""
    gps_t = T0 + np.arange(0.0, track.duration + 1e-9, gps_dt)
    xy = track.at(track.distance(gps_t - T0))[:, :2]
    if gps_noise is not None:
        xy = xy + gps_noise(gps_t - T0, xy)
    img_t = np.arange(gps_t[0] - img_lead, gps_t[-1] + img_tail, img_dt)
    ex = write_malaga_extract(tmp_path, img_t, gps_t, track_lonlat(xy), **kw)
    return ex


def interp_lonlat(ex, t):
    return np.stack([np.interp(t, ex.gps_times, ex.gps_lonlat[:, 0]),
                     np.interp(t, ex.gps_times, ex.gps_lonlat[:, 1])], axis=-1)


def angle_deg(a, b):
    return np.degrees(np.abs((np.asarray(a) - np.asarray(b) + np.pi) % (2 * np.pi) - np.pi))


# --- what it reads --------------------------------------------------------------------------------------

def test_camera_parameters_read_exactly(tmp_path):
    ex = drive(tmp_path, fx=621.18428, fy=620.5, cx=404.0076, cy=309.05989, baseline=0.119471, size=(80, 60))
    seq = load_malaga(ex.root, config={"mount_height": 1.7, "pitch": 0.02})
    c = seq.camera
    assert (c.width, c.height) == (80, 60)
    assert (c.fx, c.fy, c.cx, c.cy, c.baseline) == (621.18428, 620.5, 404.0076, 309.05989, 0.119471)
    assert (ex.camera["fx"], ex.camera["cy"]) == (621.18428, 309.05989)  # the values as written
    assert (c.mount_height, c.pitch) == (1.7, 0.02)


def test_poses_are_the_gps_interpolated_at_image_times(tmp_path):
    ex = drive(tmp_path)
    seq = load_malaga(ex.root)
    assert len(seq) == len(ex.image_times) and seq.meta["time_origin"] == f"{ex.image_times[0]:.6f}"
    assert np.array_equal(seq.timestamps, ex.image_times - ex.image_times[0])  # seconds from the first pair
    frame = GeoFrame.from_dict(seq.meta["geo_frame"])  # default: at the first fix
    assert np.abs(np.array([frame.lon0, frame.lat0]) - ex.gps_lonlat[0]).max() < 1e-12
    assert seq.meta["source"] == "malaga_urban"
    inside = (ex.image_times >= ex.gps_times[0]) & (ex.image_times <= ex.gps_times[-1])
    assert inside.sum() >= 70 and (~inside).sum() >= 4
    want = frame.to_map(interp_lonlat(ex, ex.image_times[inside]))
    got = seq.poses[inside, :2]
    assert np.abs(got - want).max() < 0.01
    # and the same through an explicit frame elsewhere, and through the frames read
    other = GeoFrame(MALAGA_LON0 + 0.01, MALAGA_LAT0 - 0.005)
    seq2 = load_malaga(ex.root, other)
    assert seq2.meta["geo_frame"] == other.to_dict()
    assert np.abs(seq2.poses[inside, :2] - other.to_map(interp_lonlat(ex, ex.image_times[inside]))).max() < 0.01
    i = int(np.flatnonzero(inside)[10])
    f = seq2[i]
    assert f.timestamp == seq2.timestamps[i] and np.allclose(f.pose.as_array(), seq2.poses[i])
    # a plain reader: the sequence (and a view of it) can go to a worker process, as a KITTI drive's can
    again = pickle.loads(pickle.dumps(seq2.view([i])))
    g = again[0]
    assert np.array_equal(g.left, f.left) and np.array_equal(g.right, f.right) and g.pose == f.pose


def test_frames_outside_the_gps_track_have_no_pose(tmp_path):
    ex = drive(tmp_path, img_lead=0.9, img_tail=1.0)
    seq = load_malaga(ex.root)
    outside = (ex.image_times < ex.gps_times[0]) | (ex.image_times > ex.gps_times[-1])
    assert outside[:4].all() and outside[-4:].all()
    assert np.isnan(seq.poses[outside]).all() and np.isfinite(seq.poses[~outside]).all()
    assert seq[0].pose is None and seq[len(seq) - 1].pose is None and seq[10].pose is not None
    assert seq.meta["frames_without_pose"] == int(outside.sum())


@pytest.mark.parametrize("gps_dt", [1.0, 0.2])
def test_yaw_is_the_direction_of_travel_on_a_curve(tmp_path, gps_dt):
    # a 30 m radius turn through 120 degrees between two straights, entered without a transition curve
    track = TurnTrack(straight1=25.0, radius=30.0, angle=math.radians(120), straight2=25.0, speed=7.0)
    ex = drive(tmp_path, track, gps_dt=gps_dt, img_dt=0.1)
    seq = load_malaga(ex.root)
    ok = np.isfinite(seq.poses[:, 2])
    truth = track.at(track.distance(ex.image_times[ok] - T0))[:, 2]
    err = angle_deg(seq.poses[ok, 2], truth)
    assert ok.sum() > 150 and err.max() < 1.0, err.max()
    on_arc = (truth > 0.2) & (truth < math.radians(100))
    assert on_arc.sum() > 20  # the curve is sampled, not only the straights


def test_standing_still_keeps_the_heading_of_the_track(tmp_path):
    # 12 s stopped 20 m along the eastward straight, the GPS fixes scattered by up to 0.3 m meanwhile
    track = TurnTrack(straight1=40.0, radius=20.0, angle=math.pi / 2, straight2=20.0, speed=6.0,
                      stop_at_m=20.0, stop_s=12.0)
    rng = np.random.default_rng(3)
    t_stop = 20.0 / 6.0

    def jitter(t, xy):
        stopped = (t > t_stop + 0.5) & (t < t_stop + 12.0 - 0.5)
        return np.where(stopped[:, None], rng.uniform(-0.3, 0.3, xy.shape), 0.0)

    ex = drive(tmp_path, track, gps_noise=jitter, img_dt=0.25)
    seq = load_malaga(ex.root)
    rel = ex.image_times - T0
    stopped = (rel > t_stop + 1.0) & (rel < t_stop + 11.0)
    assert stopped.sum() >= 35
    yaw = seq.poses[stopped, 2]
    assert np.isfinite(yaw).all() and angle_deg(yaw, 0.0).max() < 4.0
    assert np.abs(seq.poses[stopped, :2] - [20.0, 0.0]).max() < 0.45
    # without dropping the jitter the heading would follow it
    raw = load_malaga(ex.root, config={"min_step_m": 1e-3})
    assert angle_deg(raw.poses[stopped, 2], 0.0).max() > 20.0


def test_gps_rows_without_fix_are_ignored_and_long_gaps_get_no_pose(tmp_path):
    track = TurnTrack(straight1=80.0, radius=20.0, angle=0.5, straight2=10.0, speed=6.0)
    n = int(track.duration) + 1
    fix = np.ones(n, int)
    fix[3] = 0  # one lost fix: a 2 s gap, bridged
    fix[8:15] = 0  # 8 s without fix: no pose in between
    gps_t = T0 + np.arange(n, dtype=float)
    lonlat = track_lonlat(track.at(track.distance(gps_t - T0))[:, :2])
    lonlat[fix == 0] = [0.0, 0.0]  # what a receiver without signal may report
    ex = write_malaga_extract(tmp_path, T0 + np.arange(0.0, n - 1, 0.5), gps_t, lonlat, gps_fix=fix)
    seq = load_malaga(ex.root)
    rel = ex.image_times - T0
    gap = (rel > 7.0) & (rel < 15.0)
    assert np.isnan(seq.poses[gap]).all() and np.isfinite(seq.poses[~gap]).all()
    near = (rel > 2.0) & (rel < 4.0)
    truth = track.at(track.distance(rel[near]))[:, :2]
    assert np.abs(seq.poses[near, :2] - truth).max() < 0.01  # straight: linear interpolation is exact
    assert seq.meta["gps_fixes_used"] == int(fix.sum())


def test_images_are_read_as_rgb_pairs_and_unpaired_ones_skipped(tmp_path):
    ex = drive(tmp_path, drop_right=[5], drop_left=[9])
    seq = load_malaga(ex.root)
    assert len(seq) == len(ex.image_times)  # two frames fewer than written
    assert sorted(seq.meta["unpaired_skipped"]) == sorted(
        [n for n in (p.name for p in ex.image_dir.iterdir())
         if n.endswith(".jpg") and n not in ex.left_names + ex.right_names])
    assert len(seq.meta["unpaired_skipped"]) == 2
    f = seq[7]
    left, right = synthetic_pair(8, 80, 60)  # frame 7 of the sequence is the 8th written (5 dropped)
    assert f.left.shape == (60, 80, 3) and f.left.dtype == np.uint8
    assert np.abs(f.left.astype(int) - left).mean() < 4 and np.abs(f.right.astype(int) - right).mean() < 4
    assert f.left.mean() > f.right.mean() + 50  # not swapped


def test_folder_names_and_resolution_choice(tmp_path):
    ex = drive(tmp_path / "a", a0_in_folder_name=True)  # the README's spelling of the folder
    assert ex.image_dir.name.endswith("_rectified_a=0_80x60_Images")
    assert load_malaga(ex.root).camera.width == 80
    # two resolutions: the larger by default, or the one asked for
    ex2 = drive(tmp_path / "b")
    big = drive(tmp_path / "c", size=(100, 75), fx=77.64804, cx=50.50095, cy=38.63249)
    big.image_dir.rename(ex2.root / big.image_dir.name)
    big.camera_file.rename(ex2.root / big.camera_file.name)
    assert load_malaga(ex2.root).camera.width == 100
    assert load_malaga(ex2.root, config=MalagaConfig(resolution="80x60")).camera.width == 80
    with pytest.raises(ConfigError, match=r"resolution: '1024x768' not in .*'100x75', '80x60'"):
        load_malaga(ex2.root, config={"resolution": "1024x768"})


def test_a_loaded_extract_saves_as_a_satloc_sequence(tmp_path):
    ex = drive(tmp_path / "x")
    seq = load_malaga(ex.root).head(4)
    seq.save(tmp_path / "saved")
    back = Sequence.load(tmp_path / "saved")
    assert back.meta["geo_frame"] == seq.meta["geo_frame"] and back.camera == seq.camera
    assert np.array_equal(np.isnan(back.poses), np.isnan(seq.poses))
    assert np.allclose(back.poses[np.isfinite(back.poses)], seq.poses[np.isfinite(seq.poses)])


# --- bad input ------------------------------------------------------------------------------------------

def _edit_data_line(path, k, fn):
    lines = path.read_text().splitlines()
    data = [i for i, s in enumerate(lines) if s.strip() and not s.startswith("%")]
    lines[data[k]] = fn(lines[data[k]])
    path.write_text("\n".join(lines) + "\n")
    return data[k] + 1  # 1-based line number


def test_gps_log_with_wrong_column_count(tmp_path):
    ex = drive(tmp_path)
    n = _edit_data_line(ex.gps_file, 4, lambda s: " ".join(s.split()[:-1]))
    with pytest.raises(FormatError, match=rf"_GPS.txt line {n}: expected 25 whitespace-separated columns "
                                          r"\(Time, Lat, Lon, .*SAT Time\), got 24"):
        load_malaga(ex.root)
    assert len(GPS_COLUMNS) == 25


def test_gps_log_with_a_field_that_is_not_a_number(tmp_path):
    ex = drive(tmp_path)
    n = _edit_data_line(ex.gps_file, 2, lambda s: " ".join(p if k != 3 else "12,5m" for k, p in
                                                           enumerate(s.split())))
    with pytest.raises(FormatError, match=rf"{ex.gps_file.name} line {n}: column 4 \(Alt\) is not a number: "
                                          r"'12,5m'"):
        load_malaga(ex.root)


def test_empty_gps_log_and_log_without_fix(tmp_path):
    ex = drive(tmp_path)
    header = ex.gps_file.read_text().splitlines()[0]
    ex.gps_file.write_text(header + "\n\n")
    with pytest.raises(FormatError, match=r"_all-sensors_GPS.txt: empty GPS log, expected rows of 25 columns"):
        load_malaga(ex.root)
    ex.gps_file.write_text("")
    with pytest.raises(FormatError, match="empty GPS log"):
        read_gps_log(ex.gps_file)
    ex2 = drive(tmp_path / "b", gps_fix=np.zeros(16, int))
    with pytest.raises(FormatError, match=r"no GPS fix \(every row has fix = 0"):
        load_malaga(ex2.root)


def test_gps_log_in_degrees_or_out_of_order(tmp_path):
    ex = drive(tmp_path)
    n = _edit_data_line(ex.gps_file, 3, lambda s: " ".join(
        p if k not in (1, 2) else f"{math.degrees(float(p)):.10f}" for k, p in enumerate(s.split())))
    with pytest.raises(FormatError, match=rf"line {n}: Lat 36\.7.* are not WGS84 radians"):
        load_malaga(ex.root)
    ex2 = drive(tmp_path / "b")
    n = _edit_data_line(ex2.gps_file, 6, lambda s: f"{T0 - 5:14.4f}" + s[14:])
    with pytest.raises(FormatError, match=rf"line {n}: Time .* is earlier than the previous fix"):
        load_malaga(ex2.root)


def test_camera_file_missing_a_field(tmp_path):
    ex = drive(tmp_path)
    text = ex.camera_file.read_text()
    first_fy = text.index("fy=")
    end = text.index("\n", first_fy)
    ex.camera_file.write_text(text[:first_fy] + text[end + 1:])
    with pytest.raises(FormatError, match=r"camera_params_rectified_a=0_80x60.txt: \[CAMERA_LEFT\] has no 'fy'"):
        load_malaga(ex.root)
    ex.camera_file.write_text(text.replace("[CAMERA_LEFT2RIGHT_POSE]", "[SOMETHING_ELSE]"))
    with pytest.raises(FormatError, match=r"missing section \[CAMERA_LEFT2RIGHT_POSE\]"):
        load_malaga(ex.root)
    ex.camera_file.write_text(text.replace("cx=", "cx=abc", 1))
    with pytest.raises(FormatError, match=r"80x60.txt line 7: \[CAMERA_LEFT\] cx = 'abc.*' is not a number"):
        load_malaga(ex.root)


def test_left_and_right_images_of_different_sizes(tmp_path):
    def images(i):
        left, right = synthetic_pair(i, 80, 60)
        return left, (right[:50, :70] if i in (0, 3) else right)

    ex = drive(tmp_path / "a", images=images)
    with pytest.raises(FormatError, match=r"_left.jpg is 80x60 but .*_right.jpg is 70x50"):
        load_malaga(ex.root)

    ex = drive(tmp_path / "b", images=lambda i: images(i) if i == 3 else synthetic_pair(i, 80, 60))
    bad = rf"img_CAMERA1_{ex.image_times[3]:.6f}_left.jpg is 80x60 but .*_right.jpg is 70x50; expected a " \
          r"stereo pair of one size"
    with pytest.raises(FormatError, match=bad):  # every pair is checked at load, from the JPEG headers
        load_malaga(ex.root)
    # an image that changes after loading is caught when it is read
    ex = drive(tmp_path / "c")
    seq = load_malaga(ex.root)
    assert seq[3].right.shape == (60, 80, 3)
    right3 = ex.image_dir / ex.right_names[3]
    assert cv2.imwrite(str(right3), images(3)[1])
    with pytest.raises(FormatError, match=r"_left.jpg is 80x60 but .*_right.jpg is 70x50; expected a stereo "
                                          r"pair of one size"):
        seq[3]


def test_no_images_and_missing_files(tmp_path):
    ex = drive(tmp_path)
    for p in ex.image_dir.iterdir():
        p.unlink()
    with pytest.raises(FormatError, match=r"_rectified_80x60_Images: no stereo pairs"):
        load_malaga(ex.root)
    ex = drive(tmp_path / "b", drop_right=list(range(200)))
    with pytest.raises(FormatError, match=r"no stereo pairs .*unpaired: \['img_CAMERA1_"):
        load_malaga(ex.root)
    ex = drive(tmp_path / "c")
    ex.gps_file.unlink()
    with pytest.raises(FormatError, match=r"no GPS log \(malaga-urban-dataset-extract-07_all-sensors_GPS.txt\)"):
        load_malaga(ex.root)
    ex = drive(tmp_path / "d")
    ex.camera_file.unlink()
    with pytest.raises(FormatError, match=r"no camera file camera_params_rectified_a=0_80x60.txt"):
        load_malaga(ex.root)
    with pytest.raises(FormatError, match="Malaga extract directory not found"):
        load_malaga(tmp_path / "nowhere")


def test_image_size_must_match_the_camera_file(tmp_path):
    ex = drive(tmp_path, images=lambda i: synthetic_pair(i, 64, 48))
    with pytest.raises(FormatError, match=r"_left.jpg: image is 64x48, expected 80x60"):
        load_malaga(ex.root)


def test_bad_configuration(tmp_path):
    ex = drive(tmp_path)
    with pytest.raises(ConfigError, match=r"malaga config: unknown key\(s\) \['height'\]"):
        load_malaga(ex.root, config={"height": 1.5})
    with pytest.raises(ConfigError, match=r"heading_window_m: expected a positive number"):
        load_malaga(ex.root, config={"heading_window_m": 0.0})
    with pytest.raises(ConfigError, match=r"resolution: expected 'WIDTHxHEIGHT'"):
        MalagaConfig(resolution="800 by 600")


def test_camera_file_details(tmp_path):
    from malagafixture import write_camera_file

    from satloc.datasets.malaga import read_camera_params

    p = tmp_path / "camera_params_rectified_a=0_800x600.txt"
    write_camera_file(p, 800, 600, 0.7764804, 1.0353071, 0.5050095, 0.5150998, 0.119471)
    c = read_camera_params(p)  # values below 2 are fractions of the image size (MRPT's TCamera)
    # written with 5 decimals, as MRPT prints them: 0.77648, 1.03531, 0.50501, 0.51510
    assert (c.fx, c.fy, c.cx, c.cy) == pytest.approx((0.77648 * 800, 1.03531 * 600, 0.50501 * 800, 0.5151 * 600))
    text = p.read_text()
    right = text.index("[CAMERA_RIGHT]")
    p.write_text(text[:right] + text[right:].replace("cx=0.50501", "cx=0.51001", 1))
    with pytest.raises(FormatError, match=r"\[CAMERA_RIGHT\] cx = 408.008 differs from \[CAMERA_LEFT\] cx = "
                                          r"404.008; a rectified pair needs one camera"):
        read_camera_params(p)
    p.write_text(text.replace("pose_quaternion=[0.119471", "pose_quaternion=[-0.119471"))
    with pytest.raises(FormatError, match=r"line 28: \[CAMERA_LEFT2RIGHT_POSE\] pose_quaternion: expected the "
                                          r"right camera at x > 0"):
        read_camera_params(p)
    p.write_text(text.replace("resolution=[800 600]", "resolution=[800]", 1))
    with pytest.raises(FormatError, match=r"line 6: \[CAMERA_LEFT\] resolution: expected 2 numbers"):
        read_camera_params(p)


def test_jpeg_size_from_the_header(tmp_path):
    from satloc.datasets.malaga import jpeg_size

    img = np.zeros((37, 53, 3), np.uint8)
    for name, flags in (("base.jpg", []), ("prog.jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])):
        assert cv2.imwrite(str(tmp_path / name), img, flags)
        assert jpeg_size(tmp_path / name) == (53, 37)
    (tmp_path / "x.jpg").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(20))
    with pytest.raises(FormatError, match=r"x.jpg: not a JPEG image"):
        jpeg_size(tmp_path / "x.jpg")
    (tmp_path / "cut.jpg").write_bytes((tmp_path / "base.jpg").read_bytes()[:10])
    with pytest.raises(FormatError, match=r"cut.jpg: not a JPEG image \(no frame header\)"):
        jpeg_size(tmp_path / "cut.jpg")
