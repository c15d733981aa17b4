"""EFM, exhaustive feature matching: the paper's second baseline (Chu et al., Section on experiments).

A ground-image database localizer. Every database frame's LEFT image is described by local features; a query's
features are matched against those of *every* database image, each match set is verified geometrically by
RANSAC, and the database images are weighed by how many matches survive.

* **Features**: SIFT (Lowe), from OpenCV's main package (``cv2.SIFT_create``; free since its patent expired in
  2020, no contrib build needed). At most ``features`` keypoints per image, the strongest by response.
  ``contrast_threshold`` is lowered from OpenCV's 0.04 to 0.005: the rendered 620x188 road scenes of the plain
  world gave few keypoints at 0.04 (about 220 per frame on ``city``; 490 at 0.01, 700 at 0.005 capped at 1000).
  The value was chosen by ``satloc experiment tune`` on the calibration scene ``fcn_train/town_a`` (57 revisit
  queries, drifting passes, no table tests there): at the default world (varied streets over hills, cambered
  roads, the car pitching and rolling) mean error 3.29 / 2.88 / 4.60 / 20.8 m at 0.0025 / 0.005 / 0.01 / 0.04;
  on the plain world of earlier releases 1.61 / 2.86 / 1.65 / 19.6 m, 0.0025 chosen (and before that it had
  been picked on ``city``'s revisit queries, a test scene). ``scale`` resizes the images first (2x, at 0.01, was worse: 5.5 m mean); keypoint coordinates are
  always kept in the original image's pixels. The descriptors are stored as uint8: OpenCV's SIFT descriptors
  are integers in [0, 255] already, so this is lossless.
* **Matching**: each query descriptor's two nearest neighbours *within one database image* (L2), kept when
  nearest < ``ratio`` x second nearest (Lowe's ratio test). ``matcher="bf"`` is exact brute force: the
  database's descriptors are held as float32 blocks (database images in groups of 8 of similar feature
  counts, each group padded to its largest image), so a query costs one matrix product per group plus a
  two-minimum reduction. ``"flann"`` uses one randomised k-d tree forest per database image
  (``cv2.flann_Index``, ``flann_checks`` leaves; approximate: 99.7 % of the ratio-test decisions agree).
  Measured on ``city`` (300 database images of about 700 features, 20 queries of about 630), on the shared
  2-core machine under load: brute force 1.44 s per query, FLANN 3.33 s (plus 1.2 s to build the trees once),
  OpenCV's ``BFMatcher.knnMatch`` image by image 2.40 s; so ``bf`` is the default.
* **Verification**: ``cv2.findHomography`` (``geometry="homography"``, reprojection threshold ``ransac_px`` in
  original pixels) or ``cv2.findFundamentalMat`` (``"fundamental"``, epipolar distance ``ransac_px``), with
  OpenCV's USAC LO-RANSAC (``ransac_method="usac"``, ``cv2.USAC_DEFAULT``) or its plain RANSAC
  (``"ransac"``). Almost every database image keeps a few dozen ratio-test matches (repeated facades and
  zebra crossings), so a query verifies nearly all of them; plain RANSAC runs to its iteration cap on the
  wrong ones and took 3-4.5 s per query on ``city``, USAC 0.05-0.14 s with about the same inlier counts. A
  database image with fewer ratio-test matches than the model needs, or than ``min_inliers``, is not
  verified (it could not reach ``min_inliers`` anyway); this skips work, it does not change a result.
* **Similarity** of database image i: its RANSAC inlier count n_i when n_i >= ``min_inliers``, else 0.
* **Posterior** over the database images: P(i | query) = s_i / sum_j s_j. When no image reaches
  ``min_inliers`` it falls back to the ratio-test match counts (unverified), normalised the same way, and when
  there is no match at all to the uniform distribution.
* **Estimate**: the posterior-weighted mean pose of the top 3 database images
  (:func:`satloc.localizers.database.top_k_estimate`, like every method here); ``candidates`` are the database poses,
  so EFM cannot place a query between lanes: a query pass 1 m beside the database pass has a 1 m error floor.
* **Inside/outside the map**: ``inlier_score`` is the best image's inlier count (0 when none reaches
  ``min_inliers``); ``inlier`` is ``inlier_score >= inlier_threshold``.

The search is exhaustive as in the paper: there is no prefilter (a vocabulary tree or a global descriptor
would be a deviation). A query therefore costs time linear in the database's descriptor count, and the
float32 blocks take about 0.5 kB per database keypoint in memory (150 MB for 300 frames of 1000).

Persistence: ``Efm.save(path)`` writes one npz (format ``efm_database``) through :mod:`satloc.persist`:
``xy`` (N, 2) float32 keypoints, ``desc`` (N, 128) uint8, ``offsets`` (C + 1,) int64 (image i owns rows
offsets[i]:offsets[i+1]), ``poses`` (C, 3) float64, ``frame_index`` (C,) int64 (the database frame each
image came from; frames without a pose are left out), and in the header the config, the camera and the name.
"""
from __future__ import annotations

import dataclasses
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator, Literal

import cv2
import numpy as np
from tqdm import tqdm

from ..config import from_dict, to_dict
from ..errors import ConfigError, FormatError
from ..geometry import StereoCamera
from ..localizers.database import Localization, top_k_estimate
from ..persist import ArraySpec, load_npz, save_npz
from ..sequence import Frame, Sequence

FORMAT = "efm_database"
_GROUP = 8  # database images per padded block of the brute-force matcher
# fields that decide the stored features: a loaded database keeps them, the others may change
_EXTRACTION = ("features", "contrast_threshold", "edge_threshold", "sigma", "scale")


@dataclass(frozen=True)
class EfmConfig:
    features: int = 1000                 # SIFT keypoints kept per image (strongest first); 0: all
    contrast_threshold: float = 0.005    # SIFT contrastThreshold: chosen by `satloc experiment tune` (above)
    edge_threshold: float = 10.0         # SIFT edgeThreshold (OpenCV default)
    sigma: float = 1.6                   # SIFT sigma (OpenCV default)
    scale: float = 1.0                   # resize images by this before SIFT
    ratio: float = 0.75                  # Lowe's ratio test: nearest < ratio * second nearest
    matcher: Literal["bf", "flann"] = "bf"
    flann_checks: int = 64               # "flann": leaves visited per search
    geometry: Literal["homography", "fundamental"] = "homography"
    ransac_px: float = 4.0               # RANSAC threshold, original image pixels
    ransac_method: Literal["usac", "ransac"] = "usac"   # cv2.USAC_DEFAULT (LO-RANSAC) or plain cv2.RANSAC
    ransac_iters: int = 2000
    ransac_confidence: float = 0.995
    min_inliers: int = 12                # a database image with fewer inliers gets similarity 0
    inlier_threshold: float = 50.0       # query declared inside the map when its best inlier count >= this
                                         # (experiments pick it from the PR curve: satloc.evaluation.metrics)
    top_k: int = 3                       # the estimate averages the top-k database poses

    def __post_init__(self):
        checks = [
            ("features", self.features >= 0, ">= 0"),
            ("contrast_threshold", self.contrast_threshold > 0, "> 0"),
            ("edge_threshold", self.edge_threshold > 0, "> 0"),
            ("sigma", self.sigma > 0, "> 0"),
            ("scale", 0 < self.scale <= 4, "in (0, 4]"),
            ("ratio", 0 < self.ratio <= 1, "in (0, 1]"),
            ("matcher", self.matcher in ("bf", "flann"), "'bf' or 'flann'"),
            ("flann_checks", self.flann_checks >= 1, ">= 1"),
            ("geometry", self.geometry in ("homography", "fundamental"), "'homography' or 'fundamental'"),
            ("ransac_px", self.ransac_px > 0, "> 0"),
            ("ransac_method", self.ransac_method in ("usac", "ransac"), "'usac' or 'ransac'"),
            ("ransac_iters", self.ransac_iters >= 1, ">= 1"),
            ("ransac_confidence", 0 < self.ransac_confidence < 1, "in (0, 1)"),
            ("min_inliers", self.min_inliers >= 0, ">= 0"),
            ("top_k", self.top_k >= 1, ">= 1"),
        ]
        for name, ok, want in checks:
            if not ok:
                raise ConfigError(f"{name}: expected {want}, got {getattr(self, name)!r}")

    @property
    def model_points(self) -> int:
        """Correspondences the geometric model needs (4 for a homography, 8 for the fundamental matrix)."""
        return 4 if self.geometry == "homography" else 8


# --- features and pairwise matching ---------------------------------------------------------------------

def _gray(image: np.ndarray, where: str) -> np.ndarray:
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise ConfigError(f"{where}: expected a uint8 RGB (H, W, 3) or grey (H, W) image, got {img.dtype} "
                          f"{img.shape}")
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img


def sift_features(image: np.ndarray, config: EfmConfig = EfmConfig(), where: str = "image"
                  ) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints and descriptors of one image: ``xy`` (n, 2) float32 in the original image's pixels
    (pixel centres at integers) and ``desc`` (n, 128) uint8. At most ``config.features`` keypoints."""
    g = _gray(image, where)
    s = config.scale
    if s != 1.0:
        size = (max(1, round(g.shape[1] * s)), max(1, round(g.shape[0] * s)))
        g = cv2.resize(g, size, interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    sift = cv2.SIFT_create(nfeatures=config.features, contrastThreshold=config.contrast_threshold,
                           edgeThreshold=config.edge_threshold, sigma=config.sigma)
    kps, desc = sift.detectAndCompute(g, None)
    if desc is None or not kps:
        return np.zeros((0, 2), np.float32), np.zeros((0, 128), np.uint8)
    if config.features and len(kps) > config.features:  # OpenCV may keep ties beyond nfeatures
        keep = np.argsort([-k.response for k in kps], kind="stable")[: config.features]
        kps, desc = [kps[i] for i in keep], desc[keep]
    xy = np.array([k.pt for k in kps], np.float64)
    if s != 1.0:  # resized pixel centres back to the original image's
        sx, sy = g.shape[1] / image.shape[1], g.shape[0] / image.shape[0]
        xy = (xy + 0.5) / np.array([sx, sy]) - 0.5
    return xy.astype(np.float32), np.clip(np.rint(desc), 0, 255).astype(np.uint8)


def _verify(src: np.ndarray, dst: np.ndarray, config: EfmConfig) -> tuple[np.ndarray | None, int]:
    """RANSAC model (homography or fundamental matrix) mapping ``src`` to ``dst`` and its inlier count."""
    if len(src) < config.model_points:
        return None, 0
    src, dst = src.astype(np.float32), dst.astype(np.float32)
    usac = config.ransac_method == "usac"
    if config.geometry == "homography":
        M, mask = cv2.findHomography(src, dst, cv2.USAC_DEFAULT if usac else cv2.RANSAC, config.ransac_px,
                                     maxIters=config.ransac_iters, confidence=config.ransac_confidence)
    else:
        M, mask = cv2.findFundamentalMat(src, dst, cv2.USAC_DEFAULT if usac else cv2.FM_RANSAC, config.ransac_px,
                                         config.ransac_confidence, config.ransac_iters)
        if M is not None and M.shape != (3, 3):  # several solutions stacked: keep the first
            M = M[:3]
    if M is None or mask is None:
        return None, 0
    return M, int(mask.sum())


def _ratio_matches(qd: np.ndarray, dd: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Query rows and their database rows passing the ratio test (exact, brute force, one image pair)."""
    if len(dd) < 2 or len(qd) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    q, d = qd.astype(np.float32), dd.astype(np.float32)
    d2 = (d * d).sum(1)[None, :] - 2.0 * (q @ d.T)
    i1 = d2.argmin(1)
    rows = np.arange(len(q))
    m1 = d2[rows, i1].copy()
    d2[rows, i1] = np.inf
    m2 = d2.min(1)
    qn = (q * q).sum(1)
    ok = (m1 + qn) < ratio * ratio * (m2 + qn)
    return rows[ok], i1[ok]


def estimate_homography(image_a: np.ndarray, image_b: np.ndarray, config: EfmConfig = EfmConfig()
                        ) -> tuple[np.ndarray | None, int]:
    """The homography (3x3) taking pixels of ``image_a`` to ``image_b`` and its inlier count, by EFM's own
    pipeline (SIFT, ratio test, RANSAC); ``(None, 0)`` when it cannot be estimated."""
    cfg = dataclasses.replace(config, geometry="homography")
    xa, da = sift_features(image_a, cfg, "image_a")
    xb, db = sift_features(image_b, cfg, "image_b")
    qa, qb = _ratio_matches(da, db, cfg.ratio)
    H, n = _verify(xa[qa], xb[qb], cfg)
    return (None if H is None else H / H[2, 2]), n


# --- the database ----------------------------------------------------------------------------------------

@dataclass
class EfmScores:
    """What one query gives against every database image."""

    inliers: np.ndarray     # (C,) RANSAC inliers per database image (0: not verified)
    matches: np.ndarray     # (C,) ratio-test matches per database image
    num_features: int       # query keypoints


class Efm:
    """Exhaustive feature matching against a database of ground images (see the module docstring)."""

    def __init__(self, config: EfmConfig, poses: np.ndarray, xy: np.ndarray, desc: np.ndarray,
                 offsets: np.ndarray, frame_index: np.ndarray | None = None, camera: StereoCamera | None = None,
                 name: str = ""):
        poses = np.asarray(poses, np.float64)
        offsets = np.asarray(offsets, np.int64)
        if poses.ndim != 2 or poses.shape[1] != 3 or len(poses) == 0:
            raise ConfigError(f"poses: expected (C, 3) with C >= 1, got {poses.shape}")
        if not np.all(np.isfinite(poses)):
            raise ConfigError("poses: every database image needs a finite pose")
        if offsets.shape != (len(poses) + 1,) or offsets[0] != 0 or np.any(np.diff(offsets) < 0):
            raise ConfigError(f"offsets: expected {len(poses) + 1} non-decreasing values from 0, got "
                              f"shape {offsets.shape}")
        n = int(offsets[-1])
        if np.shape(xy) != (n, 2) or np.shape(desc) != (n, 128):
            raise ConfigError(f"xy/desc: expected ({n}, 2) and ({n}, 128), got {np.shape(xy)} and {np.shape(desc)}")
        self.config = config
        self.poses = poses
        self.xy = np.asarray(xy, np.float32)
        self.desc = np.asarray(desc, np.uint8)
        self.offsets = offsets
        self.frame_index = (np.arange(len(poses), dtype=np.int64) if frame_index is None
                            else np.asarray(frame_index, np.int64))
        if self.frame_index.shape != (len(poses),):
            raise ConfigError(f"frame_index: expected ({len(poses)},), got {self.frame_index.shape}")
        self.camera = camera
        self.name = name
        self.counts = np.diff(offsets)
        self._blocks = self._make_blocks()
        self._flann: list | None = None

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def num_features(self) -> int:
        return int(self.offsets[-1])

    # --- building ------------------------------------------------------------------------------------------
    @staticmethod
    def build(database: Sequence, config: EfmConfig = EfmConfig(), progress: bool = True,
              workers: int = 2) -> "Efm":
        """Extract and store the features of every posed database frame's left image (``workers`` threads:
        image decoding and SIFT release the GIL)."""
        if not isinstance(config, EfmConfig):
            raise ConfigError(f"config: expected an EfmConfig, got {type(config).__name__}")
        poses = database.poses
        posed = np.flatnonzero(np.all(np.isfinite(poses), axis=1))
        if len(posed) == 0:
            raise ConfigError(f"database {database.name!r}: no frame has a pose; nothing to localize against")
        cam = database.camera

        def extract(i: int) -> tuple[np.ndarray, np.ndarray]:
            f = database[int(i)]
            return sift_features(f.left, config, f"database {database.name!r} frame {i} left")

        xys, descs = [], []
        bar = tqdm(total=len(posed), desc="EFM features", unit="frame", disable=not progress, leave=False)
        with ThreadPoolExecutor(max(1, workers)) as pool:
            for xy, d in pool.map(extract, posed):
                xys.append(xy)
                descs.append(d)
                bar.update(1)
        bar.close()
        offsets = np.concatenate([[0], np.cumsum([len(d) for d in descs])]).astype(np.int64)
        return Efm(config, poses[posed], np.concatenate(xys), np.concatenate(descs), offsets, posed, cam,
                   database.name)

    def with_config(self, config: EfmConfig) -> "Efm":
        """The same database under another matching/verification configuration (ratio, matcher, RANSAC,
        thresholds). The feature extraction fields must be those the database was built with."""
        changed = [f for f in _EXTRACTION if getattr(config, f) != getattr(self.config, f)]
        if changed:
            raise ConfigError(f"{', '.join(changed)}: the database's features were extracted with "
                              + ", ".join(f"{f}={getattr(self.config, f)!r}" for f in changed)
                              + "; rebuild it to change them")
        return Efm(config, self.poses, self.xy, self.desc, self.offsets, self.frame_index, self.camera, self.name)

    def _make_blocks(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Database images in groups of ``_GROUP`` of similar feature counts, each group padded to its largest
        image (about 1 % padding on city, against 10 % for groups of consecutive images): (image indices,
        descriptors (b, F, 128) float32, squared norms (b, F) with +inf on the padding)."""
        order = np.argsort(self.counts, kind="stable")
        blocks = []
        for s in range(0, len(order), _GROUP):
            idx = order[s:s + _GROUP]
            F = max(int(self.counts[idx].max()), 1)
            P = np.zeros((len(idx), F, 128), np.float32)
            nrm = np.full((len(idx), F), np.inf, np.float32)
            for j, k in enumerate(idx):
                a, b = self.offsets[k], self.offsets[k + 1]
                d = self.desc[a:b].astype(np.float32)
                P[j, : b - a] = d
                nrm[j, : b - a] = (d * d).sum(1)
            blocks.append((idx, P, nrm))
        return blocks

    # --- matching ------------------------------------------------------------------------------------------
    def _match_bf(self, qdesc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(C, m) bool ratio-test pass and (C, m) nearest database row (within the image) per query feature."""
        q = qdesc.astype(np.float32)
        qn = (q * q).sum(1)
        m = len(q)
        ok = np.zeros((len(self), m), bool)
        nearest = np.zeros((len(self), m), np.int64)
        r2 = np.float32(self.config.ratio ** 2)
        for idx, P, nrm in self._blocks:
            b, F = P.shape[:2]
            d2 = P.reshape(b * F, 128) @ q.T                  # (b*F, m)
            d2 *= -2.0
            d2 += nrm.reshape(-1, 1)                           # |d|^2 - 2 d.q: |q|^2 added below
            d2 = d2.reshape(b, F, m)
            i1 = d2.argmin(1)                                  # (b, m)
            m1 = np.take_along_axis(d2, i1[:, None, :], 1)[:, 0]
            np.put_along_axis(d2, i1[:, None, :], np.inf, 1)
            m2 = d2.min(1)
            ok[idx] = (m1 + qn) < r2 * (m2 + qn)              # +inf second neighbour: fewer than 2 features
            nearest[idx] = i1
        ok[self.counts < 2] = False
        return ok, nearest

    def _match_flann(self, qdesc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self._flann is None:
            self._flann = [cv2.flann_Index(self.desc[self.offsets[i]:self.offsets[i + 1]].astype(np.float32),
                                           dict(algorithm=1, trees=4)) if self.counts[i] >= 2 else None
                           for i in range(len(self))]
        q = qdesc.astype(np.float32)
        ok = np.zeros((len(self), len(q)), bool)
        nearest = np.zeros((len(self), len(q)), np.int64)
        r2 = self.config.ratio ** 2
        for i, index in enumerate(self._flann):
            if index is None:
                continue
            idx, dist = index.knnSearch(q, 2, params=dict(checks=self.config.flann_checks))
            ok[i] = dist[:, 0] < r2 * dist[:, 1]       # FLANN's L2 distances are squared
            nearest[i] = idx[:, 0]
        return ok, nearest

    def scores(self, image: np.ndarray, where: str = "query") -> EfmScores:
        """Ratio-test matches and RANSAC inliers of one query image against every database image."""
        qxy, qdesc = sift_features(image, self.config, where)
        C = len(self)
        inliers = np.zeros(C, np.int64)
        if len(qdesc) == 0:
            return EfmScores(inliers, np.zeros(C, np.int64), 0)
        ok, nearest = (self._match_bf if self.config.matcher == "bf" else self._match_flann)(qdesc)
        matches = ok.sum(1)
        need = max(self.config.model_points, self.config.min_inliers)
        for i in np.flatnonzero(matches >= need):
            rows = np.flatnonzero(ok[i])
            dst = self.xy[self.offsets[i] + nearest[i, rows]]
            inliers[i] = _verify(qxy[rows], dst, self.config)[1]
        return EfmScores(inliers, matches.astype(np.int64), len(qdesc))

    def posterior(self, sc: EfmScores) -> np.ndarray:
        """P(database image | query) from the scores (see the module docstring)."""
        s = np.where(sc.inliers >= max(self.config.min_inliers, 1), sc.inliers, 0).astype(np.float64)
        if s.sum() <= 0:
            s = sc.matches.astype(np.float64)
        if s.sum() <= 0:
            return np.full(len(self), 1.0 / len(self))
        return s / s.sum()

    def localize(self, frame: Frame | np.ndarray) -> Localization:
        """Localize one query (a :class:`Frame`, whose left image is used, or an image)."""
        if isinstance(frame, Frame):
            if self.camera is not None:
                frame.check(self.camera, where="query frame")
            image = frame.left
        else:
            image = np.asarray(frame)
            if self.camera is not None and image.shape[:2] != (self.camera.height, self.camera.width):
                raise FormatError(f"query image: expected {self.camera.width}x{self.camera.height} (the "
                                  f"database camera's size), got {image.shape}")
        sc = self.scores(image, "query frame")
        post = self.posterior(sc)
        best = float(sc.inliers.max()) if len(sc.inliers) else 0.0
        if best < self.config.min_inliers:
            best = 0.0
        return Localization(estimate=top_k_estimate(self.poses, post, self.config.top_k),
                            candidates=self.poses, posterior=post, inlier_score=best,
                            inlier=bool(best >= self.config.inlier_threshold and best > 0),
                            num_samples=sc.num_features)

    def localize_stream(self, frames: Iterable[Frame], progress: bool = False, total: int | None = None
                        ) -> Iterator[Localization]:
        """:meth:`localize` for each frame, in order (a progress bar with ``progress``)."""
        for f in tqdm(frames, desc="EFM queries", unit="query", total=total, disable=not progress, leave=False):
            yield self.localize(f)

    # --- persistence ---------------------------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        """Write the database to one npz (atomic; see the module docstring)."""
        save_npz(path, FORMAT, {"xy": self.xy, "desc": self.desc, "offsets": self.offsets, "poses": self.poses,
                                "frame_index": self.frame_index},
                 {"config": to_dict(self.config), "camera": self.camera.to_dict() if self.camera else None,
                  "name": self.name})

    @staticmethod
    def load(path: str | Path, config: EfmConfig | None = None) -> "Efm":
        """Read a database written by :meth:`save`; ``config`` (optional) replaces the matching settings
        (see :meth:`with_config`). A damaged or foreign file raises :class:`FormatError` naming it."""
        path = Path(path)
        arrays, meta = load_npz(path, FORMAT, spec={
            "xy": ArraySpec("f", (None, None)), "desc": ArraySpec("u", (None, None), max=255),
            "offsets": ArraySpec("iu", (None,)), "poses": ArraySpec("f", (None, None)),
            "frame_index": ArraySpec("iu", (None,))})
        if arrays["desc"].dtype != np.uint8:
            raise FormatError(f"{path}: array 'desc': expected uint8 descriptors, got {arrays['desc'].dtype}")
        try:
            cfg = from_dict(EfmConfig, meta.get("config"), f"{path}: config")
            camera = StereoCamera(**meta["camera"]) if meta.get("camera") else None
        except (ConfigError, TypeError, KeyError) as e:
            raise FormatError(f"{path}: bad header field ({e})") from e
        try:
            efm = Efm(cfg, arrays["poses"], arrays["xy"], arrays["desc"], arrays["offsets"], arrays["frame_index"],
                      camera, str(meta.get("name", "")))
        except ConfigError as e:
            raise FormatError(f"{path}: inconsistent arrays ({e})") from e
        return efm.with_config(config) if config is not None else efm

