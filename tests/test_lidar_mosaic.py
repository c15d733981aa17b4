"""satloc.datasets.lidar_mosaic on synthetic KITTI drives (tests/kittifixture.py): images of a textured ground
plane, Velodyne scans (``velodyne_points/data/*.bin``) of that ground and of a box standing on it, written
through the fixture's own calibration chain (IMU -> Velodyne from ``calib_imu_to_velo.txt``), so the reader's
Velodyne -> camera chain is checked against it, not against itself."""
import math
from pathlib import Path

import numpy as np
import pytest
from kittifixture import DEFAULT_FRAME, SynthRig, write_kitti_drive

from satloc import ConfigError, Pose2
from satloc.datasets import load_kitti
from satloc.datasets.kitti import calib_values, read_calib_file, velo_to_camera
from satloc.datasets.lidar_mosaic import (
    ensure_lidar_mosaic,
    lidar_mosaic,
    read_velodyne,
    record_path,
)
from satloc.errors import FormatError
from satloc.geodata.georef import load_map
from satloc.geoframe import GeoFrame

RIG = SynthRig(width=320, height=96, fx=200.0, fy=200.0, cx=159.5, cy=47.5, pitch=0.06, roll=0.0)
N = 4
POSES = np.array([[3.0 + 2.0 * i, -2.0 + 0.5 * i, 0.25] for i in range(N)])   # in DEFAULT_FRAME
BOX = (14.0, 4.0, 2.0, 1.5)   # a box on the ground: centre x, y, half side (m), height


def texture(xy: np.ndarray) -> np.ndarray:
    """The ground's colour at map points (..., 2) of DEFAULT_FRAME: smooth, and unlike itself when shifted."""
    x, y = xy[..., 0], xy[..., 1]
    r = np.where((np.floor(x / 2) + np.floor(y / 2)) % 2 == 0, 60.0, 200.0)
    return np.stack([r, 128 + 100 * np.sin(2 * np.pi * x / 23), 128 + 100 * np.sin(2 * np.pi * y / 17)], -1)


def ground_images(i: int, pose) -> tuple[np.ndarray, np.ndarray]:
    """The ground seen from ``pose``: each pixel's ray meets z = 0 (the sky above the horizon is grey)."""
    cam = RIG.camera()
    out = []
    for side in ("left", "right"):
        m = cam.map_from_camera(Pose2(*pose), side)
        vv, uu = np.mgrid[0:cam.height, 0:cam.width]
        rays = cam.backproject(np.stack([uu, vv], -1).astype(np.float64), np.ones(uu.shape)) @ m[:3, :3].T
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -m[2, 3] / rays[..., 2]
        g = m[:3, 3] + rays * t[..., None]
        img = np.where((t > 0)[..., None], texture(g[..., :2]), 150.0)
        out.append(np.clip(img, 0, 255).astype(np.uint8))
    return out[0], out[1]


def world_points(pose: np.ndarray) -> np.ndarray:
    """(N, 3) points in DEFAULT_FRAME of the ground within 30 m of ``pose`` and of BOX's sides and top."""
    gx, gy = np.meshgrid(np.arange(-30.0, 30.0, 0.25), np.arange(-30.0, 30.0, 0.25))
    pts = [np.stack([pose[0] + gx.ravel(), pose[1] + gy.ravel(), np.zeros(gx.size)], 1)]
    cx, cy, h, top = BOX
    s = np.arange(-h, h, 0.1)
    zz = np.arange(0.1, top, 0.1)
    for a, b in ((s, np.full_like(s, -h)), (s, np.full_like(s, h)), (np.full_like(s, -h), s), (np.full_like(s, h), s)):
        px, pz = np.meshgrid(cx + a, zz)
        py, _ = np.meshgrid(cy + b, zz)
        pts.append(np.stack([px.ravel(), py.ravel(), pz.ravel()], 1))
    tx, ty = np.meshgrid(cx + s, cy + s)
    pts.append(np.stack([tx.ravel(), ty.ravel(), np.full(tx.size, top)], 1))   # its top
    world = np.concatenate(pts)
    return world[np.hypot(world[:, 0] - pose[0], world[:, 1] - pose[1]) < 30.0]


def scan(world: np.ndarray, pose: np.ndarray, velo_from_imu: np.ndarray) -> np.ndarray:
    """(N, 4) float32 Velodyne scan (x y z reflectance) of ``world`` points from the vehicle at ``pose``."""
    # the IMU: level, RIG.imu_height above the ground, placed as write_kitti_drive places it for the OXTS
    imu_yaw = pose[2] - RIG.yaw
    c, s_ = math.cos(imu_yaw), math.sin(imu_yaw)
    cam_xy = RIG.camera_in_imu()[:2]
    imu = np.array([pose[0] - (c * cam_xy[0] - s_ * cam_xy[1]), pose[1] - (s_ * cam_xy[0] + c * cam_xy[1]),
                    RIG.imu_height])
    rot = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
    in_imu = (world - imu) @ rot                                     # rot.T @ (p - imu), row-wise
    velo = in_imu @ velo_from_imu[:3, :3].T + velo_from_imu[:3, 3]
    return np.c_[velo, np.ones(len(velo))].astype(np.float32)


def write_drive(root: Path) -> Path:
    drive = write_kitti_drive(root, N, rig=RIG, poses=POSES, images=ground_images)
    calib = drive.parent / "calib_imu_to_velo.txt"
    c = read_calib_file(calib)
    velo_from_imu = np.eye(4)
    velo_from_imu[:3, :3] = calib_values(c, calib, "R", 9).reshape(3, 3)
    velo_from_imu[:3, 3] = calib_values(c, calib, "T", 3)
    (drive / "velodyne_points" / "data").mkdir(parents=True)
    for i in range(N):
        scan(world_points(POSES[i]), POSES[i], velo_from_imu).tofile(drive / "velodyne_points" / "data" / f"{i:010d}.bin")
    return drive


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    return write_drive(tmp_path_factory.mktemp("lidar"))


def test_velo_to_camera_follows_the_calibration_chain(drive):
    """Scans written through IMU -> Velodyne come back to the map through velo_to_camera (Velodyne -> rectified
    left camera) and the camera's pose: the chain closes to float32 precision."""
    seq = load_kitti(drive)
    cam, frame = seq.camera, GeoFrame.from_dict(seq.meta["geo_frame"])
    m = cam.map_from_camera(Pose2(*seq.poses[2])) @ velo_to_camera(drive.parent)
    pts = read_velodyne(drive / "velodyne_points" / "data" / "0000000002.bin")[:, :3].astype(np.float64)
    back = pts @ m[:3, :3].T + m[:3, 3]
    back[:, :2] = DEFAULT_FRAME.to_map(frame.to_lonlat(back[:, :2]))
    assert np.abs(back - world_points(POSES[2])).max() < 1e-3


@pytest.mark.filterwarnings("ignore:.*is mostly dark")   # black beyond the road, by construction
def test_velodyne_scans_place_the_ground_and_leave_out_what_stands_on_it(drive, tmp_path):
    path = tmp_path / "m.tif"
    covered = lidar_mosaic(drive, path, mpp=0.2, margin_m=30.0, max_depth_m=20.0)
    assert 0.05 < covered < 0.8
    # read back in the fixture's frame (the mosaic is in the drive's own, at its first frame)
    region = (-10.0, -15.0, 35.0, 20.0)
    m = load_map(path, 0.2, frame=DEFAULT_FRAME, region=region)
    vv, uu = np.mgrid[0:m.shape[0], 0:m.shape[1]]
    xy = m.pixel_to_world(np.stack([uu, vv], -1).astype(np.float64))
    img = m.image.astype(np.float64)
    seen = img.sum(-1) > 0
    assert seen.mean() > 0.1
    diff = np.abs(img - texture(xy))[seen]
    # measured: median 1.1 / 1.3 grey levels in the smooth channels (a 1 m shift would give about 20)
    assert np.median(diff[:, 1]) < 5 and np.median(diff[:, 2]) < 5
    # the checker channel, within 10 m of a pose and 0.3 m of its edges: measured 95 % right (farther, a
    # pixel row of these small images spans a metre of ground)
    x, y = xy[..., 0], xy[..., 1]
    near = np.min([np.hypot(x - p[0], y - p[1]) for p in POSES], axis=0) < 10.0
    clear = np.minimum(np.abs(x / 2 - np.round(x / 2)), np.abs(y / 2 - np.round(y / 2))) * 2 > 0.3
    sharp = (seen & near & clear)
    assert sharp.sum() > 1000 and np.mean(np.abs(img - texture(xy))[sharp][:, 0] < 30) > 0.9
    # the box's footprint is left out (pixels near LiDAR points more than 0.3 m above the ground) but for its
    # edge nearest a camera (measured: up to 0.7 m in, where the rays pass the box's side below 0.3 m), and
    # the ground around it is not
    cx, cy, h, _ = BOX
    inside = (np.abs(xy[..., 0] - cx) < h - 1.0) & (np.abs(xy[..., 1] - cy) < h - 1.0)
    around = (np.abs(xy[..., 0] - cx) < h + 2.0) & (np.abs(xy[..., 1] - cy) < h + 2.0) & ~inside
    assert inside.sum() > 50 and not seen[inside].any() and seen[around].mean() > 0.3


def test_reused_while_the_drive_is_unchanged(drive, tmp_path):
    path = tmp_path / "out" / "lidar_mosaic.tif"
    first = ensure_lidar_mosaic(drive, path, mpp=0.5, margin_m=10.0)
    assert not first["reused"] and first["lidar"] == ["velodyne_points/data"] and first["frames_used"] == [0, 1, 2, 3]
    stamp = path.stat().st_mtime_ns
    again = ensure_lidar_mosaic(drive, path, mpp=0.5, margin_m=10.0)
    assert again["reused"] and path.stat().st_mtime_ns == stamp
    assert again["covered_fraction"] == first["covered_fraction"]
    assert not ensure_lidar_mosaic(drive, path, mpp=0.5, margin_m=12.0)["reused"]       # other settings
    record_path(path).write_text("{damaged")
    assert not ensure_lidar_mosaic(drive, path, mpp=0.5, margin_m=12.0)["reused"]       # a damaged record
    assert ensure_lidar_mosaic(drive, path, mpp=0.5, margin_m=12.0)["reused"]
    assert not list(path.parent.glob(".*tmp*"))                                       # written atomically


def test_a_drive_without_lidar_or_with_a_damaged_scan(tmp_path):
    bare = write_kitti_drive(tmp_path / "bare", 2, rig=RIG)
    with pytest.raises(ConfigError, match=rf"{bare}: no LiDAR for any of its 2 frames; a LiDAR mosaic needs "
                                          r"velodyne_points/data/<index>.bin .* or proj_depth/velodyne/image_02/"):
        lidar_mosaic(bare, tmp_path / "m.tif")
    assert not (tmp_path / "m.tif").exists()
    (bare / "velodyne_points" / "data").mkdir(parents=True)
    bad = bare / "velodyne_points" / "data" / "0000000001.bin"
    bad.write_bytes(b"\0" * 20)
    with pytest.raises(FormatError, match=rf"{bad}: 20 bytes, not a whole number of 16-byte points"):
        lidar_mosaic(bare, tmp_path / "m.tif")
    with pytest.raises(ConfigError, match="lidar mosaic mpp: expected a positive number"):
        lidar_mosaic(bare, tmp_path / "m.tif", mpp=0.0)


@pytest.mark.filterwarnings("ignore:.*is mostly dark")
def test_projected_depth_maps_read_like_the_scans(drive, tmp_path):
    """proj_depth/velodyne/image_02/*.npz (z-depth maps in image_02, as in the shared KITTI excerpt) made from
    the same scans give the same mosaic; where a frame has both, the scan is read."""
    import shutil

    date = shutil.copytree(drive.parent, tmp_path / drive.parent.name)
    copy = date / drive.name
    cam, t = load_kitti(copy).camera, velo_to_camera(date)
    (copy / "proj_depth" / "velodyne" / "image_02").mkdir(parents=True)
    for i in range(N):
        pts = read_velodyne(copy / "velodyne_points" / "data" / f"{i:010d}.bin")[:, :3].astype(np.float64)
        pc = pts @ t[:3, :3].T + t[:3, 3]
        uv, z = cam.project(pc[pc[:, 2] > 1.0])
        col, row = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
        ok = (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
        depth = np.zeros((cam.height, cam.width), np.float32)
        order = np.argsort(-z[ok])                         # the nearest point of a pixel written last
        depth[row[ok][order], col[ok][order]] = z[ok][order]
        np.savez_compressed(copy / "proj_depth" / "velodyne" / "image_02" / f"{i:010d}.npz", velodyne_depth=depth)
    both = ensure_lidar_mosaic(copy, tmp_path / "both.tif", mpp=0.5, margin_m=10.0)
    assert both["lidar"] == ["velodyne_points/data"]
    shutil.rmtree(copy / "velodyne_points")
    npz = ensure_lidar_mosaic(copy, tmp_path / "npz.tif", mpp=0.5, margin_m=10.0)
    assert npz["lidar"] == ["proj_depth/velodyne/image_02"] and npz["frames_used"] == [0, 1, 2, 3]
    a, b = (load_map(tmp_path / f"{n}.tif").image.astype(int) for n in ("both", "npz"))
    # measured: covered fractions 0.243 and 0.240; in the smooth channels the colours differ by 1 grey level at
    # the median, 3 at the 90th percentile (a depth map keeps the pixel, not where in it the point fell: the
    # ground height, and so the far ground, moves by centimetres); the checker's edges differ more
    assert abs(npz["covered_fraction"] - both["covered_fraction"]) < 0.01
    seen = (a.sum(-1) > 0) & (b.sum(-1) > 0)
    assert seen.mean() > 0.2 and np.percentile(np.abs(a - b)[seen][:, 1:], 90) < 6
