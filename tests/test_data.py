import json

import numpy as np
import pytest

from satloc import ConfigError, FormatError, Frame, Pose2, Sequence, SequenceWriter, StereoCamera
from satloc.config import from_dict, override
from satloc.persist import load_npz, save_npz
from satloc.sequence import decode_depth, encode_depth


def make_frames(cam, n=3, depth=True, labels=True):
    rng = np.random.default_rng(0)
    out = []
    for i in range(n):
        shape = (cam.height, cam.width)
        out.append(Frame(rng.integers(0, 255, shape + (3,), dtype=np.uint8),
                         rng.integers(0, 255, shape + (3,), dtype=np.uint8),
                         Pose2(i, 2 * i, 0.1 * i), 0.1 * i,
                         rng.uniform(0, 100, shape).astype(np.float32) if depth else None,
                         rng.integers(0, 12, shape, dtype=np.uint8) if labels else None))
    return out


def test_sequence_save_load_round_trip(tmp_path):
    cam = StereoCamera.kitti().resized(64, 20)
    frames = make_frames(cam)
    seq = Sequence(cam, frames, "s", {"source": "test"}).save(tmp_path / "seq")
    back = Sequence.load(tmp_path / "seq")
    assert back.camera == cam and len(back) == 3 and back.meta == {"source": "test"}
    for a, b in zip(frames, back):
        assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
        assert np.array_equal(a.labels, b.labels)
        assert np.abs(a.depth - b.depth).max() <= 0.5 / 256 + 1e-6
        assert a.pose == b.pose and a.timestamp == b.timestamp
    assert back.path_length() == pytest.approx(2 * np.sqrt(5))


def test_depth_encoding_marks_invalid():
    d = np.array([0.0, np.nan, np.inf, 1.5, 300.0], np.float32)
    out = decode_depth(encode_depth(d))
    assert out[0] == 0 and out[1] == 0 and out[2] == 0 and out[3] == pytest.approx(1.5)
    assert out[4] == pytest.approx(65535 / 256)


def test_sequence_writer_leaves_nothing_on_error(tmp_path):
    cam = StereoCamera.kitti().resized(64, 20)
    frames = make_frames(cam, 2)
    with pytest.raises(FormatError, match="expected a 64x20"):
        with SequenceWriter(tmp_path / "seq", cam) as w:
            w.add(frames[0])
            w.add(Frame(frames[1].left[:10], frames[1].right, None))
    assert list(tmp_path.iterdir()) == []


def test_frame_of_wrong_size_rejected():
    cam = StereoCamera.kitti().resized(64, 20)
    f = make_frames(cam.resized(32, 10), 1)[0]
    with pytest.raises(FormatError, match="left"):
        Sequence(cam, [f])


def test_damaged_and_foreign_files(tmp_path):
    cam = StereoCamera.kitti().resized(64, 20)
    Sequence(cam, make_frames(cam, 1)).save(tmp_path / "seq")
    (tmp_path / "seq" / "frames.npz").write_bytes(b"garbage")
    with pytest.raises(FormatError, match="frames.npz"):
        Sequence.load(tmp_path / "seq")
    save_npz(tmp_path / "x.npz", "other_thing", {"a": np.zeros(3)})
    with pytest.raises(FormatError, match="expected a satloc 'sequence_frames' file"):
        load_npz(tmp_path / "x.npz", "sequence_frames")
    meta = json.loads((tmp_path / "seq" / "sequence.json").read_text())
    meta["version"] = 999
    (tmp_path / "seq" / "sequence.json").write_text(json.dumps(meta))
    with pytest.raises(FormatError, match="version 999"):
        Sequence.load(tmp_path / "seq")
    with pytest.raises(FormatError, match="not found"):
        Sequence.load(tmp_path / "nope")


def test_npz_never_unpickles(tmp_path):
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    import zipfile
    with zipfile.ZipFile(tmp_path / "bad.npz", "w") as z:
        z.write(tmp_path / "obj.npy", "__meta__.npy")
    with pytest.raises(FormatError):
        load_npz(tmp_path / "bad.npz", "x")


def test_config_unknown_keys_and_types():
    from dataclasses import dataclass, field

    @dataclass
    class Inner:
        a: float = 1.0

    @dataclass
    class Outer:
        name: str
        inner: Inner = field(default_factory=Inner)
        pair: tuple[int, int] = (1, 2)

    o = from_dict(Outer, {"name": "x", "inner": {"a": 3}, "pair": [4, 5]})
    assert o.inner.a == 3.0 and o.pair == (4, 5)
    with pytest.raises(ConfigError, match=r"cfg: unknown key\(s\) \['nmae'\]"):
        from_dict(Outer, {"nmae": "x"}, "cfg")
    with pytest.raises(ConfigError, match="missing required key 'name'"):
        from_dict(Outer, {}, "cfg")
    with pytest.raises(ConfigError, match=r"cfg.inner.a: expected a number"):
        from_dict(Outer, {"name": "x", "inner": {"a": "big"}}, "cfg")
    with pytest.raises(ConfigError, match=r"cfg.pair: expected 2 values"):
        from_dict(Outer, {"name": "x", "pair": [1]}, "cfg")
    assert override(o, {"inner": {"a": 7}}).inner.a == 7.0
    with pytest.raises(ConfigError, match="unknown key 'b'"):
        override(o, {"inner": {"b": 7}})
