"""The comparison harness (satloc_env/experiments/tables.py): every method on one split, Table II's counting."""
import json
from pathlib import Path

import numpy as np
import pytest

from satloc.errors import ConfigError
from satloc.persist import load_npz
from satloc.sequence import Sequence
from satloc_env.experiments.scene_run import ExperimentConfig, covered_queries
from satloc_env.experiments.tables import CompareConfig, Table2Config, _write_table2, operating_point, trained_fabmap

ROOT = Path(__file__).resolve().parent.parent
# each test builds its scenes' worlds (1-2 GB each at variety 1); dropped after each test, not after the file
pytestmark = pytest.mark.usefixtures("free_worlds_after_each_test")
TINY_BASELINES = {"fabmap": {"vocabulary_size": 40, "max_features": 150, "new_place_samples": 5},
                  "efm": {"features": 200}, "fabmap_train_frames": 6}


def meta_of(path):
    return load_npz(path, "localization")[1]


def test_fabmap_motion_window_from_the_steps():
    from satloc_env.experiments.tables import fabmap_motion_window

    db = np.column_stack([np.arange(0, 100, 2.0), np.zeros(50), np.zeros(50)])      # places every 2 m
    assert fabmap_motion_window(db, db[::5]) == 6                                    # 10 m steps: 5 places + 1
    assert fabmap_motion_window(db, db[::2] + 0.1) == 3                              # 4 m: 2 + 1
    assert fabmap_motion_window(db, db[:1]) == 1                                     # one query: no step known
    with pytest.raises(ConfigError, match="fabmap_motion_window"):
        CompareConfig(fabmap_motion_window=-1)


def test_operating_point_counts_true_positives_on_a_hand_made_case():
    # 6 queries: 4 inside the map, 2 outside
    errors = np.array([0.5, 3.0, 25.0, 2.0, 1.0, 4.0])
    scores = np.array([0.9, 0.8, 0.7, 0.2, 0.6, 0.1])
    inside = np.array([True, True, True, True, False, False])
    # thresholds 0.9, 0.8, 0.7, 0.6, 0.2, 0.1 -> TP 1, 2, 2, 2, 3, 3; declared 1..6; F1 best at 0.8 (2/2, 2/4)
    op = operating_point(errors, scores, inside, "max_f1")
    assert op["threshold"] == 0.8 and op["tp"] == 2 and op["declared"] == 2 and op["positives"] == 4
    assert op["precision"] == 1.0 and op["recall"] == 0.5
    # at least 70 % precision: threshold 0.2 declares 5, TP 3 (the 25 m query is inside but not within 10 m)
    op = operating_point(errors, scores, inside, "recall_at_precision", 0.6)
    assert op["threshold"] == 0.2 and op["tp"] == 3 and op["declared"] == 5
    assert op["recall"] == 0.75 and op["precision"] == pytest.approx(0.6)
    # a query outside the map declared inside never counts, however close its estimate
    op = operating_point([0.1, 0.1], [1.0, 0.5], np.array([False, True]), "max_f1")
    assert op["tp"] == 1 and op["threshold"] == 0.5


def test_table2_files_and_headers(tmp_path):
    e, s, ins = np.array([1.0, 20.0, 2.0]), np.array([3.0, 2.0, 1.0]), np.array([True, True, False])
    op = operating_point(e, s, ins)
    curve = op.pop("curve")
    rows = [dict({"method": "A"}, **op, queries=3, inside_queries=2, s_per_query=0.1)]
    _write_table2(tmp_path, rows, {"A": curve}, Table2Config())
    lines = (tmp_path / "table2.csv").read_text().splitlines()
    assert lines[0] == ("method,precision,recall,threshold,precision_ci95_low,precision_ci95_high,recall_ci95_low,"
                        "recall_ci95_high,oracle_precision,oracle_recall,calibrated_on,calibration_scene,"
                        "calibration_nearest_m,odometry,ci_method")
    assert lines[1] == "A,1.000,0.500,3,,,,,,,,,,,"
    assert "| A | 100.0 % |  | 50.0 % |" in (tmp_path / "table2.md").read_text()
    assert (tmp_path / "pr_curves.png").stat().st_size > 5000


def test_config_errors(tmp_path):
    with pytest.raises(ConfigError, match="baselines"):
        CompareConfig(baselines=("netvlad",))
    with pytest.raises(ConfigError, match="disjoint"):
        trained_fabmap(CompareConfig(fabmap_train_scene="city"), "city", tmp_path, progress=False, log=lambda m: None)
    with pytest.raises(ConfigError, match="rule"):
        Table2Config(rule="best")


def test_protocol_splits():
    from satloc_env.experiments.tables import protocol_split

    db, q = protocol_split("city", 50, 0.4, seed=3)
    assert len(db) == 20 and len(q) == 30 and len(np.intersect1d(db, q)) == 0
    assert sorted(np.concatenate([db, q]).tolist()) == list(range(50))
    db2, q2 = protocol_split("city", 50, 0.4, seed=3)
    assert np.array_equal(db, db2) and np.array_equal(q, q2)          # seeded: reproducible
    assert not np.array_equal(db, protocol_split("city", 50, 0.4, seed=4)[0])
    db, q = protocol_split("residential", 50, step=8)
    assert db.tolist() == [0, 8, 16, 24, 32, 40, 48] and q is None
    with pytest.raises(ConfigError, match="protocol"):
        protocol_split("highway", 50)
    with pytest.raises(ConfigError, match="protocols"):
        ExperimentConfig(protocols=("revisit", "desert"))


def test_table1_protocols_on_a_tiny_section(tmp_path):
    from satloc_env.experiments.tables import table1

    # every method on the same splits: two modes, FAB-MAP (a small vocabulary trained on a few frames of
    # residential) and EFM (few features)
    small = {"database_frames": 24, "query_frames": 3, "query_spacing_m": 6.0, "features": "rgb",
             "modes": ["go", "np"], "compare": TINY_BASELINES, "pictures": False,
             "localizers": [str(ROOT / "examples" / "own_localizer.py") + ":GpsOdometryFilter"]}   # a user's localizer, beside the built-in ones
    rows = table1(tmp_path, ("city",), small, progress=False, log=lambda m: None)
    lines = (tmp_path / "table1.csv").read_text().splitlines()
    assert lines[0] == "method,scene,mean_m,std_m,protocol,ci95_low,ci95_high,median_m,within_1m,within_10m,failure_rate,queries,odometry,ci_method"
    methods = ("Ours-GO", "Ours-NP", "FAB-MAP", "FAB-MAP + seq", "EFM", "Prior alone", "Dead reckoning",
               "GPS + odometry filter")
    assert [(r["protocol"], r["method"]) for r in rows] == [(p, m) for p in ("revisit", "city", "residential")
                                                           for m in methods]
    assert all(np.isfinite(r["mean_m"]) and r["s_per_query"] > 0 for r in rows)
    # the floors: the prior alone 2r/3 = 13.3 m from the truth on average (3 queries: loosely); the odometry
    # they were given is the tracked modes' (none tracked here: the true motion plus noise)
    by_method = {(r["protocol"], r["method"]): r for r in rows}
    assert all(0 < by_method[(p, "Prior alone")]["mean_m"] < 20 for p in ("revisit", "city", "residential"))
    assert by_method[("revisit", "Dead reckoning")]["odometry"] == "noisy_truth"
    assert by_method[("revisit", "Prior alone")]["odometry"] == ""
    res = json.loads((tmp_path / "city" / "compare.json").read_text())["methods"]
    assert list(res) == ["go", "np", "fabmap", "fabmap+seq", "efm", "prior", "dead-reckoning",
                         "user-gps-odometry-filter"]
    assert res["user-gps-odometry-filter"]["name"] == "GPS + odometry filter"
    a, meta = load_npz(tmp_path / "city" / "localization_user-gps-odometry-filter.npz", "localization")
    assert meta["name"] == "GPS + odometry filter" and np.all(np.isfinite(a["errors"]))
    assert all(m["failed"] == 0 for m in res.values() if "failed" in m)
    for m in ("fabmap", "fabmap+seq", "efm"):
        a, _ = load_npz(tmp_path / "city" / f"baseline_{m}.npz", "localization")
        assert np.all(np.isfinite(a["errors"])) and np.all(np.isfinite(a["inlier_score"]))
    # the sequential row's window: query steps of 6 m over database places about 1.6 m apart -> 4 + 1 places
    assert meta_of(tmp_path / "city" / "baseline_fabmap+seq.npz")["motion_window"] == 5
    # FAB-MAP was trained on the other scene, once for the three protocols
    stamp = json.loads((tmp_path / "city" / "fabmap_stage.json").read_text())
    assert stamp["config"]["train_scene"] == "residential" and stamp["training_images"] == 6
    by = {r["protocol"]: r for r in rows if r["method"] == "EFM"}
    assert by["city"]["queries"] == 24 - round(0.4 * 24)
    second = Sequence.load(tmp_path / "city" / "protocol_residential" / "second")
    gaps = np.hypot(*np.diff(second.poses[:, :2], axis=0).T)
    assert np.allclose(gaps, 8.0, atol=0.6)                  # one frame per second at 8 m/s
    # and its database: every k-th frame of the database pass, k measured on the pass (its frames lie about
    # 1.6 m apart, not its spacing_m of 1 m): one frame per second too
    kept = json.loads((tmp_path / "city" / "protocol_residential" / "build_stage.json").read_text())
    full = Sequence.load(tmp_path / "city" / "rec" / "database")
    d = np.hypot(*np.diff(full.poses[kept["config"]["database_frames"], :2], axis=0).T)
    assert len(d) >= 3 and np.all(np.abs(d - 8.0) < 2.0), d
    assert "Protocol **city**" in (tmp_path / "table1.md").read_text()
    # rerun: every stage reused, and every mode's localization (stamped when it finished): the same rows
    stamps = {p: p.stat().st_mtime_ns for p in (tmp_path / "city").rglob("*_stage.json")}
    stamps.update({p: p.stat().st_mtime_ns for p in (tmp_path / "city").rglob("record.json")})
    located = {p: p.stat().st_mtime_ns for p in (tmp_path / "city").rglob("localization_*.npz")
               if p.stem.split("_", 1)[1] in ("go", "np")}   # the modes' (the others run every time: no stamp)
    again = table1(tmp_path, ("city",), small, progress=False, log=lambda m: None)
    assert len(stamps) >= 5 and all(p.stat().st_mtime_ns == t for p, t in stamps.items())
    assert len(located) >= 6 and all(p.stat().st_mtime_ns == t for p, t in located.items())
    ours = lambda rs: [r for r in rs if r["method"].startswith("Ours")]   # noqa: E731
    assert ours(again) == ours(rows) and len(ours(rows)) >= 6
    # a damaged stamp: that mode is localized again
    victim = sorted(located)[0]
    victim.with_name(victim.name.replace(".npz", ".stamp.json")).write_text("{not json")
    table1(tmp_path, ("city",), small, progress=False, log=lambda m: None)
    assert victim.stat().st_mtime_ns != located[victim]


def test_sweep_config_and_figure(tmp_path):
    from satloc.config import from_dict
    from satloc_env.experiments.tables import SweepConfig, plot_sweep

    with pytest.raises(ConfigError, match="occlusion"):
        SweepConfig(occlusion=(0.0, 1.5))
    rows = [{"aliasing": a, "occlusion": o, "appearance": 0.5, "method": m, "mean_m": e, "recall_10m": r}
            for a in (0.0, 1.0) for o in (0.0, 0.6) for m, e, r in (("Ours-full", 0.5, 1.0), ("EFM", 3.0, 0.8))]
    plot_sweep(rows, tmp_path / "sweep.png")
    assert (tmp_path / "sweep.png").stat().st_size > 5000
    with pytest.raises(ConfigError, match=r"experiment\.satellite_gap: the sweep's gap is its own axis"):
        from_dict(SweepConfig, {"experiment": {"satellite_gap": 0.5}})
    with pytest.raises(ConfigError, match="satellite_gap"):
        SweepConfig(satellite_gap=(0.5, 1.5))
    assert [c[3] for c in SweepConfig(aliasing=(0.0,), occlusion=(0.3,), satellite_gap=(0.0, 0.5)).combinations()] \
        == [0.0, 0.5]


def test_gap_curve_is_the_sweep_over_the_gap_with_its_picture(tmp_path, monkeypatch):
    """satloc experiment gap: the sweep with GAP_CURVE's knobs (a user's keys replace them, ``experiment``
    merges), then gap.png from its rows."""
    import satloc_env.experiments.tables as T
    from satloc_env.cli import main

    seen = {}

    def fake_sweep(out, config, progress, log, runner):
        seen.update(config)
        return [{"scene": "city", "aliasing": 0.0, "occlusion": 0.3, "appearance": 0.5, "satellite_gap": g,
                 "method": m, "mean_m": e * (1 + g), "median_m": e / 4 * (1 + g), "within_1m": 0.9 - 0.3 * g}
                for g in (0.0, 0.5, 1.0) for m, e in (("Ours-full + track", 0.8), ("EFM", 4.8))]

    monkeypatch.setattr(T, "sweep", fake_sweep)
    rows = T.gap_curve(tmp_path, {"satellite_gap": [0.0, 1.0], "experiment": {"database_frames": 50}},
                       progress=False, log=lambda m: None)
    assert seen["satellite_gap"] == [0.0, 1.0] and seen["occlusion"] == [0.3] and seen["scene"] == "city"
    assert seen["experiment"]["database_frames"] == 50 and seen["experiment"]["modes"] == list(T.MODES)
    assert len(rows) == 6 and (tmp_path / "gap.png").stat().st_size > 5000
    # the command: a bad key of its configuration is named, nothing is written
    bad = tmp_path / "bad.yaml"
    bad.write_text("gaps: [0, 1]\n")
    assert main(["experiment", "gap", "--config", str(bad), "--out", str(tmp_path / "g"), "--quiet"]) == 2
    assert not (tmp_path / "g").exists()


def test_sweep_end_to_end_reports_intervals_failures_and_odometry(tmp_path):
    """sweep() on one tiny combination: sweep.csv has SWEEP_COLUMNS, one row per method, each the figures of
    that combination's compare.json (failures counted, bootstrap interval around the mean)."""
    from satloc_env.experiments.tables import SWEEP_COLUMNS, sweep

    exp = {"database_frames": 30, "query_frames": 4, "query_spacing_m": 6.0, "features": "rgb",
           "modes": ["go", "go+track"], "compare": dict(TINY_BASELINES, baselines=["efm"]), "pictures": False}
    rows = sweep(tmp_path, {"aliasing": [0.0], "occlusion": [0.3], "appearance": [0.5], "experiment": exp},
                 progress=False, log=lambda m: None)
    lines = (tmp_path / "sweep.csv").read_text().splitlines()
    assert lines[0] == ",".join(SWEEP_COLUMNS) and len(lines) == 6
    comp = json.loads((tmp_path / "a0_o0.3_p0.5_g0.5" / "compare.json").read_text())["methods"]
    assert [r["method"] for r in rows] == ["Ours-GO", "Ours-GO + track", "EFM", "Prior alone", "Dead reckoning"]
    for r, key in zip(rows, ("go", "go+track", "efm", "prior", "dead-reckoning")):
        m = comp[key]
        assert r["mean_m"] == round(m["mean_m"], 4) and r["failure_rate"] == round(m["failure_rate"], 4)
        assert r["ci95_low"] <= r["mean_m"] <= r["ci95_high"] and r["queries"] == 4
        assert r["odometry"] == ("visual" if key in ("go+track", "dead-reckoning") else "")
    assert "failed" in (tmp_path / "sweep.md").read_text()


def test_table2_calibrates_on_other_passes_and_reports_the_test(tmp_path):
    """table2() end to end on a tiny configuration of loop: the thresholds come from the calibration passes
    (other seeds and spacing, on another place: loop_calib, recorded and built against its own map), the test
    figures are computed at them, with intervals, beside the oracle."""
    from satloc.evaluation.metrics import precision_recall
    from satloc_env.experiments.tables import TABLE2_COLUMNS, table2

    # satellite_gap 0: two ring scenes, whose captures would cost more than the rest of this test; what is
    # tested is where Table II records, calibrates and reports
    exp = {"database_frames": 30, "query_frames": 4, "query_spacing_m": 6.0, "features": "rgb",
           "modes": ["go", "go+track"], "compare": dict(TINY_BASELINES, baselines=["efm"]), "pictures": False,
           "satellite_gap": 0.0}
    cfg = {"experiment": exp, "outside_frames": 4, "calibration_spacing_m": 4.0}
    logged = []
    rows = table2(tmp_path, cfg, progress=False, log=logged.append)
    assert any("every calibration query is inside the map" in m for m in logged)   # 4 queries on the ring
    assert [r["method"] for r in rows] == ["Ours-GO", "Ours-GO + track", "EFM"]
    lines = (tmp_path / "table2.csv").read_text().splitlines()
    assert lines[0] == ",".join(TABLE2_COLUMNS) and len(lines) == 4
    comp = {p: json.loads((tmp_path / p / "compare.json").read_text())
            for p in ("inside", "outside", "calib_inside", "calib_outside")}
    # the calibration passes are other frames at another place: loop_calib, other seeds, a 4 m spacing
    q = {"inside": Sequence.load(tmp_path / "rec" / "query"), "outside": Sequence.load(tmp_path / "rec" / "outside"),
         "calib_inside": Sequence.load(tmp_path / "calibration" / "rec" / "query"),
         "calib_outside": Sequence.load(tmp_path / "calibration" / "rec" / "calib_outside")}
    assert {q[p].meta["scene"] for p in q} == {"loop", "loop_calib"}
    assert q["calib_inside"].meta["scene"] == q["calib_outside"].meta["scene"] == "loop_calib"
    assert (tmp_path / "calibration" / "build" / "build.json").is_file()
    # recorded densely for the visual odometry of the tracked row; the queries 6 m (4 m) apart, 4 of each
    sel = {p: np.array(c["frames"]) for p, c in comp.items()}
    assert q["inside"].meta["pass_config"]["spacing_m"] == 1.0 and len(q["inside"]) > 12
    for p, sp in (("inside", 6.0), ("calib_inside", 4.0)):
        d = np.hypot(*np.diff(q[p].poses[sel[p], :2], axis=0).T)
        assert len(sel[p]) == 4 and np.all(d >= sp - 0.01) and np.all(d < sp + 2.0), (p, d)
    assert q["calib_outside"].meta["pass_config"]["seed"] == 4 and q["outside"].meta["pass_config"]["seed"] == 2
    for r in rows:
        assert "seeds 3, 4" in r["calibrated_on"] and r["queries"] == 8
        assert r["calibration_scene"] == "loop_calib" and r["calibration_nearest_m"] is None
        # the precision and recall are the test queries' at the calibrated threshold, recomputed here
        key = {"Ours-GO": "go", "Ours-GO + track": "go+track", "EFM": "efm"}[r["method"]]
        err = np.concatenate([np.load(tmp_path / p / (f"localization_{key}.npz" if key != "efm" else
                                                       "baseline_efm.npz"))["errors"] for p in ("inside", "outside")])
        sc = np.concatenate([np.load(tmp_path / p / (f"localization_{key}.npz" if key != "efm" else
                                                      "baseline_efm.npz"))["inlier_score"] for p in ("inside", "outside")])
        from satloc_env.experiments.scene_run import covered_queries
        db = Sequence.load(tmp_path / "rec" / "database")
        inside = np.concatenate([np.isin(sel[p], covered_queries(db, q[p], 5.0)) for p in ("inside", "outside")])
        sc = np.where(np.isfinite(err), sc, np.nan)
        pr = precision_recall(err, sc, r["threshold"], inside)
        assert pr["tp"] == r["tp"] and pr["declared"] == r["declared"]
        assert r["odometry"] == ("visual" if "track" in r["method"] else "")
        if np.isfinite(r["recall"]):
            assert r["recall_ci95_low"] <= r["recall"] <= r["recall_ci95_high"]
    md = (tmp_path / "table2.md").read_text()
    assert "calibration queries" in md and "oracle" in md
    with pytest.raises(ConfigError, match="calibration_seeds"):
        Table2Config(calibration_seeds=(1, 5))
    with pytest.raises(ConfigError, match="calibration_scene"):
        Table2Config(calibration_scene="loop")


def test_nearest_distance_between_query_sets():
    from satloc_env.experiments.tables import nearest_distance

    a = np.array([[0.0, 0.0], [10.0, 0.0], [np.nan, np.nan]])
    b = np.array([[10.0, 3.0], [50.0, 50.0]])
    assert nearest_distance(a, b) == pytest.approx(3.0) and nearest_distance(b, a) == pytest.approx(3.0)
    assert np.isnan(nearest_distance(a[2:], b))


def test_table2_recordings_finished_before_a_failure_are_reused(tmp_path, monkeypatch):
    """Each Table II recording is stamped when it ends, so a rerun after a failure elsewhere in its batch
    (another recording, FAB-MAP's training) records only what is missing; another configuration redoes it."""
    import types
    from pathlib import Path

    import satloc_env.envs.record as R
    import satloc_env.experiments.tables as C

    calls = []

    def fake_passes(rec, out_dir, progress):
        calls.append("query")
        (Path(out_dir) / "query").mkdir(parents=True, exist_ok=True)
        (Path(out_dir) / "query" / "sequence.json").write_text("{}")

    def fake_pass(env, p, route, out_dir, name, progress, meta):
        calls.append(name)
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        (Path(out_dir) / "sequence.json").write_text("{}")

    class FakeEnv:
        scene = types.SimpleNamespace(name="ring")

        def reset(self, seed=None):
            pass

        def close(self):
            pass

    monkeypatch.setattr(R, "record_passes", fake_passes)
    monkeypatch.setattr(C, "record_pass", fake_pass)
    monkeypatch.setattr(C, "make_env", lambda **kw: FakeEnv())
    rec = types.SimpleNamespace(scene="ring", resolution="half", aliasing=0.0, speed_mps=8.0, satellite_gap=None)
    outside = types.SimpleNamespace(seed=2, route="branch")
    for rc in ({"v": 1}, {"v": 1}, {"v": 2}):
        C._record_table2_pass(rec, "query", None, tmp_path, rc, log=lambda m: None)
        C._record_table2_pass(rec, "outside", outside, tmp_path, rc, log=lambda m: None)
    assert calls == ["query", "outside", "query", "outside"]     # the second run reused both; the third redid them
    (tmp_path / "rec" / "outside" / "sequence.json").unlink()    # a stamp without its recording: recorded again
    C._record_table2_pass(rec, "outside", outside, tmp_path, {"v": 2}, log=lambda m: None)
    assert calls[-1] == "outside" and len(calls) == 5


def test_cross_area_protocol_beside_the_database_rows(tmp_path):
    """Table I's cross-area protocol (issue 36): the revisit queries localized with no database from seeded
    priors, single and tracked, in table1.csv and beside the with-database rows on the same queries in
    cross_area.csv; a later run of that protocol alone keeps the other protocols' rows; its localizations are
    reused when nothing changed."""
    from satloc_env.experiments.cross_area import CROSS_COLUMNS
    from satloc_env.experiments.grading import query_priors
    from satloc_env.experiments.tables import table1

    small = {"database_frames": 24, "query_frames": 3, "query_spacing_m": 6.0, "modes": ["go"],
             "compare": {"baselines": []}, "pictures": False, "protocols": ["revisit", "cross-area"],
             "localizers": [str(ROOT / "examples" / "own_localizer.py") + ":GpsOdometryFilter"]}
    rows = table1(tmp_path, ("city",), small, progress=False, log=lambda m: None)
    floors = ["Prior alone", "Dead reckoning", "GPS + odometry filter"]
    assert [(r["protocol"], r["method"]) for r in rows] == (
        [("revisit", m) for m in ["Ours-GO"] + floors]
        + [("cross-area", m) for m in ["No database", "No database + track"] + floors])
    # the same priors in both protocols: the prior alone gives the same row
    same = [{k: r[k] for k in ("mean_m", "median_m", "queries")} for r in rows if r["method"] == "Prior alone"]
    assert same[0] == same[1]
    cross = {r["method"]: r for r in rows if r["protocol"] == "cross-area" and r["method"].startswith("No")}
    revisit = rows[0]
    assert all(r["queries"] == revisit["queries"] == 3 for r in cross.values())
    # a 3-query section at the start of city's look-alike frontage: single frames answer each query (measured
    # at the default world: mean 8.6 m, misses along the road), tracked ones do better (measured: mean 2.4 m,
    # median 1.2 m; on the plain, flat world of earlier releases: mean 6.2 and 0.31 m)
    assert all(r["failure_rate"] == 0 and np.isfinite(r["mean_m"]) for r in cross.values()), cross
    assert cross["No database + track"]["median_m"] < 2.0, cross
    assert cross["No database + track"]["mean_m"] < cross["No database"]["mean_m"], cross
    lines = (tmp_path / "cross_area.csv").read_text().splitlines()
    assert lines[0] == ",".join(CROSS_COLUMNS)
    assert [ln.split(",")[0] for ln in lines[1:]] == ["No database", "No database + track"] + floors + ["Ours-GO"]
    assert [ln.split(",")[3] for ln in lines[1:]] == ["none"] * 5 + ["database pass"]
    assert {ln.split(",")[2] for ln in lines[1:]} == {"a capture of the world"}
    assert "lateral 1 / 3 / 5 m" in (tmp_path / "cross_area.md").read_text()
    assert "the map: a capture of the world" in (tmp_path / "cross_area.md").read_text()
    a, _ = load_npz(tmp_path / "city" / "cross_area" / "localization_cross.npz", "localization")
    # the priors: seeded per query, within the protocol's radius and heading range of the truth
    from satloc_env.experiments.scene_run import ExperimentConfig, covered_queries

    pri = query_priors(ExperimentConfig().cross_area, a["truth"], a["frames"])
    assert np.allclose(a["prior"][:, :2], [[p.x, p.y] for p in pri])
    assert np.all(np.hypot(*(a["prior"][:, :2] - a["truth"][:, :2]).T) <= 20.0)
    # the cross-area protocol alone: the revisit row is kept from table1.json, the localizations reused
    t = {p: p.stat().st_mtime_ns for p in (tmp_path / "city" / "cross_area").glob("localization_cross*.npz")}
    again = table1(tmp_path, ("city",), dict(small, protocols=["cross-area"]), progress=False, log=lambda m: None)
    assert [r["protocol"] for r in again] == ["cross-area"] * 5
    table = json.loads((tmp_path / "table1.json").read_text())["rows"]
    assert [(r["protocol"], r["method"]) for r in table] == [(r["protocol"], r["method"]) for r in rows]
    assert len(t) == 2 and all(p.stat().st_mtime_ns == m for p, m in t.items())


def test_the_cross_area_table_says_what_the_map_is(tmp_path):
    """A scene over an image is seen and mapped from the same image: its rows say so (an upper bound)."""
    from satloc_env.experiments.cross_area import MAP_KINDS, map_kind

    for scene, kind in (("suburb_utm", "image"), ("city", "capture"), ("osm_town", "capture")):
        (tmp_path / scene / "rec").mkdir(parents=True)
        (tmp_path / scene / "rec" / "recording.json").write_text(json.dumps({"config": {"scene": scene}}))
        assert map_kind(tmp_path / scene) == MAP_KINDS[kind], scene
    assert map_kind(tmp_path / "missing") == ""
    # the camera's own parked cars on the image: still the same image, and the rows say the cars are there
    import yaml

    from satloc_env.world.scene import scene_path

    spec = yaml.safe_load(scene_path("suburb_utm").read_text())
    spec["generator"] = {**spec["generator"], "parked_per_km": 54.0,
                         "image": str(scene_path("suburb_utm").parent / spec["generator"]["image"])}
    (tmp_path / "parked.yaml").write_text(yaml.safe_dump(spec))
    (tmp_path / "parked" / "rec").mkdir(parents=True)
    (tmp_path / "parked" / "rec" / "recording.json").write_text(
        json.dumps({"config": {"scene": str(tmp_path / "parked.yaml")}}))
    assert map_kind(tmp_path / "parked") == MAP_KINDS["image_cars"] != MAP_KINDS["image"]


def test_kitti_city_protocol_splits_one_dense_pass(tmp_path):
    """The paper's KITTI-City protocol as it ran it: one pass with a frame every 0.77 m (7.7 m/s, a frame per
    0.1 s step), a seeded random 40 % of it the database and the rest the queries."""
    from satloc_env.experiments.tables import table1

    small = {"database_frames": 24, "query_frames": 3, "query_spacing_m": 6.0, "features": "rgb", "modes": ["go"],
             "compare": {"baselines": []}, "pictures": False, "protocols": ["kitti-city"],
             "kitti_city_length_m": 25.0}
    rows = table1(tmp_path, ("city",), small, progress=False, log=lambda m: None)
    assert [(r["protocol"], r["method"]) for r in rows] == [("kitti-city", m) for m in
                                                           ("Ours-GO", "Prior alone", "Dead reckoning")]
    p = Sequence.load(tmp_path / "city" / "protocol_kitti-city" / "pass")
    gaps = np.hypot(*np.diff(p.poses[:, :2], axis=0).T)
    # a frame at every 0.1 s step at 7.7 m/s, its speed drifting by 10 % (over 25 m the drift's slow start shows)
    assert len(p) == int(np.ceil(25.0 / 0.77)) + 1 and np.allclose(np.diff(p.timestamps), 0.1)
    assert 0.5 < gaps.mean() < 1.0, gaps.mean()
    n_db = round(0.4 * len(p))
    assert rows[0]["queries"] == len(p) - n_db
    build = json.loads((tmp_path / "city" / "protocol_kitti-city" / "build_stage.json").read_text())
    assert len(build["config"]["database_frames"]) == n_db and build["config"]["protocol"] == "kitti-city"
    assert "kitti-city" in (tmp_path / "table1.csv").read_text()


def test_a_query_crossing_the_database_path_is_not_covered():
    """A query within ``coverage_m`` of the database path counts only where a database frame there looks the
    same way (``coverage_yaw_deg``, 45 by default): at an intersection a query pass crossing the database's path
    lies within a few metres of it and sees none of its views (found on city's demo: one query, 206 m off in
    every mode)."""
    from types import SimpleNamespace

    north = np.array([[180.0, y, np.pi / 2] for y in np.arange(100.0, 260.0, 1.6)])   # the database drives north
    q = np.array([[186.0, 180.0, np.pi],            # crossing it westwards, 6 m east of it: too far anyway
                  [181.0, 180.0, np.pi],            # crossing it westwards over its path: not covered
                  [179.0, 150.0, np.pi / 2 + 0.5],   # beside it, 29 degrees off its heading: covered
                  [179.0, 150.0, -np.pi / 2],        # beside it, the other way: not covered
                  [np.nan, np.nan, np.nan]])
    db, qs = SimpleNamespace(poses=north), SimpleNamespace(poses=q)
    assert covered_queries(db, qs, 5.0).tolist() == [1, 2, 3]                  # position only (180: any heading)
    assert covered_queries(db, qs, 5.0, 45.0).tolist() == [2]
    assert covered_queries(db, qs, 5.0, 180.0).tolist() == [1, 2, 3]
    assert ExperimentConfig(scene="city").coverage_yaw_deg == 45.0


def test_curves_give_every_method_its_own_colour_and_a_style_by_kind():
    """The gap and sweep figures draw a sweep's 13 methods and floors in 13 colours (matplotlib's default cycle
    has 10: Ours-NP and the prior alone were both orange), the baselines dashed, the floors dotted."""
    from satloc_env.experiments.tables import _line_styles

    methods = ["Ours-GO", "Ours-NP", "Ours-full", "Ours-full + BEV align", "Ours-GO + track", "Ours-NP + track",
               "Ours-full + track", "Ours-full + track + BEV align", "FAB-MAP", "FAB-MAP + seq", "EFM",
               "Prior alone", "Dead reckoning"]
    st = _line_styles(methods + ["EFM"])        # a method named twice keeps one entry
    assert list(st) == methods
    assert len({tuple(s["color"]) for s in st.values()}) == len(methods)
    assert {m for m, s in st.items() if s["fmt"] == "--"} == {"FAB-MAP", "FAB-MAP + seq", "EFM"}
    assert {m for m, s in st.items() if s["fmt"] == ":"} == {"Prior alone", "Dead reckoning"}
