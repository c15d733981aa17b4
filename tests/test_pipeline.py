"""The method's stages end to end on a tiny recorded pass, through the command line."""
import json

import numpy as np
import pytest

from satloc import Sequence
from satloc.pipeline import BuildConfig, build, load_localizer, localize, train_projection
from satloc.localizer import LocalizerConfig
from satloc.projection import ProjectionConfig
from satloc_env.cli import main
from satloc_env.record import PassConfig, RecordConfig, record_passes


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    out = tmp_path_factory.mktemp("rec")
    record_passes(RecordConfig(scene="city", database=PassConfig(spacing_m=1.0, max_frames=25),
                               query=PassConfig(lane_offset_m=-0.75, spacing_m=4.0, max_frames=4, seed=1)),
                  out, progress=False)
    return out


def test_stages_write_reloadable_artefacts(recording, tmp_path):
    b = tmp_path / "build"
    s = build(recording / "database", recording / "map", b, BuildConfig(features="rgb"), progress=False)
    assert s["entries"] > 1000 and (b / "dictionary.npz").is_file() and (b / "satellite_features.npz").is_file()
    p = train_projection(b, ProjectionConfig(max_anchors=3000, max_epochs=3), progress=False)
    assert len(p.loss_curve) <= 3 and (b / "projection_loss.png").stat().st_size > 1000
    res = {}
    for mode in ("go", "np", "full"):
        r = localize(b, recording / "query", LocalizerConfig(mode=mode), out=tmp_path / "res", progress=False)
        res[mode] = r
        assert r["queries"] == 4 and np.all(np.isfinite(r["errors"]))
        assert json.loads((tmp_path / "res" / f"localization_{mode}.json").read_text())["mode"] == mode
    # the localizer reloads from the build directory and gives the same answer
    loc = load_localizer(b, LocalizerConfig(mode="np"))
    f = Sequence.load(recording / "query")[0]
    assert loc.localize(f).estimate == loc.localize(f).estimate


def test_cli_stages(recording, tmp_path, capsys):
    b = str(tmp_path / "b")
    assert main(["build", "--database", str(recording / "database"), "--map", str(recording / "map"),
                 "--out", b, "--features", "rgb", "--quiet"]) == 0
    assert json.loads(capsys.readouterr().out)["entries"] > 1000
    cfg = tmp_path / "p.yaml"
    cfg.write_text("max_anchors: 2000\nmax_epochs: 2\n")
    assert main(["train-projection", b, "--config", str(cfg), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["localize", b, "--queries", str(recording / "query"), "--mode", "full", "--quiet"]) == 0
    assert json.loads(capsys.readouterr().out)["queries"] == 4
    cfg.write_text("max_anchor: 2000\n")
    assert main(["train-projection", b, "--config", str(cfg), "--quiet"]) == 2
    assert "unknown key(s) ['max_anchor']" in capsys.readouterr().err
    assert main(["localize", str(tmp_path / "nope"), "--queries", str(recording / "query"), "--quiet"]) == 2
    assert "build.json: file not found" in capsys.readouterr().err
