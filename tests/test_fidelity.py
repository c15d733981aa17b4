"""satloc experiment fidelity: the image statistics measured one way for renders and real frames, and the
protocol rows beside the paper's real figures."""
import json

import cv2
import numpy as np
import pytest

from satloc.errors import ConfigError
from satloc_env.experiments.fidelity import PAPER, fidelity, image_stats, orb_keypoints, spectral_slope


def test_detail_statistics_order_smooth_and_detailed_frames():
    rng = np.random.default_rng(0)
    smooth = cv2.GaussianBlur(rng.integers(0, 255, (188, 620), dtype=np.uint8), (0, 0), 8)
    detailed = rng.integers(0, 255, (188, 620), dtype=np.uint8)
    squares = (np.indices((188, 620)).sum(0) // 6 % 2 * 255).astype(np.uint8)
    assert orb_keypoints(smooth) < 50 < orb_keypoints(squares)
    assert spectral_slope(smooth) < spectral_slope(detailed) - 2      # a smooth frame's spectrum falls off faster
    s = image_stats([detailed, cv2.cvtColor(detailed, cv2.COLOR_GRAY2RGB), cv2.resize(detailed, (1242, 375))])
    assert s["frames"] == 3 and s["orb_keypoints"] > 1000
    with pytest.raises(ConfigError, match="no frames"):
        image_stats([])


def test_fidelity_report_on_a_tiny_section(tmp_path):
    real = tmp_path / "real" / "image_02" / "data"
    real.mkdir(parents=True)
    frame = (np.random.default_rng(1).integers(0, 255, (375, 1242, 3))).astype(np.uint8)
    cv2.imwrite(str(real / "0000000000.png"), frame)
    cfg = {"aliasing": [0.0], "protocols": ["kitti-city"], "image_scenes": ["city"], "frames": 2,
           "reference_images": str(tmp_path / "real"),
           "experiment": {"database_frames": 24, "query_frames": 3, "query_spacing_m": 6.0, "features": "rgb",
                          "modes": ["go"], "compare": {"baselines": []}, "pictures": False,
                          "kitti_city_length_m": 20.0}}
    rep = fidelity(tmp_path / "f", cfg, progress=False, log=lambda m: None)
    assert [i["source"].split(":")[0] for i in rep["images"]] == ["city (aliasing 0)", "real frames"]
    assert rep["images"][0]["frames"] == 2 and rep["images"][1]["frames"] == 1
    go = next(r for r in rep["rows"] if r["method"] == "Ours-GO")
    assert go["protocol"] == "kitti-city" and go["paper_m"] == PAPER["kitti-city"]["Ours-GO"] == 0.81
    assert go["ratio"] == round(go["mean_m"] / 0.81, 3) and go["ratio_low"] <= go["ratio"] <= go["ratio_high"]
    prior = next(r for r in rep["rows"] if r["method"] == "Prior alone")
    assert prior["paper_m"] is None and prior["ratio"] is None
    assert json.loads((tmp_path / "f" / "fidelity.json").read_text())["format"] == "fidelity"
    md = (tmp_path / "f" / "fidelity.md").read_text()
    assert "ORB keypoints" in md and "**kitti-city** on `city`, aliasing 0" in md
    with pytest.raises(ConfigError, match="unknown \\['revisit'\\]"):
        fidelity(tmp_path / "g", {"protocols": ["revisit"]}, progress=False, log=lambda m: None)


def test_fidelity_images_at_each_variety(tmp_path):
    import yaml

    scene = {"name": "tiny", "seed": 3,
             "generator": {"type": "grid", "style": "city", "blocks": [2, 2], "pitch_m": 60, "margin_m": 10},
             "meters_per_pixel": 0.2, "ground_mpp": 0.2,
             "routes": {"main": {"waypoints": [[10, 10], [130, 10], [130, 130], [10, 130]], "closed": True}}}
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(scene))
    cfg = {"aliasing": [0.0], "protocols": [], "image_scenes": [str(path)], "frames": 3, "variety": [0.0, 1.0],
           "reference_images": str(tmp_path / "none")}
    rep = fidelity(tmp_path / "f", cfg, progress=False, log=lambda m: None)
    assert [i["source"] for i in rep["images"]] == [f"{path} (aliasing 0, variety 0)",
                                                    f"{path} (aliasing 0, variety 1)"]
    copy = yaml.safe_load((tmp_path / "f" / "scenes" / "tiny_variety1.yaml").read_text())
    assert copy["generator"]["variety"] == 1.0 and copy["routes"] == scene["routes"]
    pic = cv2.imread(str(tmp_path / "f" / "pictures_tiny.jpg"))
    assert pic.shape == (2 * (188 + 4), 3 * 620, 3)        # a row per variety: the same three places
    with pytest.raises(ConfigError, match="variety: expected values in"):
        fidelity(tmp_path / "g", dict(cfg, variety=[2.0]), progress=False, log=lambda m: None)
