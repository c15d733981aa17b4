"""The benchmark commands run and print the documented JSON keys (small settings; no timing asserted)."""
import json

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
