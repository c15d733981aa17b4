"""satloc_env.experiments.scale: the experiments' units as Ray tasks give the serial run's tables, byte for byte, and a rerun
skips their finished stages; Ray errors; simulator environments stepped in Ray actors."""
import sys

import numpy as np
import pytest
import yaml

ray = pytest.importorskip("ray")

from satloc.errors import ConfigError
from satloc_env.cli import main
from satloc_env.experiments.scale import Runner, Unit, env_actor

# tests/test_compare.py's tiny sweep, two knob combinations, FAB-MAP (a stage the combinations share) and the
# learned projections (torch: thread-count dependent sums, see satloc_env.experiments.scale)
# satellite_gap 0: each Ray worker is a process of its own, and a capture of city costs each of them seconds;
# what is tested here is the distribution, not the capture
TINY_SWEEP = {"aliasing": [0.0], "occlusion": [0.0, 0.3], "appearance": [0.5], "satellite_gap": [0.0],
              "experiment": {"database_frames": 24, "query_frames": 3, "query_spacing_m": 6.0, "features": "rgb",
                             "modes": ["go", "full"], "pictures": False,
                             "projection": {"max_anchors": 2000, "max_epochs": 2},
                             "compare": {"baselines": ["fabmap"],
                                         "fabmap": {"vocabulary_size": 40, "max_features": 150,
                                                    "new_place_samples": 5}, "fabmap_train_frames": 6}}}
STAGES = ("fabmap_stage.json", "*/record.json", "*/build_stage.json", "*/projection_stage.json")


@pytest.fixture(scope="module")
def cluster():
    """A local Ray cluster of 2 CPUs for the module (the runners use it as it is), shut down at the end."""
    from ray import cloudpickle

    cloudpickle.register_pickle_by_value(sys.modules[__name__])   # the units below: the workers cannot import tests/
    ray.init(num_cpus=2, logging_level="WARNING", include_dashboard=False)
    yield
    ray.shutdown()


def _square(x, progress, log):
    log(f"square {x}")
    return x * x


def _bad(progress, log):
    raise ConfigError("bad unit")


def test_runner_keeps_the_order_and_passes_errors_on(cluster):
    units = [Unit(f"u{i}", _square, (i,)) for i in range(5)]
    lines: list[str] = []
    assert Runner().run(units, log=lines.append) == [0, 1, 4, 9, 16]
    assert lines == [f"square {i}" for i in range(5)]
    lines.clear()
    with Runner(ray=True) as r:
        assert r.cpus_per_unit(5) == 1 and r.cpus_per_unit(1) == 2
        assert r.run(units, log=lines.append) == [0, 1, 4, 9, 16]
        with pytest.raises(ConfigError, match="bad unit"):   # the unit's own error, not Ray's wrapper
            r.run([Unit("bad", _bad)], log=lambda m: None)
    assert sorted(m for m in lines if m.startswith("square")) == [f"square {i}" for i in range(5)]
    assert any(m.startswith("[ray] u4: done in") for m in lines)
    assert ray.is_initialized()   # not started by the runner: left running


def test_ray_missing_and_ray_for_another_experiment(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)   # import ray raises ImportError
    with pytest.raises(ConfigError, match=r"pip install -e '\.\[ray\]'"):
        Runner(ray=True)
    assert main(["experiment", "sweep", "--out", str(tmp_path), "--ray"]) == 2
    assert "pip install" in capsys.readouterr().err
    monkeypatch.undo()
    assert main(["experiment", "aliasing", "--out", str(tmp_path), "--ray"]) == 2
    assert "only table1, table2, sweep, gap and fidelity" in capsys.readouterr().err


def test_sweep_on_ray_matches_serial_and_a_rerun_skips_finished_stages(cluster, tmp_path, capsys):
    cfg = tmp_path / "sweep.yaml"
    cfg.write_text(yaml.safe_dump(TINY_SWEEP))
    ser, par = tmp_path / "serial", tmp_path / "ray"
    assert main(["experiment", "sweep", "--config", str(cfg), "--out", str(ser), "--quiet"]) == 0
    assert main(["experiment", "sweep", "--config", str(cfg), "--out", str(par), "--ray", "--quiet"]) == 0
    # sweep.csv holds no timing column: byte-identical (so are sweep.md and each combination's localizations)
    for name in ("sweep.csv", "sweep.md", "a0_o0_p0.5_g0/localization_full.npz", "a0_o0.3_p0.5_g0/baseline_fabmap.npz"):
        assert (ser / name).read_bytes() == (par / name).read_bytes(), name
    assert len((par / "sweep.csv").read_text().splitlines()) == 1 + 2 * 5   # 3 methods and the 2 reference floors
    # rerun on Ray: every stage of every unit skipped (stamps untouched), the same table
    stamps = {p: p.stat().st_mtime_ns for pattern in STAGES for p in par.glob(pattern)}
    assert len(stamps) == 1 + 3 * 2
    capsys.readouterr()
    assert main(["experiment", "sweep", "--config", str(cfg), "--out", str(par), "--ray"]) == 0
    err = capsys.readouterr().err
    assert all(p.stat().st_mtime_ns == t for p, t in stamps.items())
    assert "[ray] sweep a0_o0.3_p0.5_g0: done in" in err and "[ray] FAB-MAP training: done in" in err
    for stage in ("recording", "building the dictionary", "learning the projections", "training FAB-MAP"):
        assert stage not in err, stage
    assert (ser / "sweep.csv").read_bytes() == (par / "sweep.csv").read_bytes()


def test_env_actor_steps_like_a_local_env(cluster):
    import gymnasium as gym

    import satloc_env  # noqa: F401  (registers the id)

    kw = {"scene": "city", "localizer": None}
    car, cars = env_actor(**kw), env_actor(num_envs=2, **kw)   # one env; the batched env of 2 in one actor
    try:
        obs, _ = ray.get(car.reset.remote(seed=3))
        act = ray.get(car.autopilot_action.remote())
        obs2, _, term, trunc, info2 = ray.get(car.step.remote(act))
        obs_space, act_space = ray.get(car.spaces.remote())
        ray.get(car.close.remote())
        vobs, _ = ray.get(cars.reset.remote(seed=0))
        vout = ray.get(cars.step.remote(ray.get(cars.autopilot_action.remote())))
    finally:
        ray.kill(car)
        ray.kill(cars)
    assert obs in obs_space and act in act_space and info2["step"] == 1 and not (term or trunc)
    assert vobs["left"].shape[0] == 2 and vout[1].shape == (2,)
    local = gym.make("satloc/SatLoc-v0", **kw)   # the same car here: the same pixels and pose
    try:
        ref, _ = local.reset(seed=3)
        ref2, *_ = local.step(local.unwrapped.autopilot_action())
    finally:
        local.close()
    for a, b in ((obs, ref), (obs2, ref2)):
        assert set(a) == set(b) and all(np.array_equal(a[k], b[k]) for k in a)


def test_a_task_refuses_a_working_directory_its_node_lacks(tmp_path):
    """A Ray task runs in the driver's working directory (relative --out paths); on a node without that
    folder it stops with a clear error instead of writing somewhere else."""
    from satloc_env.experiments.scale import _run_unit

    with pytest.raises(ConfigError, match="does not exist on this node"):
        _run_unit(Unit("sq", _square, (3,)), 1, None, str(tmp_path / "not_here"))


def test_sweep_refuses_knob_values_that_share_a_folder():
    from satloc_env.experiments.tables import SweepConfig

    with pytest.raises(ConfigError, match="first 6 significant digits"):
        SweepConfig(aliasing=(0.0, 0.0))
    with pytest.raises(ConfigError, match="occlusion"):
        SweepConfig(occlusion=(0.1234561, 0.1234564))   # both print as 0.123456: one folder
