"""FAB-MAP (Cummins and Newman, "FAB-MAP: Probabilistic Localization and Mapping in the Space of Appearance",
IJRR 27(6), 2008), the appearance-only baseline of Chu et al.'s Table I: database images are the places.

The model, as published (the equations are those of the paper's sections 3-4; where this implementation
chooses among the paper's options it says so):

* **Observations.** Local features of the LEFT image are quantised into a visual vocabulary; an observation
  is the binary vector Z = (z_1 ... z_V), z_q = 1 when word q occurs in the image. The paper used SURF, which
  is not in OpenCV's free builds: this implementation uses SIFT (``cv2.SIFT_create``). The vocabulary is
  k-means over descriptors of training images (faiss), words by nearest centre.
* **Chow-Liu tree.** The joint distribution of the z_q is approximated by the maximum-weight spanning tree of
  the pairwise mutual information of the binary occurrence variables (Chow and Liu 1968), learned from
  training images that must be disjoint from the test images; rooted, with the conditional tables
  p(z_q = 1 | z_parent = 0/1) and the marginals p(z_q = 1) (additive ``pseudo_count`` smoothing). The tree is
  found by Prim's algorithm with mutual-information rows computed on demand from the sparse occurrences, so
  memory stays linear in the vocabulary.
* **Detector model.** Hidden existence variables e_q with p(z_q = 1 | e_q = 1) = ``p_detect`` and
  p(z_q = 1 | e_q = 0) = ``p_false``; defaults 0.39 and 0.005, the published detector model (openFABMAP's
  sample settings ship 0.39 and 0).
* **Place appearance models.** A place L_j is learned from its single database observation:
  p(e_q = 1 | L_j) = p(z_q^j | e_q = 1) p(e_q = 1) / sum_s p(z_q^j | e_q = s) p(e_q = s), with the prior
  p(e_q = 1) taken as the training marginal p(z_q = 1) (the approximation openFABMAP makes too).
* **Observation likelihood** through the tree:
  p(Z | L_j) = p(z_r | L_j) prod_q p(z_q | z_pq, L_j),
  p(z_q | z_pq, L_j) = sum_s p(z_q | e_q = s, z_pq) p(e_q = s | L_j), and
  p(z_q | e_q, z_pq) = (1 + a / b)^-1, a = p(z_q') p(~z_q | e_q) p(~z_q | z_pq), b = p(~z_q') p(z_q | e_q) p(z_q | z_pq)
  where z_q' is z_q's value and ~ its negation (paper's eq. for the Chow-Liu factor; it follows from
  p(z_q | e_q, z_p) proportional to p(z_q | e_q) p(z_q | z_p) / p(z_q)). Because p(e_q | L_j) depends only on
  the place's own z_q^j, log p(Z | L_j) = c(Z) + sum_q z_q^j d_q(Z) exactly: one sparse product scores every
  place (the same identity FAB-MAP 2.0 builds its inverted index on; no approximation is made here).
* **New place.** ``new_place="sampled"`` (the paper's preferred one): p(Z | L_new) is the mean of p(Z | L_u)
  over place models L_u built from ``new_place_samples`` training images; ``"mean_field"``: one "average
  place" whose p(e_q = 1) is the training marginal.
* **Bayesian update.** p(L | Z) proportional to p(Z | L) p(L), over the places and the new place, in log
  space, then smoothed as in the paper: p <- ``smoothing`` * p + (1 - ``smoothing``) / (n + 1). Prior: the
  new place gets ``new_place_prior`` and the places share the rest, uniformly for a single query
  (:meth:`FabMap.localize`); with ``sequential`` (:meth:`FabMap.localize_stream`) the places' share follows
  the paper's simple motion model: the previous posterior moved to the places within ``motion_window``
  database indices (adjacent places; the previous new-place mass spread over all places).

Output per query: a :class:`satloc.localizers.database.Localization` whose ``candidates`` are the database poses,
``posterior`` the place posterior without the new place, renormalised (p(L_j | Z, at a place), smoothed over
the places the same way; so it does not depend on the new-place model), ``estimate`` its top-3 weighted pose
(:func:`satloc.localizers.database.top_k_estimate`), ``inlier_score`` = 1 - p(new place | Z) (the probability that
the query was taken at one of the database places), ``inlier`` = inlier_score >= ``inlier_threshold`` and
``num_samples`` the number of local features of the query.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator, Literal, Union

import cv2
import numpy as np
import scipy.sparse as sp
from scipy.special import logsumexp
from tqdm import tqdm

from ..config import from_dict, to_dict
from ..errors import ConfigError, FormatError
from ..localizers.database import Localization, top_k_estimate
from ..persist import load_npz, save_npz
from ..sequence import Frame, Sequence

FORMAT = "fabmap"
_EPS = 1e-9
Image = Union[Frame, np.ndarray]


@dataclass(frozen=True)
class FabMapConfig:
    """FAB-MAP's knobs: the build (features, vocabulary, tree) and the inference (detector, new place, prior)."""

    # vocabulary_size and contrast_threshold: chosen by `satloc experiment tune` on fcn_train/town_a (trained on
    # town_b; no table tests there), mean error of 57 revisit queries. At the default world (varied streets over
    # hills, cambered roads, the car pitching and rolling; commit 7e1994c): words 500 / 1000 / 2000 / 5000 at
    # 0.005: 77.5 / 41.5 / 10.95 / 7.06 m; then contrast 0.005 / 0.01 / 0.04 at 5000 words: 7.06 / 8.76 / 12.3 m.
    # (On the plain world of earlier releases: 80.5 / 51.2 / 4.46 / 4.53 m, 2000 words chosen.)
    vocabulary_size: int = 5000           # k-means words
    max_features: int = 1000              # SIFT keypoints kept per image (strongest)
    contrast_threshold: float = 0.005     # SIFT's (OpenCV's default 0.04 finds ~180 features a rendered frame)
    image_scale: float = 1.0              # the left image is resized by this before feature extraction
    kmeans_iterations: int = 20
    max_train_descriptors: int = 300_000  # descriptors sampled for k-means
    pseudo_count: float = 1.0             # additive smoothing of the tree's marginals and conditionals
    p_detect: float = 0.39                # p(z = 1 | e = 1), the paper's detector model
    p_false: float = 0.005                # p(z = 1 | e = 0)
    new_place: Literal["sampled", "mean_field"] = "sampled"
    new_place_samples: int = 1000         # training images sampled as new-place models (at most all of them)
    new_place_prior: float = 0.9          # prior of the new place (openFABMAP's Pnew); the places share the rest
    smoothing: float = 0.99               # the paper's posterior smoothing sigma (1: none)
    sequential: bool = False              # localize_stream: the motion-model prior instead of a uniform one
    motion_window: int = 1                # sequential: places within this many database indices are adjacent
    top_k: int = 3                        # the estimate averages the top-k places
    inlier_threshold: float = 0.5         # inlier when 1 - p(new place) reaches this
    seed: int = 0

    def __post_init__(self):
        def need(ok: bool, name: str, what: str) -> None:
            if not ok:
                raise ConfigError(f"{name}: expected {what}, got {getattr(self, name)!r}")

        need(self.vocabulary_size >= 2, "vocabulary_size", "an integer >= 2")
        need(self.max_features >= 1, "max_features", "an integer >= 1")
        need(self.contrast_threshold > 0, "contrast_threshold", "a number > 0")
        need(0 < self.image_scale <= 4, "image_scale", "a number in (0, 4]")
        need(self.kmeans_iterations >= 1, "kmeans_iterations", "an integer >= 1")
        need(self.max_train_descriptors >= self.vocabulary_size, "max_train_descriptors",
             f"an integer >= vocabulary_size ({self.vocabulary_size})")
        need(self.pseudo_count >= 0, "pseudo_count", "a number >= 0")
        need(0 < self.p_detect < 1, "p_detect", "a probability in (0, 1)")
        need(0 <= self.p_false < self.p_detect, "p_false", f"a probability in [0, p_detect={self.p_detect})")
        need(self.new_place in ("sampled", "mean_field"), "new_place", "'sampled' or 'mean_field'")
        need(self.new_place_samples >= 1, "new_place_samples", "an integer >= 1")
        need(0 < self.new_place_prior < 1, "new_place_prior", "a probability in (0, 1)")
        need(0 < self.smoothing <= 1, "smoothing", "a number in (0, 1]")
        need(self.motion_window >= 0, "motion_window", "an integer >= 0")
        need(self.top_k >= 1, "top_k", "an integer >= 1")
        need(0 <= self.inlier_threshold <= 1, "inlier_threshold", "a probability in [0, 1]")


# --- Chow-Liu tree ---------------------------------------------------------------------------------------------

@dataclass
class ChowLiuTree:
    """A rooted Chow-Liu tree over binary word occurrences.

    ``parent[q]``: q's parent word (-1 at the root); ``marginal[q]`` = p(z_q = 1); ``cond[q, s]`` =
    p(z_q = 1 | z_parent = s) (the root's rows hold its marginal); ``mutual_information[q]``: of the edge
    (q, parent[q]) (0 at the root)."""

    parent: np.ndarray
    marginal: np.ndarray
    cond: np.ndarray
    mutual_information: np.ndarray

    @property
    def root(self) -> int:
        return int(np.flatnonzero(self.parent < 0)[0])

    def edges(self) -> set[tuple[int, int]]:
        """Undirected edges as (min, max) pairs."""
        return {(min(q, int(p)), max(q, int(p))) for q, p in enumerate(self.parent) if p >= 0}

    def __len__(self) -> int:
        return len(self.parent)


def _as_occurrences(occ: np.ndarray | sp.spmatrix) -> sp.csr_matrix:
    m = sp.csr_matrix(occ, dtype=np.float32)
    m.data[:] = 1.0
    m.eliminate_zeros()
    return m


def _mi_row(c: np.ndarray, nj: float, n: np.ndarray, total: float) -> np.ndarray:
    """Mutual information (nats) of the empirical joint of word j with every word, from co-occurrence counts
    ``c`` (V,), j's count ``nj``, the counts ``n`` (V,) and the number of images ``total``."""
    out = np.zeros(len(n))
    cells = ((c, nj, n), (nj - c, nj, total - n), (n - c, total - nj, n), (total - nj - n + c, total - nj, total - n))
    for cnt, na, nb in cells:              # each cell of the 2x2 joint: its count and the two marginal counts
        with np.errstate(divide="ignore", invalid="ignore"):
            term = (cnt / total) * np.log(cnt * total / (na * nb))
        out += np.where(cnt > 0, term, 0.0)
    return np.maximum(out, 0.0)


def chow_liu_tree(occurrences: np.ndarray | sp.spmatrix, pseudo_count: float = 1.0, root: int | None = None,
                  progress: bool = False) -> ChowLiuTree:
    """The Chow-Liu tree of binary occurrences (N images, V words): the maximum spanning tree of the pairwise
    mutual information of the empirical distribution (Prim's algorithm, rows computed on demand), rooted at
    ``root`` (default: the most frequent word), with conditionals smoothed by ``pseudo_count``."""
    z = _as_occurrences(occurrences)
    total, v = z.shape
    if total < 2 or v < 2:
        raise ConfigError(f"chow_liu_tree: expected at least 2 images and 2 words, got {total} x {v}")
    if pseudo_count < 0:
        raise ConfigError(f"chow_liu_tree: pseudo_count must be >= 0, got {pseudo_count}")
    zc = z.tocsc()
    n = np.asarray(z.sum(axis=0)).ravel().astype(np.float64)
    root = int(np.argmax(n)) if root is None else int(root)
    if not 0 <= root < v:
        raise ConfigError(f"chow_liu_tree: root {root} is not a word of a vocabulary of {v}")

    def cooc(j: int) -> np.ndarray:
        rows = zc.indices[zc.indptr[j]:zc.indptr[j + 1]]
        return np.asarray(z[rows].sum(axis=0)).ravel().astype(np.float64) if len(rows) else np.zeros(v)

    in_tree = np.zeros(v, bool)
    parent = np.full(v, -1, np.int64)
    best = np.full(v, -np.inf)
    best_c = np.zeros(v)           # co-occurrence count with the current best parent
    bar = tqdm(total=v, desc="Chow-Liu tree", unit="word", disable=not progress, leave=False)
    j = root
    for _ in range(v):
        in_tree[j] = True
        bar.update(1)
        c = cooc(j)
        mi = _mi_row(c, n[j], n, total)
        better = ~in_tree & (mi > best)
        best[better], parent[better], best_c[better] = mi[better], j, c[better]
        if in_tree.all():
            break
        j = int(np.argmax(np.where(in_tree, -np.inf, best)))
    bar.close()
    parent[root] = -1
    a = float(pseudo_count)
    marginal = (n + a) / (total + 2 * a) if total + 2 * a > 0 else n / total
    cond = np.empty((v, 2))
    has = parent >= 0
    p = parent[has]
    c11 = best_c[has]
    with np.errstate(divide="ignore", invalid="ignore"):
        cond[has, 1] = (c11 + a) / (n[p] + 2 * a)
        cond[has, 0] = (n[has] - c11 + a) / (total - n[p] + 2 * a)
    cond[~has] = marginal[~has, None]
    cond = np.nan_to_num(cond, nan=0.5)
    mi = np.where(has, best, 0.0)
    return ChowLiuTree(parent, np.clip(marginal, _EPS, 1 - _EPS), np.clip(cond, _EPS, 1 - _EPS), mi)


# --- the observation model -------------------------------------------------------------------------------------

def _place_existence(marginal: np.ndarray, p_detect: float, p_false: float) -> np.ndarray:
    """(V, 2): p(e_q = 1 | L) for a place whose single observation has z_q = 0 (column 0) or 1 (column 1)."""
    pe = marginal
    out = np.empty((len(pe), 2))
    for lz, (pd, pf) in enumerate(((1 - p_detect, 1 - p_false), (p_detect, p_false))):
        num = pd * pe
        out[:, lz] = num / (num + pf * (1 - pe))
    return out


def observation_tables(tree: ChowLiuTree, p_detect: float, p_false: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-word factors of p(Z | L) through the tree.

    Returns ``place`` (V, 2, 2, 2) = p(z_q | z_pq, L) indexed [z_q, z_pq, z_q of the place's observation] and
    ``mean_field`` (V, 2, 2) = p(z_q | z_pq, L_avg) indexed [z_q, z_pq], the "average place" whose
    p(e_q = 1) is the marginal. For the root, z_pq is ignored."""
    v = len(tree)
    m = tree.marginal
    det = np.array([[1 - p_false, 1 - p_detect], [p_false, p_detect]])    # det[z, e] = p(z | e)
    pz = np.stack([1 - m, m], axis=1)                                         # pz[q, z]
    pzp = np.stack([1 - tree.cond, tree.cond], axis=1)                        # pzp[q, z, zp] = p(z_q=z | z_p=zp)
    # p(z_q = z | e_q = e, z_p = zp) = b / (a + b), a = p(z) p(~z | e) p(~z | zp), b = p(~z) p(z | e) p(z | zp)
    pz_e_zp = np.empty((v, 2, 2, 2))                                          # [q, z, e, zp]
    for z in (0, 1):
        for e in (0, 1):
            a = pz[:, z, None] * det[1 - z, e] * pzp[:, 1 - z, :]
            b = pz[:, 1 - z, None] * det[z, e] * pzp[:, z, :]
            pz_e_zp[:, z, e, :] = b / (a + b)
    root = tree.parent < 0
    pz_e_zp[root] = det[None, :, :, None]                                     # the root: p(z | e) alone
    pe = _place_existence(m, p_detect, p_false)                               # [q, lz] = p(e=1 | L)
    place = np.empty((v, 2, 2, 2))
    for lz in (0, 1):
        w1 = pe[:, lz][:, None, None]
        place[:, :, :, lz] = (1 - w1) * pz_e_zp[:, :, 0, :] + w1 * pz_e_zp[:, :, 1, :]
    mf = (1 - m)[:, None, None] * pz_e_zp[:, :, 0, :] + m[:, None, None] * pz_e_zp[:, :, 1, :]
    return place, mf


def motion_prior(belief: np.ndarray, window: int) -> np.ndarray:
    """The places' prior (n,) for the next frame from the previous posterior ``belief`` (n places, then the new
    place), the paper's simple motion model in database order: each place's mass moves in equal parts to the
    places within ``window`` indices of it that exist; the new-place mass spreads over all places."""
    b = np.asarray(belief, np.float64)
    n = len(b) - 1
    if n < 1 or window < 0:
        raise ConfigError(f"motion_prior: expected a belief over >= 1 place and the new place and a window >= 0, "
                          f"got {len(b)} values and window {window}")
    i = np.arange(n)
    lo, hi = np.maximum(i - window, 0), np.minimum(i + window, n - 1)
    share = b[:n] / (hi - lo + 1)                  # what place j sends to each of its targets
    cs = np.concatenate([[0.0], np.cumsum(share)])
    prior = cs[hi + 1] - cs[lo] + b[n] / n         # place i receives from every j with |i - j| <= window
    return prior / prior.sum()


# --- features and vocabulary ----------------------------------------------------------------------------------

def _gray(image: Image, where: str) -> np.ndarray:
    img = image.left if isinstance(image, Frame) else image
    if not isinstance(img, np.ndarray) or img.dtype != np.uint8 or not (
            img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)):
        got = f"{img.dtype} {img.shape}" if isinstance(img, np.ndarray) else type(img).__name__
        raise ConfigError(f"{where}: expected a Frame or an RGB (H, W, 3) / grey (H, W) uint8 image, got {got}")
    if img.shape[0] < 16 or img.shape[1] < 16:
        raise ConfigError(f"{where}: image of {img.shape[1]}x{img.shape[0]} is too small for local features")
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img


# --- FAB-MAP ------------------------------------------------------------------------------------------------------

class FabMap:
    """FAB-MAP over a database of places (see the module docstring). Build with :meth:`train`, then
    :meth:`add_places`; :meth:`localize` one image, :meth:`localize_stream` a sequence."""

    def __init__(self, config: FabMapConfig, centres: np.ndarray, tree: ChowLiuTree,
                 training: sp.csr_matrix):
        centres = np.ascontiguousarray(centres, np.float32)
        if centres.ndim != 2 or centres.shape[0] != len(tree) or centres.shape[1] != 128:
            raise ConfigError(f"FabMap: expected (V, 128) word centres for a tree of {len(tree)} words, "
                              f"got {centres.shape}")
        if training.shape[1] != len(tree) or training.shape[0] < 1:
            raise ConfigError(f"FabMap: expected training occurrences (N >= 1, {len(tree)}), got {training.shape}")
        self.config = config
        self.centres = centres
        self.tree = tree
        self.training = _as_occurrences(training)
        self._index = None
        self._sift = None
        self.place_poses = np.zeros((0, 3))
        self.places = sp.csr_matrix((0, len(tree)), dtype=np.float32)
        self._belief: np.ndarray | None = None
        self._prepare()

    # --- construction ---------------------------------------------------------------------------------------------
    def _prepare(self) -> None:
        c = self.config
        place, mf = observation_tables(self.tree, c.p_detect, c.p_false)
        self._log_place = np.log(np.maximum(place, 1e-300))
        self._log_mf = np.log(np.maximum(mf, 1e-300))
        n = self.training.shape[0]
        rng = np.random.default_rng(c.seed)
        pick = np.sort(rng.choice(n, size=min(n, c.new_place_samples), replace=False))
        self._samples = self.training[pick]

    @property
    def vocabulary_size(self) -> int:
        return len(self.tree)

    @property
    def num_places(self) -> int:
        return self.places.shape[0]

    @staticmethod
    def train(images: Iterable[Image] | Sequence, config: FabMapConfig = FabMapConfig(),
              progress: bool = True) -> "FabMap":
        """Learn the vocabulary (k-means of SIFT descriptors) and the Chow-Liu tree from training images
        (Frames: their left image; or RGB / grey uint8 arrays), which must be disjoint from the test images."""
        import faiss

        dummy = FabMap.__new__(FabMap)
        dummy.config = config
        dummy._sift = None
        descs: list[np.ndarray] = []
        seq = images if isinstance(images, Sequence) else None
        items = range(len(seq)) if seq is not None else images
        for i, item in enumerate(tqdm(items, desc="FAB-MAP features", unit="image", disable=not progress,
                                      leave=False, total=len(seq) if seq is not None else None)):
            img = seq[item] if seq is not None else item
            descs.append(dummy._descriptors(img, f"training image {i}"))
        counts = np.array([len(d) for d in descs])
        if len(descs) < 2:
            raise ConfigError(f"FabMap.train: expected at least 2 training images, got {len(descs)}")
        total = int(counts.sum())
        if total < config.vocabulary_size:
            raise ConfigError(f"FabMap.train: {total} descriptors in {len(descs)} training images, fewer than "
                              f"vocabulary_size={config.vocabulary_size}; give more images or a smaller vocabulary")
        allx = np.concatenate(descs).astype(np.float32)
        rng = np.random.default_rng(config.seed)
        x = allx[rng.choice(total, config.max_train_descriptors, replace=False)] \
            if total > config.max_train_descriptors else allx
        km = faiss.Kmeans(128, config.vocabulary_size, niter=config.kmeans_iterations, seed=config.seed,
                          verbose=False, max_points_per_centroid=max(256, len(x) // config.vocabulary_size + 1))
        km.train(np.ascontiguousarray(x))
        centres = np.asarray(km.centroids, np.float32).reshape(config.vocabulary_size, 128)
        index = faiss.IndexFlatL2(128)
        index.add(centres)
        _, words = index.search(allx, 1)
        rows = np.repeat(np.arange(len(descs)), counts)
        occ = sp.csr_matrix((np.ones(total, np.float32), (rows, words[:, 0])),
                            shape=(len(descs), config.vocabulary_size))
        occ.sum_duplicates()
        tree = chow_liu_tree(occ, config.pseudo_count, progress=progress)
        fm = FabMap(config, centres, tree, occ)
        fm._index = index
        return fm

    def _descriptors(self, image: Image, where: str) -> np.ndarray:
        g = _gray(image, where)
        c = self.config
        if c.image_scale != 1.0:
            g = cv2.resize(g, None, fx=c.image_scale, fy=c.image_scale,
                           interpolation=cv2.INTER_AREA if c.image_scale < 1 else cv2.INTER_LINEAR)
        if self._sift is None:
            self._sift = cv2.SIFT_create(nfeatures=c.max_features, contrastThreshold=c.contrast_threshold)
        _, d = self._sift.detectAndCompute(g, None)
        d = np.zeros((0, 128), np.float32) if d is None else d[: c.max_features]
        return d.astype(np.float32)

    def observe(self, image: Image, where: str = "query") -> tuple[np.ndarray, int]:
        """The binary word-occurrence vector (V,) of an image's left view and its number of features."""
        d = self._descriptors(image, where)
        z = np.zeros(self.vocabulary_size, bool)
        if len(d):
            if self._index is None:
                import faiss
                self._index = faiss.IndexFlatL2(128)
                self._index.add(self.centres)
            _, w = self._index.search(np.ascontiguousarray(d), 1)
            z[w[:, 0]] = True
        return z, len(d)

    def add_places(self, database: Sequence | Iterable[Frame], progress: bool = True) -> int:
        """Add every posed frame of ``database`` as a place (its pose is the place's position); frames without
        a pose are skipped. Returns the number of places added. Places keep the database order (the motion
        model's adjacency)."""
        frames = database if isinstance(database, Sequence) else list(database)
        poses, rows = [], []
        n = len(frames)
        for i in tqdm(range(n), desc="FAB-MAP places", unit="frame", disable=not progress, leave=False):
            f = frames[i]
            if not isinstance(f, Frame):
                raise ConfigError(f"add_places: database item {i} is a {type(f).__name__}, expected a Frame")
            if f.pose is None:
                continue
            z, _ = self.observe(f, f"database frame {i}")
            rows.append(np.flatnonzero(z))
            poses.append(f.pose.as_array())
        if not rows:
            raise ConfigError(f"add_places: none of the {n} database frames has a pose")
        indptr = np.concatenate([[0], np.cumsum([len(r) for r in rows])])
        new = sp.csr_matrix((np.ones(indptr[-1], np.float32), np.concatenate(rows).astype(np.int64), indptr),
                            shape=(len(rows), self.vocabulary_size))
        self.places = sp.vstack([self.places, new]).tocsr()
        self.place_poses = np.concatenate([self.place_poses, np.array(poses)])
        self._belief = None
        return len(rows)

    # --- inference ------------------------------------------------------------------------------------------------
    def _factors(self, z: np.ndarray, log_tab: np.ndarray) -> tuple[float, np.ndarray]:
        """c(Z) and d(Z) with log p(Z | L) = c + z^L . d for a place of observation z^L."""
        zi = z.astype(np.int64)
        zp = np.where(self.tree.parent >= 0, zi[np.maximum(self.tree.parent, 0)], 0)
        q = np.arange(len(zi))
        l0, l1 = log_tab[q, zi, zp, 0], log_tab[q, zi, zp, 1]
        return float(l0.sum()), l1 - l0

    def log_likelihoods(self, z: np.ndarray, places: sp.csr_matrix | None = None) -> np.ndarray:
        """log p(Z | L_j) for the rows of ``places`` (default: the database places)."""
        z = np.asarray(z, bool).ravel()
        if z.shape != (self.vocabulary_size,):
            raise ConfigError(f"log_likelihoods: expected an occurrence vector of {self.vocabulary_size} words, "
                              f"got shape {z.shape}")
        c, d = self._factors(z, self._log_place)
        places = self.places if places is None else _as_occurrences(places)
        return c + places @ d

    def new_place_log_likelihood(self, z: np.ndarray) -> float:
        """log p(Z | L_new): sampled (mean over training place models) or mean field."""
        z = np.asarray(z, bool).ravel()
        if self.config.new_place == "sampled":
            ll = self.log_likelihoods(z, self._samples)
            return float(logsumexp(ll) - math.log(len(ll)))
        zi = z.astype(np.int64)
        zp = np.where(self.tree.parent >= 0, zi[np.maximum(self.tree.parent, 0)], 0)
        return float(self._log_mf[np.arange(len(zi)), zi, zp].sum())

    def _answer(self, z: np.ndarray, nfeat: int, sequential: bool) -> Localization:
        n = self.num_places
        if n == 0:
            raise ConfigError("FabMap: no places; call add_places(database) first")
        c = self.config
        ll = np.empty(n + 1)
        ll[:n] = self.log_likelihoods(z)
        ll[n] = self.new_place_log_likelihood(z)
        if sequential and self._belief is not None:
            place_prior = motion_prior(self._belief, c.motion_window)
        else:
            place_prior = np.full(n, 1.0 / n)
        with np.errstate(divide="ignore"):
            logp = ll + np.log(np.concatenate([(1 - c.new_place_prior) * place_prior, [c.new_place_prior]]))
        post = np.exp(logp - logsumexp(logp))
        # the paper's smoothing of p(L | Z) over the n + 1 hypotheses; it gives p(new place) and the belief the
        # motion model moves on
        smoothed = c.smoothing * post + (1 - c.smoothing) / (n + 1)
        if sequential:
            self._belief = smoothed
        # the place posterior reported (and the estimate): p(L_j | Z, in the map), smoothed the same way over the
        # places; it does not depend on the new-place model
        places = logp[:n] - logsumexp(logp[:n])
        places = c.smoothing * np.exp(places) + (1 - c.smoothing) / n
        score = float(1.0 - smoothed[n])
        return Localization(estimate=top_k_estimate(self.place_poses, places, c.top_k),
                            candidates=self.place_poses.copy(), posterior=places, inlier_score=score,
                            inlier=score >= c.inlier_threshold, num_samples=int(nfeat))

    def localize(self, image: Image) -> Localization:
        """Localize one image (a Frame's left view, or an image) with a uniform prior over the places."""
        z, nfeat = self.observe(image)
        return self._answer(z, nfeat, sequential=False)

    def reset(self) -> None:
        """Forget the sequential belief (the next stream starts from the uniform prior)."""
        self._belief = None

    def localize_next(self, image: Image, where: str = "query frame") -> Localization:
        """Localize the next image of a stream: with ``config.sequential`` its prior is the previous posterior
        moved by the motion model (uniform after :meth:`reset`); otherwise as :meth:`localize`."""
        z, nfeat = self.observe(image, where)
        return self._answer(z, nfeat, sequential=self.config.sequential)

    def localize_stream(self, frames: Iterable[Image]) -> Iterator[Localization]:
        """Localize frames in order (:meth:`reset`, then :meth:`localize_next` for each)."""
        self.reset()
        for i, f in enumerate(frames):
            yield self.localize_next(f, f"query frame {i}")

    def with_config(self, **changes) -> "FabMap":
        """A FabMap sharing this one's vocabulary, tree and places, with inference settings changed (the build
        settings -- vocabulary, features, pseudo_count -- must stay as trained)."""
        build = ("vocabulary_size", "max_features", "contrast_threshold", "image_scale", "kmeans_iterations",
                 "max_train_descriptors", "pseudo_count")
        bad = sorted(k for k in changes if k in build and changes[k] != getattr(self.config, k))
        if bad:
            raise ConfigError(f"with_config: {bad} are build settings; train a new FabMap to change them")
        cfg = from_dict(FabMapConfig, {**to_dict(self.config), **changes}, "with_config")
        fm = FabMap(cfg, self.centres, self.tree, self.training)
        fm._index = self._index
        fm.places, fm.place_poses = self.places, self.place_poses
        return fm

    # --- persistence ----------------------------------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        """Vocabulary, tree, training occurrences, places and configuration in one npz (atomic)."""
        t, p = self.training, self.places
        save_npz(path, FORMAT, {
            "centres": self.centres, "parent": self.tree.parent, "marginal": self.tree.marginal,
            "cond": self.tree.cond, "mutual_information": self.tree.mutual_information,
            "train_indices": t.indices.astype(np.int64), "train_indptr": t.indptr.astype(np.int64),
            "place_indices": p.indices.astype(np.int64), "place_indptr": p.indptr.astype(np.int64),
            "place_poses": self.place_poses,
        }, {"config": to_dict(self.config), "vocabulary_size": self.vocabulary_size,
            "num_training": int(t.shape[0]), "num_places": self.num_places})

    @staticmethod
    def load(path: str | Path) -> "FabMap":
        arrays, meta = load_npz(path, FORMAT)
        try:
            config = from_dict(FabMapConfig, meta["config"], f"{path}: config")
            v = int(meta["vocabulary_size"])
            nt, npl = int(meta["num_training"]), int(meta["num_places"])
        except (KeyError, TypeError, ValueError, ConfigError) as e:
            raise FormatError(f"{path}: bad or missing header field ({e})") from e
        want = {"centres": (v, 128), "parent": (v,), "marginal": (v,), "cond": (v, 2), "mutual_information": (v,),
                "train_indptr": (nt + 1,), "place_indptr": (npl + 1,), "place_poses": (npl, 3)}
        for k, shape in want.items():
            if k not in arrays:
                raise FormatError(f"{path}: missing array '{k}'")
            if arrays[k].shape != shape:
                raise FormatError(f"{path}: array '{k}' has shape {arrays[k].shape}, expected {shape}")
        for k in ("train_indices", "place_indices"):
            if k not in arrays:
                raise FormatError(f"{path}: missing array '{k}'")
        parent = arrays["parent"].astype(np.int64)
        if (parent < -1).any() or (parent >= v).any() or (parent < 0).sum() != 1:
            raise FormatError(f"{path}: array 'parent' is not a rooted tree over {v} words")
        for k in ("marginal", "cond"):
            if not np.all((arrays[k] > 0) & (arrays[k] < 1)):
                raise FormatError(f"{path}: array '{k}' holds values outside (0, 1)")

        def csr(prefix: str, rows: int) -> sp.csr_matrix:
            ind, ptr = arrays[f"{prefix}_indices"], arrays[f"{prefix}_indptr"]
            if ptr[0] != 0 or np.any(np.diff(ptr) < 0) or ptr[-1] != len(ind) or \
                    (len(ind) and (ind.min() < 0 or ind.max() >= v)):
                raise FormatError(f"{path}: arrays '{prefix}_indices/indptr' are not a valid sparse matrix")
            return sp.csr_matrix((np.ones(len(ind), np.float32), ind, ptr), shape=(rows, v))

        tree = ChowLiuTree(parent, arrays["marginal"].astype(np.float64), arrays["cond"].astype(np.float64),
                           arrays["mutual_information"].astype(np.float64))
        try:
            fm = FabMap(config, arrays["centres"], tree, csr("train", nt))
        except ConfigError as e:
            raise FormatError(f"{path}: {e}") from e
        fm.places, fm.place_poses = csr("place", npl), arrays["place_poses"].astype(np.float64)
        return fm
