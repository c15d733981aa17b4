"""Compare FCN weight files on calibration data: the held-out ground episodes and tile strips of the training
scenes (never an evaluation scene), with the same episode seeds a training run on those scenes draws.

    python docs/tools/fcn_compare.py OUT.json SCENE.yaml [SCENE.yaml ...] --weights A.pt B.pt [--gaps 0.5 0]

Per weights file: the ground view on ``eval_episodes`` held-out episodes of each scene (seeds as
``train_features`` draws them for those scenes with the default ``heldout``), the satellite view on the bottom
``sat_holdout`` strip of each scene's tile captured at each gap; pixel accuracy, mean IoU, boundary F1, and
the same pooled over the scenes.
"""
from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from satloc.features.fcn import FCNPredictor
from satloc_env.experiments.train_features import (
    HELDOUT,
    Metrics,
    TrainConfig,
    _split_tile,
    episode_seeds,
    render_ground,
)
from satloc_env.world.scene import load_scene


def _metrics(pred, view, pairs, pooled):
    m = Metrics()
    for image, labels in pairs:
        out = pred(image, view)
        args = (out.scores.argmax(axis=0), out.edge > 0.0, labels)
        m.add(*args)
        pooled.add(*args)
    return m.summary()


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("out")
    p.add_argument("scenes", nargs="+")
    p.add_argument("--weights", nargs="+", required=True)
    p.add_argument("--gaps", nargs="+", type=float, default=[0.5, 0.0])
    p.add_argument("--lane-offset-m", type=float, default=2.5)
    a = p.parse_args(argv)
    cfg = TrainConfig(lane_offset_m=a.lane_offset_m)
    # the training run's seed draw: its held-out episodes of each training scene
    _, eval_seeds = episode_seeds(np.random.default_rng(cfg.seed), a.scenes, HELDOUT, cfg)
    ground = {s: list(zip(*render_ground(s, 0.0, eval_seeds[s], max(1, cfg.frames_per_episode // 2),
                                         cfg.frame_every * 2, cfg.dt, 1.0, lane_offset_m=cfg.lane_offset_m)))
              for s in a.scenes}
    strips = {}
    for g in a.gaps:
        for s in a.scenes:
            sm = load_scene(s, 0.0, g).satmap
            r = _split_tile(sm.labels, cfg.sat_holdout)
            strips[(g, s)] = (sm.image[r:], sm.labels[r:])
    res = {}
    for w in a.weights:
        pred = FCNPredictor(w)
        out = {"ground": {}, "satellite": {}}
        pooled = Metrics()
        for s, pairs in ground.items():
            out["ground"][s] = _metrics(pred, "ground", pairs, pooled)
        out["ground"]["pooled"] = pooled.summary()
        for g in a.gaps:
            pooled = Metrics()
            for s in a.scenes:
                out["satellite"][f"gap{g:g}:{s}"] = _metrics(pred, "satellite", [strips[(g, s)]], pooled)
            out["satellite"][f"gap{g:g}:pooled"] = pooled.summary()
        res[w] = out
        for k, v in [("ground", out["ground"]["pooled"])] + [(f"sat gap {g:g}", out["satellite"][f"gap{g:g}:pooled"])
                                                            for g in a.gaps]:
            print(f"{w}  {k}: accuracy {v['pixel_accuracy']:.3f}  mean IoU {v['mean_iou']:.3f}  "
                  f"boundary F1 {v['boundary_f1']:.3f}", flush=True)
    with open(a.out, "w") as f:
        json.dump({"scenes": a.scenes, "gaps": a.gaps, "lane_offset_m": a.lane_offset_m, "results": res}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
