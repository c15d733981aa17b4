"""satloc experiment tune: the settings once tuned on test runs, chosen on a calibration scene."""
import json

import numpy as np
import pytest

from satloc.errors import ConfigError
from satloc_env.experiments.tune import TuneConfig, pick_lowest, pick_lowest_vo, pick_smallest_within, tune


def rows(*spec):
    return [{"value": v, "mean_m": m, "failure_rate": f} for v, m, f in spec]


def test_pick_smallest_within_takes_the_cheapest_setting_that_matches_the_largest():
    r = rows((24, 0.40, 0.0), (32, 0.33, 0.0), (48, 0.31, 0.0), (96, 0.30, 0.0))
    assert pick_smallest_within(r, 0.05)["value"] == 32
    assert pick_smallest_within(r, 0.0)["value"] == 96
    # a cheaper value with a lower mean but more failures does not match the reference
    r = rows((24, 0.20, 0.05), (48, 0.31, 0.0), (96, 0.30, 0.0))
    assert pick_smallest_within(r, 0.05)["value"] == 48
    with pytest.raises(ValueError):
        pick_smallest_within([], 0.05)


def test_pick_lowest_breaks_ties_toward_the_current_default():
    r = rows((0.0, 1.2, 0), (0.5, 0.9, 0), (0.9, 0.9, 0), (0.99, 1.0, 0))
    assert pick_lowest(r)["value"] == 0.5
    assert pick_lowest(r, prefer=0.9)["value"] == 0.9
    assert pick_lowest(r, prefer=0.99)["value"] == 0.5   # not tied: the lower mean wins
    # the same answers can give means a few float bits apart (seen: 21.431019949 and 21.431019951 m): still a tie
    r = rows((0.0, 21.431019949082792, 0), (0.9, 21.43101995146071, 0))
    assert pick_lowest(r, prefer=0.9)["value"] == 0.9


def test_pick_lowest_vo_takes_the_smallest_drift_then_fewer_failures_then_the_default():
    r = [{"value": v, "trans_pct": t, "failed_steps": f} for v, t, f in
         ((9, 0.30, 0), (15, 0.25, 2), (21, 0.25, 0))]
    assert pick_lowest_vo(r)["value"] == 21
    r[2]["failed_steps"] = 2
    assert pick_lowest_vo(r)["value"] == 15 and pick_lowest_vo(r, prefer=21)["value"] == 21
    with pytest.raises(ValueError):
        pick_lowest_vo([])


def test_tune_config_is_checked():
    with pytest.raises(ConfigError, match="lock_mode"):
        TuneConfig(lock_mode="full+align")
    with pytest.raises(ConfigError, match="ef_search"):
        TuneConfig(ef_search=())
    with pytest.raises(ConfigError, match="lk_window_px"):
        TuneConfig(vo_lk_window_px=(9, 10))   # an even window: the VOConfig refuses it before any work
    with pytest.raises(ConfigError, match="detector"):
        TuneConfig(vo_detector=("sift",))
    with pytest.raises(ConfigError, match="contrast_threshold"):
        TuneConfig(efm_contrast_threshold=(0.0,))
    with pytest.raises(ConfigError, match="unknown|bogus"):
        tune("/nonexistent/never-written", {"bogus": 1})


@pytest.mark.parametrize("over", [{"scene": "city"}, {"compare": {"fabmap_train_scene": "residential"}}])
def test_tune_refuses_a_scene_the_tables_test_on(tmp_path, over):
    with pytest.raises(ConfigError, match="tables test on"):
        tune(tmp_path, {"experiment": over})
    assert not any(tmp_path.iterdir())   # refused before any work


def test_tune_refuses_an_invalid_grid_point_before_any_work(tmp_path):
    with pytest.raises(ConfigError, match="ef_search"):
        tune(tmp_path, {"ef_search": [8, 96]})   # below the localizer's 20 neighbours
    assert not any(tmp_path.iterdir())


def test_tune_runs_each_grid_on_the_calibration_scene_and_applies_its_rules(tmp_path):
    """End to end on a tiny calibration run: every grid point localized with its own value, the choices by
    the documented rules, tune.json and tune.md written."""
    from satloc.baselines.fabmap import FabMap, FabMapConfig
    from satloc.tracking.track import TrackConfig

    exp = {"database_frames": 30, "query_frames": 4, "query_spacing_m": 6.0, "features": "rgb",
           "compare": {"fabmap": {"max_features": 150, "new_place_samples": 5}, "fabmap_train_frames": 6}}
    cfg = {"experiment": exp, "ef_search": [20, 96], "ef_mode": "go", "lock_mass": [0.0, 0.9],
           "lock_mode": "go+track", "vocabulary_size": [20, 40], "contrast_threshold": [0.01, 0.04],
           "efm_contrast_threshold": [0.005, 0.04], "vo_detector": ["gftt", "orb"], "vo_lk_window_px": [9, 15],
           "vo_segment_m": 5.0}
    res = tune(tmp_path, cfg, progress=False, log=lambda m: None)
    saved = json.loads((tmp_path / "tune.json").read_text())
    assert saved["chosen"] == res["chosen"]
    assert "calib/town_a" in res["calibrated_on"] and "calib/town_b" in res["calibrated_on"]
    by = {}
    for r in res["rows"]:
        by.setdefault(r["setting"], []).append(r)
        assert r["queries"] == 4 and np.isfinite(r["mean_m"])
    assert [r["value"] for r in by["ef_search"]] == [20, 96]
    assert res["chosen"]["ef_search"] == pick_smallest_within(by["ef_search"], 0.05)["value"]
    fc = FabMapConfig()   # ties go to the current defaults
    assert res["chosen"]["lock_mass"] == pick_lowest(by["lock_mass"], TrackConfig().lock_mass)["value"]
    assert res["chosen"]["fabmap.vocabulary_size"] == pick_lowest(by["fabmap.vocabulary_size"],
                                                                  fc.vocabulary_size)["value"]
    assert res["chosen"]["fabmap.contrast_threshold"] == pick_lowest(by["fabmap.contrast_threshold"],
                                                                     fc.contrast_threshold)["value"]
    # each grid point ran with its own value
    for v in (20, 96):
        s = json.loads((tmp_path / f"ef_search_{v}" / "summary.json").read_text())
        assert s["config"]["localizer"]["ef_search"] == v and s["config"]["scene"] == "calib/town_a"
    for v in (0.0, 0.9):
        s = json.loads((tmp_path / f"lock_mass_{v}" / "summary.json").read_text())
        assert s["config"]["localizer"]["tracking"]["lock_mass"] == v
    for v in (20, 40):
        fm = FabMap.load(tmp_path / f"fabmap_vocabulary_size_{v}" / "fabmap" / "fabmap.npz")
        assert fm.config.vocabulary_size == v
    from satloc.baselines.efm import EfmConfig
    from satloc.tracking.vo import VOConfig

    assert [r["value"] for r in by["efm.contrast_threshold"]] == [0.005, 0.04]
    assert res["chosen"]["efm.contrast_threshold"] == pick_lowest(by["efm.contrast_threshold"],
                                                                  EfmConfig().contrast_threshold)["value"]
    vo = {}
    for r in res["vo_rows"]:
        vo.setdefault(r["setting"], []).append(r)
        assert np.isfinite(r["trans_pct"]) and r["segments"] > 0
    assert [r["value"] for r in vo["vo.detector"]] == ["gftt", "orb"]
    assert res["chosen"]["vo.detector"] == pick_lowest_vo(vo["vo.detector"], VOConfig().detector)["value"]
    if res["chosen"]["vo.detector"] == "gftt":   # the window only for the corner tracker
        assert res["chosen"]["vo.lk_window_px"] == pick_lowest_vo(vo["vo.lk_window_px"], 9)["value"]
        assert {r["value"] for r in vo["vo.lk_window_px"]} == {9, 15}
    else:
        assert "vo.lk_window_px" not in res["chosen"]
    md = (tmp_path / "tune.md").read_text()
    assert "| vo.detector |" in md and "| efm.contrast_threshold |" in md
    assert md.count("| ef_search |") == 2 and f"**{res['chosen']['ef_search']}**" in md
