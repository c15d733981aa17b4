import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from satloc import SatelliteMap, Sequence
from satloc_env.cli import main
from satloc_env.envs.record import PassConfig, RecordConfig, record_passes

ROOT = Path(__file__).resolve().parent.parent


def test_record_database_and_query_passes(tmp_path):
    cfg = RecordConfig(scene="city",
                       database=PassConfig(spacing_m=2.0, max_frames=4, wander_m=0.0, speed_wander=0.0),
                       query=PassConfig(lane_offset_m=-0.75, spacing_m=5.0, max_frames=3, occlusion=0.5,
                                        appearance=0.5, seed=1, wander_m=0.0, speed_wander=0.0))
    db, q = record_passes(cfg, tmp_path / "rec", progress=False)   # on the lane offsets exactly (no drift)
    assert len(db) == 4 and len(q) == 3
    db2 = Sequence.load(tmp_path / "rec" / "database")
    assert np.allclose(db2.poses, db.poses)
    steps = np.linalg.norm(np.diff(db2.poses[:, :2], axis=0), axis=1)
    assert np.all((steps > 1.9) & (steps < 2.9))  # one frame every ~2 m at 0.8 m per step
    f = db2[0]
    assert f.depth is not None and f.depth.shape == (188, 620) and (f.depth > 0).mean() > 0.3
    # the query drives 1 m further left than the database
    d0, q0 = db2.poses[0], Sequence.load(tmp_path / "rec" / "query").poses[0]
    assert np.hypot(*(q0[:2] - d0[:2])) == pytest.approx(1.0, abs=1e-6)
    sm = SatelliteMap.load(tmp_path / "rec" / "map")
    assert sm.contains(db2.poses[:, :2]).all()
    assert db2.meta["scene"] == "city" and q.meta["pass_config"]["occlusion"] == 0.5


def test_cli_record_and_scene(tmp_path, capsys):
    assert main(["record", "--scene", "city", "--out", str(tmp_path / "r"), "--max-frames", "2", "--quiet"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["database_frames"] == 2 and out["query_frames"] == 2
    assert main(["scene", "residential", "--save", str(tmp_path / "s"), "--picture", str(tmp_path / "s.png")]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["buildings"] > 20 and (tmp_path / "s" / "scene.json").is_file() and (tmp_path / "s.png").is_file()


def test_cli_reports_bad_scene(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nroutes: {}\ncolour: red\n")
    assert main(["scene", str(bad)]) == 2
    assert "unknown key(s) ['colour']" in capsys.readouterr().err


def test_example_drive_runs(tmp_path):
    r = subprocess.run([sys.executable, str(ROOT / "examples" / "drive.py"), "--steps", "60", "--out", str(tmp_path)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "dead-reckoning drift" in r.stdout and list(tmp_path.glob("view_*.png"))


def test_make_vec_async_default_context():
    """The plain call from the issue, in a fresh process (no GL context exists before the workers fork).
    localizer=None: without it each worker would build (or load) the default "auto" localizer first."""
    code = ("import gymnasium as gym, numpy as np, satloc_env\n"
            "envs = gym.make_vec('satloc/SatLoc-v0', 2, vectorization_mode='async', localizer=None)\n"
            "obs, info = envs.reset(seed=0)\n"
            "for _ in range(3): obs, r, te, tr, info = envs.step(np.array([[8.0, 0.0]] * 2, np.float32))\n"
            "print(obs['left'].shape, info['pose'].shape)\nenvs.close()\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "(2, 188, 620, 3) (2, 3)" in r.stdout


def test_recordings_with_a_captured_map_and_wandering_passes(tmp_path):
    """A recording's map is a capture and its passes wander by default: the map is the captured one, the
    recording says so, the database pass drifts about its lane. Its stamp says both; a recording at gap 0
    without drift is stamped with the keys of before (what earlier stamps and caches hold: a map the ground's
    copy, passes on the lane offset), and a stamp of before never matches today's default."""
    from satloc.config import to_dict
    from satloc_env import load_scene
    from satloc_env.envs.record import record_stamp
    from satloc_env.experiments.scene_run import ExperimentConfig, record_config

    still = PassConfig(wander_m=0.0, speed_wander=0.0)
    old = RecordConfig(satellite_gap=0.0, database=still, query=dataclasses.replace(RecordConfig().query,
                                                                                   wander_m=0.0, speed_wander=0.0))
    stamp_before = record_stamp(old)
    assert "satellite_gap" not in stamp_before and "wander_m" not in stamp_before["database"]
    assert not {"wander_m", "speed_wander"} & set(to_dict(still, stamp=True))
    assert record_stamp(RecordConfig())["satellite_gap"] == 0.5 and record_stamp(RecordConfig()) != stamp_before
    assert to_dict(PassConfig())["wander_m"] == 0.3 and to_dict(ExperimentConfig())["speed_wander"] == 0.1
    assert not {"satellite_gap", "wander_m", "speed_wander"} & set(to_dict(ExperimentConfig(wander_m=0.0,
                                                                                             speed_wander=0.0),
                                                                            stamp=True))
    # a plain dict gives back what was set, an explicit 0 included (configurations derived from others)
    from satloc.config import from_dict
    assert from_dict(PassConfig, to_dict(still)).wander_m == 0.0 and "wander_m" in to_dict(still)
    cfg = RecordConfig(scene="city", satellite_gap=0.5,
                       database=PassConfig(spacing_m=1.0, max_frames=60, wander_m=0.4),
                       query=PassConfig(lane_offset_m=-0.75, spacing_m=10.0, max_frames=2, seed=1, wander_m=0.4))
    db, _ = record_passes(cfg, tmp_path / "rec", progress=False)
    assert db.meta["satellite_gap"] == 0.5 and db.meta["pass_config"]["wander_m"] == 0.4
    saved = SatelliteMap.load(tmp_path / "rec" / "map")
    assert np.array_equal(saved.image, load_scene("city", satellite_gap=0.5).satmap.image)
    route = load_scene("city").routes["main"]
    straight = db.poses[db.poses[:, 0] > 30]     # the first street, west from (100, 180), before its corner
    assert len(straight) > 30
    lateral = np.array([route.project(p[:2], s_hint=100.0 - p[0], window=10.0)[1] for p in straight])
    assert lateral.std() > 0.05 and np.abs(lateral + 1.75).max() < 0.9
    rc = record_config(ExperimentConfig(satellite_gap=0.5, wander_m=0.3))
    assert rc.satellite_gap == 0.5 and rc.database.wander_m == 0.3 and rc.query.wander_m == 0.3


def test_bad_wander_or_gap_of_a_recording_is_refused_before_any_work(tmp_path, capsys):
    from satloc import ConfigError

    with pytest.raises(ConfigError, match="wander_m"):
        PassConfig(wander_m=0.9)
    assert main(["record", "--scene", "city", "--out", str(tmp_path / "r"), "--wander", "0.9"]) == 2
    assert "wander_m" in capsys.readouterr().err
    assert main(["record", "--scene", "city", "--out", str(tmp_path / "g"), "--satellite-gap", "1.5"]) == 2
    assert "satellite_gap" in capsys.readouterr().err
    assert not (tmp_path / "r").exists() and not (tmp_path / "g").exists()


def test_a_pass_records_with_its_own_attitude_and_stamps_it(tmp_path):
    """A pass drives with its PassConfig's attitude (1 by default: the body pitches and rolls), whatever the
    environment's default; the stamp names it, so a level recording made before the field is not reused."""
    from satloc.config import to_dict
    from satloc_env.envs.record import make_env, record_pass

    assert to_dict(PassConfig(), stamp=True)["attitude"] == 1.0
    assert "attitude" not in to_dict(PassConfig(attitude=0.0), stamp=True)    # as stamped before the field
    with pytest.raises(Exception, match="attitude"):
        PassConfig(attitude=1.5)
    tilts = {}
    for a in (0.0, 1.0):
        env = make_env(scene="city", localizer=None, attitude=1.0 - a)           # the env's own setting is overridden
        try:
            record_pass(env, PassConfig(spacing_m=2.0, max_frames=3, attitude=a), "main", tmp_path / f"a{a}", "db",
                        progress=False)
            tilts[a] = env.attitude.tilt
        finally:
            env.close()
    assert tilts[0.0] is None and tilts[1.0] is not None
    assert Sequence.load(tmp_path / "a1.0").meta["pass_config"]["attitude"] == 1.0
