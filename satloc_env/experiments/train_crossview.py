"""``satloc train-crossview``: learn the cross-view projections (:mod:`satloc.features.crossview_learn`) across places.

For each training scene, a revisit-like pass (another lane, occluders, another appearance and day, the map a
capture at the scene's satellite gap) is recorded into ``out/<scene>/rec`` (reused when there), its frames
turned into training samples, and the projections learned on all of them together. Writes
``out/crossview.pt`` (the projections, with the scenes they were trained on), ``out/train_crossview.json``
(configuration, scenes, frames, curves, the kept epoch) and ``out/learning_curve.png``.

An evaluation scene must never be a training scene: the tables' scenes (``city``, ``residential``, ``loop``,
``loop_calib``) and ``suburb_utm`` are refused unless ``allow_evaluation_scenes``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

from satloc.config import from_dict, to_dict
from satloc.errors import ConfigError
from satloc.features import make_extractor
from satloc.features.crossview_learn import (
    CrossTrainConfig,
    plot_learning_curve,
    samples_from_sequence,
    train_crossview,
)
from satloc.features.dictionary import SatelliteFeatures
from satloc.persist import header, write_json
from satloc.satmap import SatelliteMap
from satloc.sequence import Sequence
from satloc_env.envs.record import QUERY_CHANGE, PassConfig, RecordConfig, record_passes

#: scenes the tables and the cross-area protocol evaluate on: never trained on
EVALUATION_SCENES = ("city", "residential", "loop", "loop_calib", "suburb_utm")
#: the default training places: the FCN's training scenes but town_a (kept for calibration) at the default world
#: (varied streets over hills, cambered roads; until 2026-12-07 the plain fcn_train scenes themselves)
TRAIN_SCENES = ("calib/town_b", "calib/suburb_a", "calib/suburb_b")


@dataclass
class TrainCrossConfig:
    scenes: tuple[str, ...] = TRAIN_SCENES
    frames: int = 120                     # frames per scene's pass
    spacing_m: float = 4.0
    train: CrossTrainConfig = field(default_factory=CrossTrainConfig)
    allow_evaluation_scenes: bool = False

    def __post_init__(self):
        if not self.scenes:
            raise ConfigError("train-crossview: scenes: give at least one training scene")
        bad = [s for s in self.scenes if Path(s).stem in EVALUATION_SCENES]
        if bad and not self.allow_evaluation_scenes:
            raise ConfigError(f"train-crossview: {bad} are evaluation scenes (the tables and the cross-area protocol "
                              f"report on {list(EVALUATION_SCENES)}); train on others")
        if self.frames < 2 or self.spacing_m <= 0:
            raise ConfigError("train-crossview: frames >= 2 and spacing_m > 0")


def _record(scene: str, cfg: TrainCrossConfig, out: Path, progress: bool) -> Path:
    rec = RecordConfig(scene=scene, database=PassConfig(max_frames=2, spacing_m=4.0),
                       query=PassConfig(lane_offset_m=-0.75, spacing_m=cfg.spacing_m, occlusion=0.3, appearance=0.5,
                                        change=QUERY_CHANGE, seed=1, max_frames=cfg.frames))
    d = out / Path(scene).stem / "rec"
    record_passes(rec, d, progress)   # a complete recording of the same configuration is reused
    return d


def train_crossview_scenes(out: str | Path, config: TrainCrossConfig | dict | None = None, progress: bool = True,
                           log=print) -> dict:
    """Record, sample and train (see the module docstring); returns the summary written to
    ``train_crossview.json``."""
    cfg = config if isinstance(config, TrainCrossConfig) else from_dict(TrainCrossConfig, dict(config or {}),
                                                                          "train-crossview config")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    ext = make_extractor("default")
    samples, names, mpp = [], [], None
    for scene in cfg.scenes:
        rec = _record(scene, cfg, out, progress)
        seq, sm = Sequence.load(rec / "query"), SatelliteMap.load(rec / "map")
        if mpp is not None and abs(sm.meters_per_pixel - mpp) > 1e-9:
            raise ConfigError(f"train-crossview: {scene}'s map is {sm.meters_per_pixel} m/px, the others' {mpp}")
        mpp = sm.meters_per_pixel
        s = samples_from_sequence(seq, SatelliteFeatures.compute(sm, ext), search_m=cfg.train.search_m,
                                  progress=progress, config=cfg.train)
        log(f"train-crossview: {scene}: {len(s['index'])} of {len(seq)} frames see enough ground")
        samples.append(s)
        names.append(scene)
    t1 = time.perf_counter()
    proj = train_crossview(samples, cfg.train, names, mpp, progress=progress, log=log)
    proj.save(out / "crossview.pt")
    plot_learning_curve(proj, out / "learning_curve.png")
    summary = dict(header("train_crossview"), config=to_dict(cfg), trained_on=names,
                   frames={n: int(len(s["index"])) for n, s in zip(names, samples)}, best_epoch=proj.best_epoch,
                   curves=proj.curves, record_and_sample_s=round(t1 - t0, 1),
                   train_s=round(time.perf_counter() - t1, 1))
    write_json(out / "train_crossview.json", summary)
    log(f"train-crossview: kept epoch {proj.best_epoch}; written {out / 'crossview.pt'}")
    return summary
