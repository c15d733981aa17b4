"""Learned cross-view projections (satloc.features.crossview_learn, issue 36): the correlation surfaces training
differentiates are OpenCV's masked NCC, training lowers the loss on a few frames, files round-trip and damaged
ones are refused, the shipped projections were trained on scenes disjoint from every evaluation scene, and
`satloc train-crossview` refuses an evaluation scene."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from satloc import ConfigError, FormatError, Sequence
from satloc.features import make_extractor
from satloc.features.crossview_learn import (
    CrossTrainConfig,
    CrossViewProjections,
    samples_from_sequence,
    surfaces,
    train_crossview,
)
from satloc.features.dictionary import SatelliteFeatures
from satloc.localizers.crossview import SHIPPED_PROJECTIONS, CrossViewConfig, CrossViewLocalizer, draw_prior
from satloc.satmap import SatelliteMap
from satloc_env.envs.record import PassConfig, RecordConfig, record_passes


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    out = tmp_path_factory.mktemp("rec")
    record_passes(RecordConfig(scene="residential", database=PassConfig(spacing_m=4.0, max_frames=2),
                               query=PassConfig(lane_offset_m=-0.75, spacing_m=6.0, max_frames=10, seed=1)),
                  out, progress=False)
    seq, sm = Sequence.load(out / "query"), SatelliteMap.load(out / "map")
    sf = SatelliteFeatures.compute(sm, make_extractor("default"))
    cfg = CrossTrainConfig(far=3, epochs=2, batch_size=4, val_frac=0.3, val_block=2)
    return seq, sm, sf, samples_from_sequence(seq, sf, config=cfg), cfg


def test_surfaces_are_what_the_localizer_computes(data):
    """Training's surfaces (torch, differentiable) against the localizer's: satloc.tracking.align's normalisation of the
    BEV and of the whole map, the map resampled at the pose, cv2's masked TM_CCOEFF_NORMED."""
    from satloc.features import BilateralRGB
    from satloc.features.dictionary import FrameDepth
    from satloc.tracking.align import BevAligner

    seq, sm, sf, s, cfg = data
    assert s["ground"].shape[1] == 3 and s["sat"].shape[1] == sf.dim and s["far"].shape[1] == 3
    b = 2
    i = int(s["index"][b])
    al = BevAligner(seq.camera, sf.features, sf.meters_per_pixel, sf.origin).with_search(cfg.search_m)
    chans, mask = al.bev(BilateralRGB()(seq[i].left, "ground"), FrameDepth(seq.camera)(seq[i], "q"))
    ref = cv2.matchTemplate(al._crop(seq[i].pose)[0], chans[0], cv2.TM_CCOEFF_NORMED, mask=mask)
    p = CrossViewProjections.initial(1, sf.dim)   # one channel: the grey level, as the localizer's default
    g, m, st = (torch.tensor(s[k][b:b + 1]) for k in ("ground", "mask", "sat"))
    r = surfaces((torch.tensor(p.W_g), torch.tensor(p.W_s)), g, m, st, 1.0 / sm.meters_per_pixel)[0].numpy()
    assert np.array_equal(m[0].numpy().astype(bool), mask.astype(bool))
    # the same surface up to the order of resampling and normalising the map, and float16 storage (measured:
    # at most 0.003 apart)
    assert r.shape == ref.shape and np.abs(r - ref).max() < 0.02, np.abs(r - ref).max()
    assert np.unravel_index(int(r.argmax()), r.shape) == np.unravel_index(int(ref.argmax()), ref.shape)
    c = r.shape[0] // 2   # the truth, at the centre, near the peak
    i0, j0 = np.unravel_index(int(r.argmax()), r.shape)
    assert max(abs(i0 - c), abs(j0 - c)) * sm.meters_per_pixel <= 1.0



def test_samples_see_the_ground_where_the_localizer_does(data):
    """Training's BEV mask is the localizer's, on the mounting's plane or on the plane ``fit_ground`` fits to the
    stereo depth (it was always the mounting's)."""
    from satloc.features import BilateralRGB
    from satloc.features.dictionary import FrameDepth
    from satloc.tracking.align import AlignConfig, BevAligner

    seq, sm, sf, s, cfg = data
    frames = [int(i) for i in s["index"][:3]]
    for fit in (False, True):
        align = AlignConfig(fit_ground=fit)
        smp = samples_from_sequence(seq, sf, frames=frames, align=align, config=cfg)
        al = BevAligner(seq.camera, sf.features, sf.meters_per_pixel, sf.origin, align).with_search(cfg.search_m)
        for k, i in enumerate(smp["index"]):
            _, mask = al.bev(BilateralRGB()(seq[int(i)].left, "ground"), FrameDepth(seq.camera)(seq[int(i)], "q"))
            assert np.array_equal(smp["mask"][k].astype(bool), mask.astype(bool)), (fit, int(i))

def test_training_lowers_the_loss_and_round_trips(data, tmp_path):
    seq, sm, sf, s, cfg = data
    p = train_crossview([s], cfg, ["residential (test only)"], sm.meters_per_pixel, progress=False, log=lambda m: None)
    c = p.curves
    assert len(c["loss"]) == 3 and c["loss"][2] < c["loss"][1] and 0 <= p.best_epoch <= 2
    assert p.W_g.shape == (3, 3) and p.W_s.shape == (3, sf.dim)
    p.save(tmp_path / "cv.pt")
    q = CrossViewProjections.load(tmp_path / "cv.pt")
    assert np.array_equal(q.W_g, p.W_g) and np.array_equal(q.W_s, p.W_s) and q.trained_on == p.trained_on
    # the localizer with them: the learned channels of the bilateral RGB against the map's
    cv = CrossViewLocalizer(seq.camera, sf, make_extractor("default"),
                            CrossViewConfig(projections=str(tmp_path / "cv.pt")), labels=sm.labels)
    t = seq[3].pose
    r = cv.localize(seq[3], draw_prior(t, 10.0, 5.0, np.random.default_rng(0)))
    assert r.pose is not None and r.cells > 400
    # damaged files: a clear error naming the file
    (tmp_path / "bad.pt").write_bytes(b"not a torch file")
    with pytest.raises(FormatError, match="bad.pt"):
        CrossViewProjections.load(tmp_path / "bad.pt")
    torch.save({"format": "crossview_projections", "version": 1, "W_g": torch.zeros(2, 4), "W_s": torch.zeros(2, 3)},
               tmp_path / "shape.pt")
    with pytest.raises(FormatError, match="W_g"):
        CrossViewProjections.load(tmp_path / "shape.pt")
    with pytest.raises(ConfigError, match="W_s takes"):
        CrossViewProjections(p.W_g, p.W_s[:, :5]).satellite(sf.features[:4, :4])


def test_shipped_projections_were_trained_elsewhere():
    from satloc_env.experiments.train_crossview import EVALUATION_SCENES, TrainCrossConfig

    p = CrossViewProjections.load(SHIPPED_PROJECTIONS)
    assert p.trained_on and not {Path(s).stem for s in p.trained_on} & set(EVALUATION_SCENES)
    report = json.loads((Path(SHIPPED_PROJECTIONS).parent / "crossview_report.json").read_text())
    assert report["trained_on"] == p.trained_on and report["best_epoch"] == p.best_epoch
    with pytest.raises(ConfigError, match="evaluation scenes"):
        TrainCrossConfig(scenes=("fcn_train/town_b", "city"))
    assert TrainCrossConfig(scenes=("city",), allow_evaluation_scenes=True).scenes == ("city",)


def test_cli_refuses_an_evaluation_scene(tmp_path, capsys):
    from satloc_env.cli import main

    assert main(["train-crossview", "--scenes", "suburb_utm", "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "evaluation scenes" in capsys.readouterr().err
