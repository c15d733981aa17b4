"""The examples run (small settings), so they never rot. ``examples/drive.py`` is run in test_record.py."""
import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def test_example_stress_runs_and_writes_its_table_and_curve(tmp_path):
    r = subprocess.run([sys.executable, str(ROOT / "examples" / "stress.py"), "--aliasing", "0", "1",
                        "--occlusion", "0.5", "--db-frames", "20", "--query-frames", "3", "--modes", "np",
                        "--features", "rgb", "--out", str(tmp_path)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    rows = list(csv.DictReader(open(tmp_path / "stress.csv")))
    assert [(float(x["aliasing"]), float(x["occlusion"]), x["mode"]) for x in rows] == [(0.0, 0.5, "np"),
                                                                                         (1.0, 0.5, "np")]
    assert all(np.isfinite(float(x["mean_m"])) and int(x["queries"]) >= 2 for x in rows)
    assert (tmp_path / "stress.png").stat().st_size > 5000
    # the knobs reached the recorded passes
    meta = json.loads((tmp_path / "a1_o0.5" / "rec" / "database" / "sequence.json").read_text())["meta"]
    assert meta["aliasing"] == 1.0
    meta = json.loads((tmp_path / "a1_o0.5" / "rec" / "query" / "sequence.json").read_text())["meta"]
    assert meta["pass_config"]["occlusion"] == 0.5
