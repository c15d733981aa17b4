"""The benchmark commands run and print the documented JSON keys (small settings; no timing asserted)."""
import json

import numpy as np
import pytest

from satloc.device import resolve_device
from satloc_env.cli import main


def test_bench_localize_prints_one_row_per_size(tmp_path, capsys):
    assert main(["bench", "localize", "--scene", "city", "--sizes-km", "0.03", "--queries", "2",
                 "--work", str(tmp_path), "--quiet"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert len(rows) == 1
    for r in rows:
        for key in ("db_km", "queries_per_s", "ms_per_query", "build_s", "train_projection_s", "entries",
                    "sequential_queries_per_s", "refined_queries_per_s", "refined_median_error_m"):
            assert key in r, key
        assert r["queries"] == 2 and r["queries_per_s"] > 0 and 0.02 < r["db_km"] < 0.04
        assert r["device"] == str(resolve_device("auto"))    # the device "auto" resolved to


def test_bench_env_prints_steps_per_second(capsys):
    assert main(["bench", "env", "--steps", "10"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["steps"] == 10 and r["steps_per_s"] > 0 and r["width"] == 620
    assert r["gl_renderer"] and r["gl_version"]       # which driver rendered (llvmpipe here, a GPU's elsewhere)
    assert r["cpu_ms_per_step"] > 0 and r["sensor"] == 0.0 and r["attitude"] == 1.0   # the defaults, named


def test_bench_env_takes_the_camera_knobs_and_refuses_bad_ones(capsys):
    assert main(["bench", "env", "--steps", "4", "--sensor", "1", "--attitude", "0.5"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["sensor"] == 1.0 and r["attitude"] == 0.5 and r["steps"] == 4
    with pytest.raises(SystemExit):
        main(["bench", "env", "--steps", "4", "--sensor", "2"])
    assert "--sensor" in capsys.readouterr().err


def test_bench_localize_reuses_only_a_recording_that_covers_the_longest_size(tmp_path):
    """A recording of another scene, or one shorter than the longest size asked, or one recorded otherwise
    (its stamp: another satellite gap or drift, as recordings made before the defaults moved), is not reused
    (it once measured a 1.14 km database under build_4km and said nothing)."""
    from satloc.persist import write_json
    from satloc_env.envs.record import STATUS, _status, record_stamp
    from satloc_env.experiments.bench import _bench_record_config, bench_recording

    def done(name, stamp=None):
        (tmp_path / name / "query").mkdir(parents=True)
        (tmp_path / name / "query" / "sequence.json").write_text("{}")
        n = int(name.rsplit("_", 1)[1])
        write_json(tmp_path / name / STATUS, _status(stamp or record_stamp(_bench_record_config("loop", n)), "sha",
                                                     ["database", "query"], complete=True))

    assert bench_recording(tmp_path, "loop", 717) == (tmp_path / "rec_loop_717", False)
    done("rec_loop_900", stamp={"scene": "loop", "note": "recorded before the drift"})
    assert bench_recording(tmp_path, "loop", 717) == (tmp_path / "rec_loop_717", False)
    done("rec_loop_717")
    assert bench_recording(tmp_path, "loop", 717) == (tmp_path / "rec_loop_717", True)
    assert bench_recording(tmp_path, "loop", 500) == (tmp_path / "rec_loop_717", True)    # its first frames
    assert bench_recording(tmp_path, "loop", 2717) == (tmp_path / "rec_loop_2717", False)
    assert bench_recording(tmp_path, "city", 500) == (tmp_path / "rec_city_500", False)
    (tmp_path / "rec_loop_3000" / "query").mkdir(parents=True)   # interrupted: no sequence.json
    assert bench_recording(tmp_path, "loop", 2717) == (tmp_path / "rec_loop_2717", False)


def test_bench_localize_refuses_a_size_longer_than_the_route(tmp_path, monkeypatch):
    import pytest

    import satloc.sequence
    from satloc.errors import ConfigError
    from satloc_env.experiments import bench

    class Short:   # a recording of a 0.1 km route
        poses = np.c_[np.linspace(0, 100, 60), np.zeros(60), np.zeros(60)]

    rec = tmp_path / "rec_city_1383"
    (rec / "query").mkdir(parents=True)
    (rec / "query" / "sequence.json").write_text("{}")
    monkeypatch.setattr(satloc.sequence.Sequence, "load", staticmethod(lambda p: Short()))
    with pytest.raises(ConfigError, match="0.10 km, less than the 0.9 km"):
        next(bench.bench_localize((0.9,), tmp_path, scene="city", progress=False))
