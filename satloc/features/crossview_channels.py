"""The learned channels of the no-database localizer (:class:`CrossViewProjections`): ``W_g`` on the ground's
bilateral RGB, ``W_s`` on the map's features. Applying them needs numpy alone; reading or writing their ``.pt``
file imports torch (on demand), and :meth:`CrossViewProjections.save_npz` keeps a plain copy that reads without it.
They are learned by :mod:`satloc.features.crossview_learn`."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ConfigError, FormatError
from ..persist import FORMAT_VERSION, ArraySpec, atomic_path, load_npz, save_npz

FORMAT = "crossview_projections"

__all__ = ["CrossViewProjections", "FORMAT"]


@dataclass
class CrossViewProjections:
    """Learned channels: ``W_g`` (k, 3) on the ground's bilateral RGB, ``W_s`` (k, D) on the map's features;
    ``trained_on``: the places (scene names) of the training data; ``curves``: per epoch ``loss``,
    ``val_within_1m``; ``best_epoch`` (0: the untrained projections won)."""

    W_g: np.ndarray
    W_s: np.ndarray
    trained_on: list = field(default_factory=list)
    curves: dict = field(default_factory=dict)
    best_epoch: int = 0

    @staticmethod
    def initial(k: int, d: int, seed: int = 0) -> CrossViewProjections:
        """Channel 0: the grey level on both views (the mean of the RGB, the first 3 of the map's features);
        the others the grey level plus small random weights (seeded)."""
        rng = np.random.default_rng(seed)
        wg = np.zeros((k, 3), np.float32)
        ws = np.zeros((k, d), np.float32)
        wg[:], ws[:, :3] = 1.0 / 3.0, 1.0 / 3.0
        if k > 1:   # the others: the grey level slightly perturbed (the mean over channels starts at the grey level)
            wg[1:] += rng.normal(0, 0.03, (k - 1, 3))
            ws[1:] += rng.normal(0, 0.03, (k - 1, d))
        return CrossViewProjections(wg, ws)

    def ground(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W, k) float32 channels of a bilateral RGB image (H, W, 3)."""
        return np.ascontiguousarray(np.asarray(rgb, np.float32) @ self.W_g.T)

    def satellite(self, features: np.ndarray) -> np.ndarray:
        """(H, W, k) float32 channels of the map's features (H, W, D)."""
        f = np.asarray(features)
        if f.shape[-1] != self.W_s.shape[1]:
            raise ConfigError(f"crossview projections: W_s takes {self.W_s.shape[1]} feature channels, the map has "
                              f"{f.shape[-1]}")
        out = np.empty(f.shape[:2] + (self.W_s.shape[0],), np.float32)
        for r0 in range(0, f.shape[0], 256):   # in row blocks: a float32 copy of a whole map is large
            out[r0:r0 + 256] = f[r0:r0 + 256].astype(np.float32) @ self.W_s.T
        return out

    def save(self, path: str | Path) -> None:
        import torch

        obj = {"format": FORMAT, "version": FORMAT_VERSION, "W_g": torch.from_numpy(np.asarray(self.W_g, np.float32)),
               "W_s": torch.from_numpy(np.asarray(self.W_s, np.float32)), "trained_on": [str(s) for s in self.trained_on],
               "curves": {k: [float(x) for x in v] for k, v in self.curves.items()}, "best_epoch": int(self.best_epoch)}
        with atomic_path(path, suffix=".pt") as tmp:
            torch.save(obj, tmp)

    @staticmethod
    def load(path: str | Path) -> CrossViewProjections:
        import torch

        from .projection import load_torch_dict

        path = Path(path)
        obj = load_torch_dict(path, FORMAT)
        w = {}
        for key, cols in (("W_g", 3), ("W_s", None)):
            t = obj.get(key)
            if (not isinstance(t, torch.Tensor) or t.dtype != torch.float32 or t.dim() != 2 or t.shape[0] < 1
                    or (cols is not None and t.shape[1] != cols) or not bool(torch.isfinite(t).all())):
                raise FormatError(f"{path}: '{key}': expected a finite float32 matrix (k, {cols or 'D'})")
            w[key] = t.numpy().copy()
        if w["W_g"].shape[0] != w["W_s"].shape[0]:
            raise FormatError(f"{path}: W_g has {w['W_g'].shape[0]} channels, W_s {w['W_s'].shape[0]}")
        trained = obj.get("trained_on", [])
        if not isinstance(trained, list) or not all(isinstance(s, str) for s in trained):
            raise FormatError(f"{path}: 'trained_on': expected a list of scene names")
        curves = obj.get("curves", {})
        if not isinstance(curves, dict):
            raise FormatError(f"{path}: 'curves': expected a dict of lists")
        return CrossViewProjections(w["W_g"], w["W_s"], trained, {str(k): list(v) for k, v in curves.items()},
                                    int(obj.get("best_epoch", 0)))


    def save_npz(self, path: str | Path) -> None:
        """The matrices and the record in an npz (plain arrays, no torch to read it back: a cache of a ``.pt``)."""
        save_npz(path, FORMAT, {"W_g": np.asarray(self.W_g, np.float32), "W_s": np.asarray(self.W_s, np.float32)},
                 {"trained_on": [str(s) for s in self.trained_on], "best_epoch": int(self.best_epoch),
                  "curves": {k: [float(x) for x in v] for k, v in self.curves.items()}})

    @staticmethod
    def load_npz(path: str | Path) -> CrossViewProjections:
        """What :meth:`save_npz` wrote; :class:`FormatError` for a damaged or foreign file."""
        a, m = load_npz(path, FORMAT, {"W_g": ArraySpec("f", ("K", 3)), "W_s": ArraySpec("f", ("K", "D"))})
        if not (np.all(np.isfinite(a["W_g"])) and np.all(np.isfinite(a["W_s"]))):
            raise FormatError(f"{path}: the projections are not finite")
        return CrossViewProjections(a["W_g"].astype(np.float32), a["W_s"].astype(np.float32),
                                    list(m.get("trained_on", [])), dict(m.get("curves", {})), int(m.get("best_epoch", 0)))
