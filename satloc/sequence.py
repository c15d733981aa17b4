"""Frames and sequences: what the simulator and the dataset readers produce and the method consumes.

On-disk layout of a sequence directory (format ``sequence``, version 1)::

    sequence.json          header, name, camera (StereoCamera fields), frame count, which channels exist,
                           free-form ``meta`` (source, scene, pass settings)
    frames.npz             poses (N, 3) float64 [x, y, yaw] in the map frame, timestamps (N,) float64 seconds,
                           has_pose (N,) bool
    left/000000.png        left colour image, RGB stored as an 8-bit PNG
    right/000000.png       right colour image
    depth/000000.png       optional: left-camera metric z-depth as 16-bit PNG, metres * 256, 0 = invalid
    labels/000000.png      optional: left-camera semantic class ids (satloc.labels.CLASSES), 8-bit PNG

Sequences are written to a temporary directory and renamed into place only when complete.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator
from typing import Sequence as Seq

import cv2
import numpy as np

from .errors import ConfigError, FormatError
from .geoframe import GeoFrame
from .geometry import Pose2, StereoCamera
from .labels import NUM_CLASSES
from .persist import ArraySpec, atomic_dir, header, header_number, load_npz, read_json, save_npz, write_json
from .satmap import read_image

DEPTH_SCALE = 256.0  # depth PNG units per metre


@dataclass
class Frame:
    """One stereo capture. Images are RGB uint8 (H, W, 3); depth float32 metres (0 = invalid)."""

    left: np.ndarray
    right: np.ndarray
    pose: Pose2 | None = None
    timestamp: float = 0.0
    depth: np.ndarray | None = None
    labels: np.ndarray | None = None

    def check(self, camera: StereoCamera, where: str = "frame") -> None:
        want = (camera.height, camera.width)
        for name in ("left", "right"):
            img = getattr(self, name)
            if img.shape[:2] != want or img.ndim != 3 or img.dtype != np.uint8:
                raise FormatError(
                    f"{where}.{name}: expected a {camera.width}x{camera.height} RGB uint8 image "
                    f"(the camera's size), got {img.dtype} {img.shape}")
        for name in ("depth", "labels"):
            arr = getattr(self, name)
            if arr is not None and arr.shape[:2] != want:
                raise FormatError(f"{where}.{name}: expected shape {want}, got {arr.shape}")


def _imwrite(path: Path, img: np.ndarray) -> None:
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    if not cv2.imwrite(str(path), img):
        raise OSError(f"{path}: could not write image")


def encode_depth(depth: np.ndarray) -> np.ndarray:
    d = np.nan_to_num(np.asarray(depth, dtype=np.float64), nan=0.0, posinf=0.0)
    return np.clip(np.round(d * DEPTH_SCALE), 0, 65535).astype(np.uint16)


def decode_depth(png: np.ndarray) -> np.ndarray:
    return png.astype(np.float32) / DEPTH_SCALE


class SequenceWriter:
    """Streams frames into a sequence directory; the directory appears only when :meth:`close` succeeds.

    Use as a context manager: on an exception nothing is left behind.
    """

    def __init__(self, path: str | Path, camera: StereoCamera, name: str = "", meta: dict | None = None):
        self.path = Path(path)
        self.camera = camera
        self.name = name or self.path.name
        self.meta = dict(meta or {})
        self._ctx = atomic_dir(self.path)
        self._tmp = self._ctx.__enter__()
        self._poses: list[np.ndarray] = []
        self._has_pose: list[bool] = []
        self._stamps: list[float] = []
        self._channels: set[str] | None = None
        for sub in ("left", "right"):
            (self._tmp / sub).mkdir()

    def add(self, frame: Frame) -> None:
        i = len(self._stamps)
        frame.check(self.camera, where=f"{self.path} frame {i}")
        channels = {c for c in ("depth", "labels") if getattr(frame, c) is not None}
        if self._channels is None:
            self._channels = channels
            for c in channels:
                (self._tmp / c).mkdir()
        elif channels != self._channels:
            raise FormatError(f"{self.path} frame {i}: has channels {sorted(channels)}, earlier frames "
                              f"{sorted(self._channels)}; every frame needs the same ones")
        name = f"{i:06d}.png"
        _imwrite(self._tmp / "left" / name, frame.left)
        _imwrite(self._tmp / "right" / name, frame.right)
        if frame.depth is not None:
            _imwrite(self._tmp / "depth" / name, encode_depth(frame.depth))
        if frame.labels is not None:
            _imwrite(self._tmp / "labels" / name, frame.labels.astype(np.uint8))
        self._poses.append(frame.pose.as_array() if frame.pose is not None else np.full(3, np.nan))
        self._has_pose.append(frame.pose is not None)
        self._stamps.append(float(frame.timestamp))

    def close(self) -> "Sequence":
        n = len(self._stamps)
        save_npz(self._tmp / "frames.npz", "sequence_frames", {
            "poses": np.array(self._poses, dtype=np.float64).reshape(n, 3),
            "timestamps": np.array(self._stamps, dtype=np.float64),
            "has_pose": np.array(self._has_pose, dtype=bool),
        })
        info = header("sequence")
        info.update(name=self.name, camera=self.camera.to_dict(), num_frames=n,
                    channels=sorted(self._channels or []), meta=self.meta)
        write_json(self._tmp / "sequence.json", info)
        self._ctx.__exit__(None, None, None)
        return Sequence.load(self.path)

    def abort(self) -> None:
        try:
            raise RuntimeError("aborted")
        except RuntimeError as e:
            try:
                self._ctx.__exit__(type(e), e, e.__traceback__)
            except RuntimeError:
                pass

    def __enter__(self) -> "SequenceWriter":
        return self

    def __exit__(self, et, ev, tb) -> None:
        if et is not None:
            self.abort()


class Sequence:
    """Frames plus the camera that took them. In memory, or backed by a directory (loaded lazily)."""

    def __init__(self, camera: StereoCamera, frames: Seq[Frame] | None = None, name: str = "",
                 meta: dict | None = None):
        self.camera = camera
        self.name = name
        self.meta = dict(meta or {})
        self._frames = list(frames) if frames is not None else []
        self._dir: Path | None = None
        self._read: Callable[[int], Frame] | None = None  # lazy frame source (dataset readers)
        self._channels: list[str] = []
        for i, f in enumerate(self._frames):
            f.check(camera, where=f"sequence {name!r} frame {i}")
        self._poses = np.array([f.pose.as_array() if f.pose is not None else np.full(3, np.nan)
                                for f in self._frames]).reshape(-1, 3)
        self._stamps = np.array([f.timestamp for f in self._frames], dtype=np.float64)

    # --- access -----------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._stamps)

    def __getitem__(self, i: int) -> Frame:
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame {i} out of range for a sequence of {n}")
        i %= n
        if self._read is not None:
            f = self._read(i)
            f.check(self.camera, where=f"sequence {self.name!r} frame {i}")
            return f
        if self._dir is None:
            return self._frames[i]
        return self._read_frame(i)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    @staticmethod
    def lazy(camera: StereoCamera, poses: np.ndarray, timestamps: np.ndarray, read: Callable[[int], Frame],
             name: str = "", meta: dict | None = None) -> "Sequence":
        """A sequence whose frames are read on demand by ``read(i)`` (e.g. from a dataset's own layout).

        ``poses`` (N, 3) with NaN rows where a frame has no pose, ``timestamps`` (N,). Each frame read is
        checked against ``camera``; its ``pose`` and ``timestamp`` should be those given here."""
        poses = np.asarray(poses, np.float64)
        stamps = np.asarray(timestamps, np.float64)
        if poses.ndim != 2 or poses.shape[1] != 3 or stamps.shape != (len(poses),):
            raise FormatError(f"sequence {name!r}: expected poses (N, 3) and timestamps (N,), got "
                              f"{poses.shape} and {stamps.shape}")
        seq = Sequence(camera, None, name, meta)
        seq._poses, seq._stamps, seq._read = poses, stamps, read
        return seq

    @property
    def poses(self) -> np.ndarray:
        """(N, 3) [x, y, yaw]; rows of NaN where a frame has no pose."""
        return self._poses.copy()

    @property
    def geo_frame(self) -> GeoFrame | None:
        """The :class:`GeoFrame` the poses are in (real data: ``meta["geo_frame"]``); None for a local frame."""
        d = self.meta.get("geo_frame")
        return None if d is None else GeoFrame.from_dict(d, f"sequence {self.name!r} meta.geo_frame")

    @property
    def timestamps(self) -> np.ndarray:
        return self._stamps.copy()

    def head(self, n: int) -> "Sequence":
        """A view of the first ``n`` frames (frames are still read lazily from disk)."""
        if n < 0:
            raise ValueError(f"head: n must be >= 0, got {n}")
        v = Sequence.__new__(Sequence)
        v.__dict__.update(self.__dict__)
        v._frames, v._poses, v._stamps = self._frames[:n], self._poses[:n], self._stamps[:n]
        return v

    def view(self, index=None, camera: StereoCamera | None = None, name: str | None = None) -> "Sequence":
        """A lazy sequence of the frames ``index`` (default: all) with both images resampled into ``camera``
        (default: this sequence's): resized to its image size, then warped to its intrinsics (a rectified
        pinhole pair: an affine map), e.g. a drive at half resolution or a query drive in the database's
        intrinsics. Depth and labels are kept when the camera is unchanged, dropped when the images are
        resampled. ``meta["source_frames"]`` lists the indices."""
        n = len(self)
        index = np.arange(n) if index is None else np.asarray(index, np.int64).reshape(-1)
        if len(index) and (index.min() < -n or index.max() >= n):
            raise IndexError(f"view: frame indices must lie in [-{n}, {n}), got {index.min()}..{index.max()}")
        index = np.where(index < 0, index + n, index)   # meta["source_frames"] names the frames as 0..n-1
        camera = camera or self.camera
        meta = dict(self.meta, source_frames=[int(i) for i in index], source_camera=self.camera.to_dict())
        return Sequence.lazy(camera, self._poses[index], self._stamps[index], _Resampled(self, index, camera),
                             name=name or self.name, meta=meta)

    def path_length(self) -> float:
        p = self._poses[:, :2]
        p = p[np.all(np.isfinite(p), axis=1)]
        return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0

    # --- persistence ------------------------------------------------------------------------------
    def save(self, path: str | Path) -> "Sequence":
        with SequenceWriter(path, self.camera, self.name, self.meta) as w:
            for f in self:
                w.add(f)
            return w.close()

    @staticmethod
    def load(path: str | Path) -> "Sequence":
        d = Path(path)
        if not d.is_dir():
            raise FormatError(f"{d}: sequence directory not found")
        sj = d / "sequence.json"
        info = read_json(sj, "sequence")
        camera = camera_from_dict(info.get("camera"), f"{sj}: camera")
        n = header_number(info, "num_frames", sj, integer=True)
        if n < 0:
            raise FormatError(f"{sj}: field 'num_frames': expected an integer >= 0, got {n}")
        name = info.get("name", d.name)
        meta = info.get("meta", {})
        channels = info.get("channels", [])
        if not isinstance(name, str):
            raise FormatError(f"{sj}: field 'name': expected a string, got {str(name)[:60]!r}")
        if not isinstance(meta, dict):
            raise FormatError(f"{sj}: field 'meta': expected a mapping, got {type(meta).__name__}")
        if not isinstance(channels, list) or not all(isinstance(c, str) for c in channels) \
                or not set(channels) <= set(_CHANNELS) or len(set(channels)) != len(channels):
            raise FormatError(f"{sj}: field 'channels': expected a list of {list(_CHANNELS)}, got {str(channels)[:60]}")
        if meta.get("geo_frame") is not None:
            try:
                GeoFrame.from_dict(meta["geo_frame"], "meta.geo_frame")
            except ConfigError as e:
                raise FormatError(f"{sj}: {e}") from e
        arrays, _ = load_npz(d / "frames.npz", "sequence_frames", {
            "poses": ArraySpec("f", ("N", 3), finite=False), "timestamps": ArraySpec("f", ("N",)),
            "has_pose": ArraySpec("b", ("N",))}, {"N": (n, f"num_frames in {sj}")})
        poses, has_pose = arrays["poses"].astype(np.float64), arrays["has_pose"]
        bad = np.flatnonzero(has_pose & ~np.isfinite(poses).all(axis=1))
        if len(bad):
            raise FormatError(f"{d / 'frames.npz'}: frame {bad[0]} has a pose (has_pose) with non-finite values "
                              f"{poses[bad[0]].tolist()}")
        seq = Sequence(camera, None, name, meta)
        seq._dir = d
        seq._poses = np.where(has_pose[:, None], poses, np.nan)
        seq._stamps = arrays["timestamps"].astype(np.float64)
        seq._channels = list(channels)
        for i in (0, n - 1) if n else ():
            if not (d / "left" / f"{i:06d}.png").is_file():
                raise FormatError(f"{d / 'left' / f'{i:06d}.png'}: missing frame image ({n} frames in {sj})")
        return seq

    def _read_frame(self, i: int) -> Frame:
        d, name = self._dir, f"{i:06d}.png"
        cam = self.camera
        want = (cam.height, cam.width)
        imgs = {}
        for c in ("left", "right") + tuple(self._channels):
            p = d / c / name
            img = read_image(p, grayscale=c in _CHANNELS)
            dtype = np.uint16 if c == "depth" else np.uint8
            if img.shape[:2] != want or img.dtype != dtype:
                raise FormatError(f"{p}: expected a {cam.width}x{cam.height} {np.dtype(dtype).name} image (the "
                                  f"camera's size in {d / 'sequence.json'}), got {img.dtype} "
                                  f"{img.shape[1]}x{img.shape[0]}")
            if c == "labels" and img.max() >= NUM_CLASSES:
                raise FormatError(f"{p}: class id {img.max()} >= {NUM_CLASSES} (satloc.labels.CLASSES)")
            imgs[c] = img
        depth = decode_depth(imgs["depth"]) if "depth" in imgs else None
        pose = Pose2.from_array(self._poses[i]) if np.all(np.isfinite(self._poses[i])) else None
        return Frame(imgs["left"], imgs["right"], pose, float(self._stamps[i]), depth, imgs.get("labels"))


_CHANNELS = ("depth", "labels")


#: the ranges of a saved camera's fields that :func:`camera_from_dict` accepts: (low, high], a plausible rig
CAMERA_RANGES = {"width": (0, 100_000), "height": (0, 100_000), "fx": (0.0, 1e7), "fy": (0.0, 1e7),
                 "cx": (-1e7, 1e7), "cy": (-1e7, 1e7), "baseline": (0.0, 100.0), "mount_height": (0.0, 100.0),
                 "pitch": (-math.pi / 2, math.pi / 2 - 1e-9)}


def camera_from_dict(d, where: str) -> StereoCamera:
    """A :class:`StereoCamera` from its saved fields (``to_dict()``), every field checked: integers for the
    image size, and every value within :data:`CAMERA_RANGES` (finite; positive focal lengths, baseline and
    mounting height; pitch within +-90 degrees). :class:`FormatError` naming ``where`` (the file and field)
    otherwise."""
    from .config import from_dict

    try:
        cam = from_dict(StereoCamera, d, where)
    except ConfigError as e:
        raise FormatError(str(e)) from e
    return check_camera_ranges(cam, where)


def check_camera_ranges(cam: StereoCamera, where: str) -> StereoCamera:
    """``cam`` if every field lies in :data:`CAMERA_RANGES`, else :class:`FormatError` naming ``where`` (the
    file the camera was read from) and the field."""
    for k, (lo, hi) in CAMERA_RANGES.items():
        v = getattr(cam, k)
        if not (math.isfinite(v) and lo < v <= hi):
            raise FormatError(f"{where}.{k}: expected a value in ({lo:g}, {hi:g}], got {v!r}")
    return cam


class _Resampled:
    """Reads frame ``index[j]`` of ``seq`` and resamples both images into ``camera`` (a plain object, so a
    view can be pickled like the readers' sequences)."""

    def __init__(self, seq: Sequence, index: np.ndarray, camera: StereoCamera):
        self.seq, self.index = seq, np.asarray(index, np.int64)
        src = seq.camera
        self.size = (camera.width, camera.height)
        self.resize = (src.width, src.height) != self.size
        # area averaging to shrink; bilinear to enlarge (OpenCV's area mode enlarges like nearest neighbour)
        self.interp = cv2.INTER_AREA if camera.width <= src.width and camera.height <= src.height else cv2.INTER_LINEAR
        r = src.resized(*self.size)  # the camera of cv2.resize's output
        a = np.array([[camera.fx / r.fx, 0.0, camera.cx - camera.fx / r.fx * r.cx],
                      [0.0, camera.fy / r.fy, camera.cy - camera.fy / r.fy * r.cy]])
        self.affine = None if np.allclose(a, [[1, 0, 0], [0, 1, 0]], rtol=0, atol=1e-9) else a

    def _image(self, img: np.ndarray) -> np.ndarray:
        if self.resize:
            img = cv2.resize(img, self.size, interpolation=self.interp)
        if self.affine is not None:
            img = cv2.warpAffine(img, self.affine, self.size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        return img

    def __call__(self, j: int) -> Frame:
        f = self.seq[int(self.index[j])]
        if not self.resize and self.affine is None:
            return f
        return Frame(self._image(f.left), self._image(f.right), f.pose, f.timestamp)
