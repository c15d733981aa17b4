"""Semantic and edge features from a small fully convolutional network (FCN) trained on the simulator.

The project ships its own network, :class:`SegEdgeNet`, trained from scratch on images rendered by
:mod:`satloc_env` (whose labels are exact), because no pretrained weights can be downloaded. It is an
encoder-decoder with skip connections and two heads: per-pixel scores of the :data:`satloc.labels.CLASSES`
and one boundary logit. There is one network per view (``ground``, ``satellite``), both stored in one
weights file, ``satloc/weights/fcn.pt`` (retrain with ``python -m satloc_env.experiments.train_features``).

Extractors (the :mod:`satloc.features.extractor` interface, ``extractor(image, view) -> (H, W, dim) float32``):

- :class:`SemanticFeatures`: per-pixel class probabilities (softmax of the scores), ``dim = NUM_CLASSES``; or
  of any torch module you plug in that returns per-pixel class scores.
- :class:`EdgeFeatures`: edge potentials in [0, 1], ``dim = 1``: the boundary head of the network, or a
  structured-forest model through ``cv2.ximgproc`` when given a model file.

One network pass serves both: the extractors share an :class:`FCNPredictor` (by default the process-wide
:func:`default_predictor` of their ``device``), which remembers the outputs for the last image and view it
ran on (for the last n images after a :meth:`FCNPredictor.prefetch` of n images). A ``FeatureStack([SemanticFeatures(), EdgeFeatures()])`` therefore runs the network once per image.

The networks run on the predictor's ``device`` (:mod:`satloc.device`: ``"auto"``, the default, is CUDA
when it is available, else the CPU); outputs come back as numpy arrays.

Weights file: ``torch.save`` of a dict of primitives and tensors, read with ``torch.load(weights_only=True)``::

    {"format": "satloc_fcn", "version": 1, "num_classes": 12, "classes": [...],
     "views": {"ground": {"widths": [...], "input_scale": 0.5, "state_dict": {name: float16 tensor}},
               "satellite": {...}},
     "training": {...}}            # free-form summary of how the weights were made

A missing, damaged or foreign file raises :class:`satloc.FormatError` naming the file.
"""
from __future__ import annotations

import contextlib
import functools
import hashlib
import os
from collections import OrderedDict
from pathlib import Path
from typing import Any, Iterator, Mapping, NamedTuple, Sequence

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..device import resolve_device
from ..errors import ConfigError, FormatError
from ..labels import CLASSES, NUM_CLASSES
from ..persist import atomic_path, check_header, check_zip, header
from .extractor import View, check_image

FORMAT = "satloc_fcn"
VIEWS: tuple[str, ...] = ("ground", "satellite")
WEIGHTS_DIR = Path(__file__).resolve().parent.parent / "weights"
DEFAULT_WEIGHTS = WEIGHTS_DIR / "fcn.pt"
DEFAULT_WIDTHS: tuple[int, ...] = (16, 32, 48, 64, 96)

# fixed input normalisation of SegEdgeNet (RGB in [0, 1])
_MEAN, _STD = 0.45, 0.25


def _conv_bn_relu(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class SegEdgeNet(nn.Module):
    """Encoder-decoder FCN with a class head and a boundary head.

    Level ``i`` of the encoder halves the resolution with a strided 3x3 convolution, then applies another,
    with ``widths[i]`` channels, so the deepest features are at 1/2**len(widths) of the input. The decoder
    goes back up to 1/2 resolution (U-Net style): a 2x2 transposed convolution doubles the resolution, the
    encoder level of that resolution is concatenated (skip connection), a 3x3 convolution merges them. A 1x1
    convolution then gives ``num_classes`` scores and one boundary logit, upsampled bilinearly to the
    requested output size. Every 3x3 convolution is followed by batch normalisation and a ReLU.

    Input: (N, 3, H, W) float RGB in [0, 1], any H and W (padded internally to a multiple of :attr:`stride`
    by edge replication, and cropped back).
    """

    def __init__(self, num_classes: int = NUM_CLASSES, widths: Sequence[int] = DEFAULT_WIDTHS):
        super().__init__()
        if num_classes < 1 or len(widths) < 2 or min(widths) < 1:
            raise ConfigError(f"SegEdgeNet: need num_classes >= 1 and >= 2 positive widths, got {num_classes}, "
                              f"{list(widths)}")
        self.num_classes = int(num_classes)
        self.widths = tuple(int(w) for w in widths)
        enc, prev = [], 3
        for w in self.widths:
            enc.append(nn.Sequential(_conv_bn_relu(prev, w, stride=2), _conv_bn_relu(w, w)))
            prev = w
        self.encoder = nn.ModuleList(enc)
        self.upsample = nn.ModuleList(nn.ConvTranspose2d(self.widths[i + 1], self.widths[i], 2, stride=2)
                                      for i in range(len(self.widths) - 1))
        self.decoder = nn.ModuleList(_conv_bn_relu(2 * self.widths[i], self.widths[i])
                                     for i in range(len(self.widths) - 1))
        self.head = nn.Conv2d(self.widths[0], self.num_classes + 1, 1)

    @property
    def stride(self) -> int:
        """Input sizes are padded to a multiple of this."""
        return 2 ** len(self.widths)

    def forward_with_edges(self, x: torch.Tensor, out_size: tuple[int, int] | None = None
                           ) -> tuple[torch.Tensor, torch.Tensor]:
        """Class scores (N, C, h, w) and boundary logits (N, 1, h, w) at ``out_size`` (default: input size).

        ``out_size`` other than the input size covers the same field of view (e.g. the full-resolution
        image when ``x`` was downscaled).
        """
        n, _, h, w = x.shape
        oh, ow = out_size if out_size is not None else (h, w)
        s = self.stride
        ph, pw = -h % s, -w % s
        x = (x - _MEAN) / _STD
        if ph or pw:
            x = F.pad(x, (0, pw, 0, ph), mode="replicate")
        skips = []
        for level in self.encoder:
            x = level(x)
            skips.append(x)
        x = skips.pop()
        for up, merge in zip(reversed(self.upsample), reversed(self.decoder)):
            x = merge(torch.cat([up(x), skips.pop()], dim=1))
        y = self.head(x)
        # the padded input maps to (h + ph) * oh / h rows of output; crop the image's part
        full = (int(round((h + ph) * oh / h)), int(round((w + pw) * ow / w)))
        y = F.interpolate(y, size=full, mode="bilinear", align_corners=False)[:, :, :oh, :ow]
        return y[:, : self.num_classes], y[:, self.num_classes:]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Class scores (N, C, H, W) at the input size (the plug-in convention of :class:`SemanticFeatures`)."""
        return self.forward_with_edges(x)[0]


class ViewNet(NamedTuple):
    """The network of one view and the scale at which it sees images (0.5: half resolution)."""

    net: SegEdgeNet
    input_scale: float


# --- weights files --------------------------------------------------------------------------------------
def save_fcn(path: str | os.PathLike, views: Mapping[str, ViewNet], training: Mapping[str, Any] | None = None) -> None:
    """Write the per-view networks to one weights file (float16 tensors plus a header), atomically."""
    bad = sorted(set(views) - set(VIEWS))
    if bad or not views:
        raise ConfigError(f"save_fcn: views must be a non-empty subset of {list(VIEWS)}, got {sorted(views)}")
    data: dict[str, Any] = dict(header(FORMAT))
    data.update(num_classes=NUM_CLASSES, classes=list(CLASSES), views={}, training=dict(training or {}))
    for view, vn in views.items():
        if vn.net.num_classes != NUM_CLASSES:
            raise ConfigError(f"save_fcn: the {view} network has {vn.net.num_classes} classes, satloc has "
                              f"{NUM_CLASSES}")
        state = {k: (v.detach().to(torch.float16) if v.is_floating_point() else v.detach()).cpu().clone()
                 for k, v in vn.net.state_dict().items()}
        data["views"][view] = {"widths": list(vn.net.widths), "input_scale": float(vn.input_scale),
                               "state_dict": state}
    with atomic_path(path, suffix=".pt") as tmp:
        torch.save(data, tmp)


def load_fcn(path: str | os.PathLike = DEFAULT_WEIGHTS) -> tuple[dict[str, ViewNet], dict[str, Any]]:
    """Read a weights file written by :func:`save_fcn`; networks in eval mode, plus the ``training`` summary.

    Raises :class:`FormatError` naming the file if it is missing, damaged, foreign or of another version.
    """
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"{path}: FCN weights file not found")
    check_zip(path)  # torch.load does not check the CRCs: a flipped bit would load as another weight
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch.load raises many types on damaged or foreign input; all mean the same here
        raise FormatError(f"{path}: damaged or not a torch weights file ({type(e).__name__}: "
                          f"{str(e).splitlines()[0] if str(e) else ''})") from e
    check_header(data, FORMAT, path)
    if data.get("num_classes") != NUM_CLASSES or data.get("classes") != list(CLASSES):
        raise FormatError(f"{path}: trained for classes {str(data.get('classes'))[:200]}; satloc has {list(CLASSES)}")
    views = data.get("views")
    if not isinstance(views, dict) or not views or not set(views) <= set(VIEWS):
        raise FormatError(f"{path}: 'views' must map a subset of {list(VIEWS)} to networks")
    out = {}
    for view, v in views.items():
        try:
            net = SegEdgeNet(NUM_CLASSES, _checked_widths(v))
            state, model = v["state_dict"], net.state_dict()
            for k, t in state.items():
                want = model.get(k)
                if want is not None and (not isinstance(t, torch.Tensor) or t.is_complex()
                                         or t.is_floating_point() != want.is_floating_point()
                                         or (not want.is_floating_point() and t.dtype != want.dtype)
                                         or t.shape != want.shape):
                    raise TypeError(f"tensor {k!r} of {getattr(t, 'dtype', type(t).__name__)}, expected {want.dtype}")
                if isinstance(t, torch.Tensor) and t.is_floating_point() and not bool(torch.isfinite(t).all()):
                    raise ValueError(f"tensor {k!r} has non-finite values")
            net.load_state_dict({k: t.float() if t.is_floating_point() else t for k, t in state.items()})
            scale = v["input_scale"]
            if isinstance(scale, bool) or not isinstance(scale, (int, float)):
                raise TypeError(f"input_scale {str(scale)[:40]!r} is not a number")
        except (KeyError, TypeError, AttributeError, RuntimeError, ValueError, ConfigError) as e:
            raise FormatError(f"{path}: bad '{view}' network ({type(e).__name__}: {str(e)[:300]})") from e
        if not 0.0 < scale <= 4.0:
            raise FormatError(f"{path}: '{view}' input_scale {scale} outside (0, 4]")
        out[view] = ViewNet(net.eval(), float(scale))
    training = data.get("training")
    return out, dict(training) if isinstance(training, dict) else {}


def _checked_widths(v: Mapping[str, Any]) -> list[int]:
    """A view's ``widths``, checked against its state_dict's encoder tensors before any network is built (a
    damaged width must not allocate a huge network)."""
    widths, state = v["widths"], v["state_dict"]
    if not isinstance(widths, list) or not isinstance(state, dict) or not all(
            isinstance(w, int) and not isinstance(w, bool) and w >= 1 for w in widths):
        raise TypeError(f"widths {str(widths)[:60]} (a list of positive integers) and a state_dict are needed")
    prev = 3
    for i, w in enumerate(widths):
        t = state.get(f"encoder.{i}.0.0.weight")
        if not isinstance(t, torch.Tensor) or tuple(t.shape) != (w, prev, 3, 3):
            raise ValueError(f"widths {widths}: level {i} needs encoder.{i}.0.0.weight of shape {(w, prev, 3, 3)}, "
                             f"got {tuple(t.shape) if isinstance(t, torch.Tensor) else None}")
        prev = w
    return widths


# --- inference ------------------------------------------------------------------------------------------
class FCNOutput(NamedTuple):
    """Network outputs at the image's full resolution."""

    scores: np.ndarray  # (C, H, W) float32 class logits (channels first, as the network computes them)
    edge: np.ndarray    # (H, W) float32 boundary logits


def _to_tensor(image: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1).unsqueeze(0).float().div_(255.0)


def _one_thread_after_fork() -> None:
    """In a child made by ``fork``: run torch on one thread.

    torch's CPU kernels run on an OpenMP (libgomp) thread pool that ``fork`` does not copy; once the parent
    has used it with more than one thread, the child's first parallel region waits forever for the missing
    workers (measured: a 3x3 convolution in a forked child never returned; with one thread it ran in
    13 ms). torch's own DataLoader workers also run on one thread. Children made by ``spawn`` or
    ``forkserver`` keep torch's default; raising the number again in a fork child brings the hang back."""
    torch.set_num_threads(1)


os.register_at_fork(after_in_child=_one_thread_after_fork)


@contextlib.contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Run the block with ``n`` torch threads (None: unchanged), then restore the previous number."""
    if n is None:
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


class FCNPredictor:
    """Runs the project's per-view networks on RGB images and remembers the last result.

    ``weights``: a file written by :func:`save_fcn` (default: the shipped ``satloc/weights/fcn.pt``).
    ``tile``: images larger than ``tile`` pixels (at the network's input scale) on a side are processed in
    overlapping tiles of that size, each keeping its centre (``margin`` pixels of context are dropped on
    inner sides), to bound memory on large satellite maps. ``threads``: torch threads while the network
    runs (the global setting is restored after each call); None keeps torch's global setting. One thread
    is the robust choice when other processes load the cores: with two, every parallel region waits for a
    descheduled thread (measured: 23 ms instead of 780 ms per ground frame on a busy 2-core machine).
    ``device``: where the networks run (:func:`satloc.device.resolve_device`: ``"auto"`` is CUDA when it is
    available, else the CPU); tiles go to it one at a time, the outputs come back to the CPU.
    """

    def __init__(self, weights: str | os.PathLike | None = None, tile: int = 1024, margin: int = 96,
                 threads: int | None = None, device: str | torch.device = "auto"):
        if tile < 64 or not 0 <= margin < tile // 4:
            raise ConfigError(f"FCNPredictor: need tile >= 64 and 0 <= margin < tile / 4, got {tile}, {margin}")
        if threads is not None and threads < 1:
            raise ConfigError(f"FCNPredictor: threads must be >= 1 or None, got {threads}")
        self.device = resolve_device(device)
        self.weights = Path(weights) if weights is not None else DEFAULT_WEIGHTS
        self.views, self.training = load_fcn(self.weights)   # on the CPU, then moved
        for vn in self.views.values():
            vn.net.to(self.device)
        self.tile, self.margin, self.threads = tile, margin, threads
        self._cache: OrderedDict[tuple, FCNOutput] = OrderedDict()   # the latest outputs, by image and view
        self._cache_size = 1

    def _key(self, image: np.ndarray, view: View) -> tuple:
        check_image(image, "FCN input")
        if view not in self.views:
            raise ConfigError(f"FCN: view {view!r} has no network in {self.weights} (has {sorted(self.views)})")
        return view, image.shape, hashlib.blake2b(np.ascontiguousarray(image), digest_size=16).digest()

    def _remember(self, key: tuple, out: FCNOutput) -> None:
        self._cache[key] = out
        self._cache.move_to_end(key)
        while len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)

    def __call__(self, image: np.ndarray, view: View) -> FCNOutput:
        """Class logits and boundary logits of ``image`` (RGB uint8) seen from ``view``."""
        key = self._key(image, view)
        out = self._cache.get(key)
        if out is None:
            out = self._run(self.views[view], image)
            self._remember(key, out)
        return out

    def prefetch(self, images: Sequence[np.ndarray], view: View) -> None:
        """Run the network on ``images`` (seen from ``view``) in one batch and remember the outputs, so that
        the next calls with these images (e.g. the localizations of a vector environment's cars) cost no
        network pass. Images the predictor already remembers are skipped; images of different sizes, or too
        large for one tile, run one by one. The outputs equal those of single calls up to float rounding of the
        batched convolutions (the network has no batch-dependent layer in inference)."""
        keys = [self._key(im, view) for im in images]
        self._cache_size = max(self._cache_size, len(keys))
        todo = {}
        for key, im in zip(keys, images):
            if key not in self._cache:
                todo.setdefault(key, im)
        vn = self.views[view]
        sizes = {im.shape for im in todo.values()}
        if len(todo) < 2 or len(sizes) > 1:
            for key, im in todo.items():
                self._remember(key, self._run(vn, im))
            return
        h, w = next(iter(sizes))[:2]
        x = torch.cat([self._input(vn, im) for im in todo.values()])
        if max(x.shape[-2:]) > self.tile:
            for key, im in todo.items():
                self._remember(key, self._run(vn, im))
            return
        with torch.inference_mode(), torch_threads(self.threads):
            scores, edge = (y.cpu() for y in vn.net.forward_with_edges(x.to(self.device), out_size=(h, w)))
        for i, key in enumerate(todo):
            self._remember(key, FCNOutput(scores[i].contiguous().numpy(), edge[i, 0].contiguous().numpy()))

    @staticmethod
    def _input(vn: ViewNet, image: np.ndarray) -> torch.Tensor:
        """The network's (1, 3, h, w) input tensor for ``image`` (resized by the view's input scale)."""
        h, w = image.shape[:2]
        if vn.input_scale != 1.0:
            sw, sh = max(1, int(round(w * vn.input_scale))), max(1, int(round(h * vn.input_scale)))
            image = cv2.resize(image, (sw, sh), interpolation=cv2.INTER_AREA if vn.input_scale < 1
                               else cv2.INTER_LINEAR)
        return _to_tensor(image)

    def _run(self, vn: ViewNet, image: np.ndarray) -> FCNOutput:
        h, w = image.shape[:2]
        x = self._input(vn, image)
        with torch.inference_mode(), torch_threads(self.threads):
            if max(x.shape[-2:]) <= self.tile:
                scores, edge = (y.cpu() for y in vn.net.forward_with_edges(x.to(self.device), out_size=(h, w)))
            else:
                scores, edge = self._tiled(vn.net, x)
                if scores.shape[-2:] != (h, w):
                    scores = F.interpolate(scores, size=(h, w), mode="bilinear", align_corners=False)
                    edge = F.interpolate(edge, size=(h, w), mode="bilinear", align_corners=False)
        return FCNOutput(scores[0].contiguous().numpy(), edge[0, 0].contiguous().numpy())

    def _tiled(self, net: SegEdgeNet, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Outputs at the input's size, from overlapping tiles whose centres are kept (the image and the
        outputs stay on the CPU; one tile at a time is on the device)."""
        _, _, h, w = x.shape
        core, m = self.tile - 2 * self.margin, self.margin
        scores = torch.empty((1, net.num_classes, h, w))
        edge = torch.empty((1, 1, h, w))
        for y0 in range(0, h, core):
            for x0 in range(0, w, core):
                y1, x1 = min(y0 + core, h), min(x0 + core, w)
                ty0, tx0 = max(0, y0 - m), max(0, x0 - m)
                ty1, tx1 = min(h, y1 + m), min(w, x1 + m)
                s, e = (y.cpu() for y in net.forward_with_edges(x[:, :, ty0:ty1, tx0:tx1].to(self.device)))
                scores[:, :, y0:y1, x0:x1] = s[:, :, y0 - ty0:y1 - ty0, x0 - tx0:x1 - tx0]
                edge[:, :, y0:y1, x0:x1] = e[:, :, y0 - ty0:y1 - ty0, x0 - tx0:x1 - tx0]
        return scores, edge


def default_predictor(device: str | torch.device = "auto") -> FCNPredictor:
    """The process-wide predictor with the shipped weights on ``device`` (loaded on first use, then shared:
    ``"auto"`` and the device it resolves to give the same one)."""
    return _shared_predictor(str(resolve_device(device)))


@functools.lru_cache(maxsize=2)
def _shared_predictor(device: str) -> FCNPredictor:
    return FCNPredictor(device=device)


# --- extractors -----------------------------------------------------------------------------------------
def _probabilities(scores: torch.Tensor, temperature: float) -> np.ndarray:
    """(H, W, C) float32 softmax of (C, H, W) scores / temperature (computed channels first: much faster
    than over a last axis of a dozen classes)."""
    if temperature != 1.0:
        scores = scores / temperature
    return torch.softmax(scores, dim=0).permute(1, 2, 0).contiguous().numpy()


class SemanticFeatures:
    """Per-pixel class probabilities (softmax of class scores / ``temperature``) as features.

    By default the shipped network of each view (through ``predictor``, default :func:`default_predictor`),
    with ``dim = NUM_CLASSES``. Alternatively plug in any torch module: ``model`` for both views, or
    ``view_models`` = ``{"ground": m1, "satellite": m2}``. A module receives a (1, 3, H, W) float32 RGB
    tensor in [0, 1] and returns class scores (1, C, h, w) (a tensor, or a mapping with key ``"out"`` as
    torchvision's segmentation models do); scores of another size are resized bilinearly to (H, W). It is
    put in eval mode and runs on the device its parameters are on (the input goes there, the scores come
    back). ``dim = C``: ``num_classes`` if given, else found by running the module once on a 64x64 image.
    ``device``: where the shipped network runs when no ``predictor`` is given (:mod:`satloc.device`).
    """

    name = "semantic"

    def __init__(self, model: nn.Module | None = None, view_models: Mapping[str, nn.Module] | None = None,
                 temperature: float = 1.0, num_classes: int | None = None, predictor: FCNPredictor | None = None,
                 device: str = "auto"):
        if not temperature > 0:
            raise ConfigError(f"SemanticFeatures: temperature must be > 0, got {temperature}")
        if model is not None and view_models is not None:
            raise ConfigError("SemanticFeatures: give either model (both views) or view_models, not both")
        if (model is not None or view_models is not None) and predictor is not None:
            raise ConfigError("SemanticFeatures: a predictor runs the project's networks; it cannot be combined "
                              "with a plugged-in model")
        self.temperature = float(temperature)
        self._predictor = predictor
        self._device = resolve_device(device)
        self._modules: dict[str, nn.Module] | None = None
        if model is not None:
            self._modules = {v: model for v in VIEWS}
        elif view_models is not None:
            bad = sorted(set(view_models) - set(VIEWS))
            if bad or not view_models:
                raise ConfigError(f"SemanticFeatures: view_models keys must be among {list(VIEWS)}, got "
                                  f"{sorted(view_models)}")
            self._modules = dict(view_models)
        if self._modules is None:
            self.dim = NUM_CLASSES if num_classes is None else int(num_classes)
            if self.dim != NUM_CLASSES:
                raise ConfigError(f"SemanticFeatures: the shipped network has {NUM_CLASSES} classes, "
                                  f"num_classes={num_classes}")
            return
        for v, m in self._modules.items():
            if not isinstance(m, nn.Module):
                raise ConfigError(f"SemanticFeatures: the {v} model must be a torch.nn.Module, got {type(m).__name__}")
            m.eval()
        if num_classes is not None:
            self.dim = int(num_classes)
        else:
            probe = np.zeros((64, 64, 3), np.uint8)
            dims = {v: self._module_scores(m, probe, v).shape[0] for v, m in self._modules.items()}
            if len(set(dims.values())) != 1:
                raise ConfigError(f"SemanticFeatures: the view models give different numbers of classes {dims}")
            self.dim = next(iter(dims.values()))
        if self.dim < 1:
            raise ConfigError(f"SemanticFeatures: num_classes must be >= 1, got {self.dim}")

    @property
    def predictor(self) -> FCNPredictor:
        if self._predictor is None:
            self._predictor = default_predictor(self._device)
        return self._predictor

    @staticmethod
    def _module_scores(module: nn.Module, image: np.ndarray, view: str) -> torch.Tensor:
        """(C, H, W) float32 scores of a plugged-in module."""
        h, w = image.shape[:2]
        param = next(module.parameters(), None)
        with torch.inference_mode():
            x = _to_tensor(image)
            y = module(x.to(param.device) if param is not None else x)
            if isinstance(y, Mapping):
                y = y.get("out")
            if not isinstance(y, torch.Tensor) or y.ndim != 4 or y.shape[0] != 1:
                got = tuple(y.shape) if isinstance(y, torch.Tensor) else type(y).__name__
                raise ConfigError(f"SemanticFeatures: the {view} model must return (1, C, h, w) scores, got {got}")
            if y.shape[-2:] != (h, w):
                y = F.interpolate(y.float(), size=(h, w), mode="bilinear", align_corners=False)
            return y[0].float().cpu()

    def prefetch(self, images: Sequence[np.ndarray], view: View) -> None:
        """Run the shipped network on ``images`` in one batch (see :meth:`FCNPredictor.prefetch`); a plugged-in
        model runs per image at the calls."""
        if self._modules is None:
            self.predictor.prefetch(images, view)

    def __call__(self, image: np.ndarray, view: View) -> np.ndarray:
        check_image(image, f"{self.name} features")
        if self._modules is None:
            scores = torch.from_numpy(self.predictor(image, view).scores)
        else:
            if view not in self._modules:
                raise ConfigError(f"SemanticFeatures: no model for view {view!r} (have {sorted(self._modules)})")
            scores = self._module_scores(self._modules[view], image, view)
            if scores.shape[0] != self.dim:
                raise ConfigError(f"SemanticFeatures: the {view} model returned {scores.shape[0]} classes, "
                                  f"expected {self.dim}")
        return _probabilities(scores, self.temperature)


class EdgeFeatures:
    """Edge potentials in [0, 1], one channel.

    Default: the boundary head of the shipped network (sigmoid of its logit), through ``predictor`` (default
    :func:`default_predictor`, shared with :class:`SemanticFeatures`, so both cost one network pass).
    With ``model_file``: OpenCV's structured-forest edge detector
    (``cv2.ximgproc.createStructuredEdgeDetection``, from ``opencv-contrib``), the same for both views.
    A model file that does not exist, or ``cv2.ximgproc`` missing, raises :class:`ConfigError`.
    ``device``: where the shipped network runs when no ``predictor`` is given (:mod:`satloc.device`).
    """

    name = "edge"
    dim = 1

    def __init__(self, model_file: str | os.PathLike | None = None, predictor: FCNPredictor | None = None,
                 device: str = "auto"):
        self._predictor = predictor
        self._device = resolve_device(device)
        self._forest = None
        if model_file is not None:
            if predictor is not None:
                raise ConfigError("EdgeFeatures: give either a structured-forest model_file or a predictor")
            if not Path(model_file).is_file():
                raise ConfigError(f"EdgeFeatures: structured-forest model file {str(model_file)!r} not found")
            if not hasattr(cv2, "ximgproc"):
                raise ConfigError(f"EdgeFeatures: model file {str(model_file)!r} needs cv2.ximgproc, which this "
                                  f"OpenCV lacks (install opencv-contrib-python-headless instead of "
                                  f"opencv-python-headless), or leave model_file unset to use the FCN")
            self._forest = cv2.ximgproc.createStructuredEdgeDetection(str(model_file))

    @property
    def predictor(self) -> FCNPredictor:
        if self._predictor is None:
            self._predictor = default_predictor(self._device)
        return self._predictor

    def prefetch(self, images: Sequence[np.ndarray], view: View) -> None:
        """Run the shipped network on ``images`` in one batch (see :meth:`FCNPredictor.prefetch`)."""
        if self._forest is None:
            self.predictor.prefetch(images, view)

    def __call__(self, image: np.ndarray, view: View) -> np.ndarray:
        check_image(image, f"{self.name} features")
        if self._forest is not None:
            e = self._forest.detectEdges(image.astype(np.float32) * (1.0 / 255.0))
        else:
            e = torch.sigmoid(torch.from_numpy(self.predictor(image, view).edge)).numpy()
        return np.ascontiguousarray(e, dtype=np.float32)[..., None]
