"""The episode viewer (satloc_env.envs.viewer, satloc view): Rerun recordings of an environment's episode and of
an experiment folder, read back with Rerun's own ``rrd print``."""
import collections
import os
import re
import subprocess
import sys

import gymnasium as gym
import pytest

import satloc_env  # noqa: F401

rr = pytest.importorskip("rerun")


def entities(path) -> collections.Counter:
    """Rows logged per entity path of an .rrd (Rerun's ``rrd print``)."""
    r = subprocess.run([sys.executable, "-m", "rerun", "rrd", "print", str(path)], capture_output=True, text=True,
                       timeout=120, env=dict(os.environ, RERUN_ANALYTICS="0"))
    assert r.returncode == 0, r.stderr
    rows = collections.Counter()
    for m in re.finditer(r"with (\d+) rows .*? - (/(?:\\.|\S)+)", r.stdout):
        rows[m.group(2)] += int(m.group(1))
    return rows


class PriorCentre:
    name = "prior centre"

    def reset(self, context):
        pass

    def localize(self, query):
        return query.prior.pose


def test_the_wrapper_logs_views_trails_posterior_prior_and_error(tmp_path):
    from satloc_env.envs.viewer import RerunViewer

    path = tmp_path / "episode.rrd"
    env = RerunViewer(gym.make("satloc/SatLoc-v0", scene="city", localizer=PriorCentre()), path)
    env.reset(seed=0)
    for _ in range(4):
        env.step(env.unwrapped.autopilot_action())
    assert env.unwrapped.last_prior is not None
    env.close()
    rows = entities(path)
    for e in ("/camera/left", "/camera/right", "/map/truth", "/map/estimate", "/map/posterior", "/map/prior",
              "/map/car", "/error_m"):
        assert rows[e] == 5, (e, rows)          # the reset and 4 steps
    assert rows["/map/image"] == 1               # the map once


def test_satloc_view_of_an_experiment_folder(tmp_path):
    from satloc_env.cli import main
    from satloc_env.experiments.scene_run import ExperimentConfig, run_scene

    cfg = ExperimentConfig(scene="city", database_frames=20, query_frames=3, query_spacing_m=6.0, features="rgb",
                           modes=("go",), pictures=False)
    run_scene(cfg, tmp_path / "run", progress=False, log=lambda m: None)
    out = tmp_path / "run.rrd"
    assert main(["view", str(tmp_path / "run"), "--out", str(out), "--quiet"]) == 0
    rows = entities(out)
    n = 3
    assert rows["/camera/left"] == n and rows["/map/truth"] == n and rows["/map/image"] == 1
    for name in ("Ours-GO", "Prior alone", "Dead reckoning"):
        e = rr.escape_entity_path_part(name)
        assert rows[f"/methods/{e}/trail"] == n and rows[f"/methods/{e}/estimate"] == n, (name, rows)
        assert rows[f"/error_m/{e}"] == n
    assert rows[f"/methods/{rr.escape_entity_path_part('Prior alone')}/prior"] == n


def test_satloc_view_refuses_what_is_not_a_folder(tmp_path, capsys):
    from satloc_env.cli import main

    assert main(["view", str(tmp_path)]) != 0
    assert "no localization_*.npz" in capsys.readouterr().err
