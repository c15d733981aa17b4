from pathlib import Path

import cv2
import numpy as np
import pytest

from satloc import ConfigError, StereoCamera
from satloc.stereo import StereoConfig, StereoDepth, depth_error

KITTI = (Path(__file__).resolve().parents[2] / "shared" / "realdata" / "kitti_raw_2011_09_26_drive_0023_7frames"
         / "2011_09_26" / "2011_09_26_drive_0023_sync")


def test_sgbm_depth_on_rendered_ground():
    import gymnasium as gym

    import satloc_env  # noqa: F401

    env = gym.make("satloc/SatLoc-v0", scene="city", depth=True, localizer=None)
    obs, _ = env.reset(seed=0)
    stereo = StereoDepth(env.unwrapped.camera)
    err = depth_error(stereo(obs["left"], obs["right"]), obs["depth"], max_depth=30.0)
    env.close()
    assert err["median_rel"] < 0.03 and err["valid_frac"] > 0.6, err


@pytest.mark.skipif(not KITTI.is_dir(), reason="shared KITTI fixture absent")
def test_sgbm_depth_on_real_kitti_against_lidar():
    # rectified colour pair of 2011_09_26: P_rect_02 / P_rect_03 give a 0.533 m baseline
    cam = StereoCamera(1242, 375, 721.5377, 721.5377, 609.5593, 172.854, 0.5327)
    stereo = StereoDepth(cam)
    errs = []
    for i in (0, 3, 6):
        name = f"{i:010d}"
        left = cv2.cvtColor(cv2.imread(str(KITTI / "image_02" / "data" / f"{name}.png")), cv2.COLOR_BGR2RGB)
        right = cv2.cvtColor(cv2.imread(str(KITTI / "image_03" / "data" / f"{name}.png")), cv2.COLOR_BGR2RGB)
        with np.load(KITTI / "proj_depth" / "velodyne" / "image_02" / f"{name}.npz", allow_pickle=False) as z:
            lidar = z["velodyne_depth"].astype(np.float32)
        errs.append(depth_error(stereo(left, right), lidar, max_depth=30.0)["median_rel"])
    assert np.median(errs) < 0.05, errs


def test_stereo_input_checks():
    cam = StereoCamera.kitti_half()
    s = StereoDepth(cam)
    img = np.zeros((100, 100, 3), np.uint8)
    with pytest.raises(ConfigError, match="left image is 100x100, the camera is 620x188"):
        s(img, img)
    with pytest.raises(ConfigError, match="block_size"):
        StereoConfig(block_size=4)
