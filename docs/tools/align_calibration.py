"""The bird's-eye alignment's settings on a calibration scene: Ours-GO with and without the alignment.

    python docs/tools/align_calibration.py SCENE OUT [KEY=VALUE[,KEY=VALUE...] ...]

SCENE is a scene name or file (a calibration scene: never ``city``, ``residential``, ``loop``, ``loop_calib``
or ``suburb_utm``, whose figures are the tables'); OUT a directory that keeps the recording and the build, so
that a second call with other settings reuses them. Records a database pass of 300 frames 1 m apart and 30
revisit queries 9 m apart on another lane (the revisit protocol's appearance, occluders and change), builds
the dictionary with the shipped features, and localizes every query with Ours-GO alone, then refined at the
default :class:`satloc.tracking.align.AlignConfig`, then at each given variant of it, for example
``channels=edge`` or ``fit_ground=False,shift_penalty=0``. Prints per variant the median and mean error, the
share within 1 m and the share more than 2 m to the side of the truth (a lane over).

The calibration scenes of docs/method.md: ``scenes/fcn_train/town_a.yaml`` with ``generator.variety: 1`` and
``terrain: {relief_m: 1.0, wavelength_m: 250}``, ``town_b`` and ``suburb_a`` with ``generator.variety: 1``.
"""
import dataclasses
import math
import sys
from pathlib import Path

import numpy as np

from satloc import Sequence
from satloc.pipeline import BuildConfig, LocalizerConfig, build, localize
from satloc.tracking.align import AlignConfig
from satloc_env.envs.record import PassConfig, RecordConfig, record_passes


def variant(text: str) -> AlignConfig:
    """``key=value,key=value`` as an AlignConfig: each value read as its field's type."""
    fields = {f.name: f for f in dataclasses.fields(AlignConfig)}
    kw = {}
    for part in text.split(","):
        key, _, value = part.partition("=")
        if key not in fields:
            raise SystemExit(f"{text}: AlignConfig has no field {key!r}")
        default = getattr(AlignConfig(), key)
        kw[key] = value == "True" if isinstance(default, bool) else type(default)(value)
    return AlignConfig(**kw)


def main(argv: list[str]) -> None:
    if len(argv) < 2:
        raise SystemExit(__doc__)
    scene, out = argv[0], Path(argv[1])
    if not (out / "query").exists():
        record_passes(RecordConfig(scene=scene, database=PassConfig(spacing_m=1.0, max_frames=300),
                                   query=PassConfig(lane_offset_m=-0.75, spacing_m=9.0, max_frames=30, seed=1)),
                      out, progress=False)
    if not (out / "build").exists():
        build(out / "database", out / "map", out / "build", BuildConfig(), progress=False)
    truth = np.asarray(Sequence.load(out / "query").poses)
    runs = {"no alignment": None, "default": AlignConfig(), **{a: variant(a) for a in argv[2:]}}
    for i, (name, align) in enumerate(runs.items()):
        cfg = LocalizerConfig(mode="go", refine=align is not None, **({"align": align} if align else {}))
        res = out / f"res{i}"
        r = localize(out / "build", out / "query", cfg, res, progress=False)
        e = np.asarray(r["errors"])
        est = np.load(next(res.glob("localization_*.npz")))["estimates"]
        lateral = np.array([-math.sin(t[2]) * (x[0] - t[0]) + math.cos(t[2]) * (x[1] - t[1])
                            for t, x in zip(truth, est)])
        print(f"{name:40s} median {np.median(e):.2f} m  mean {e.mean():.2f} m  within 1 m {np.mean(e < 1):.0%}  "
              f"a lane over {np.mean(np.abs(lateral) > 2):.0%}", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
