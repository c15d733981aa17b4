"""Tests of the FCN features (satloc.features.fcn) and their training (satloc_env.experiments.train_features)."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from torch import nn

from satloc import ConfigError, FormatError
from satloc.features import FeatureStack
from satloc.features.fcn import (
    DEFAULT_WEIGHTS,
    FORMAT,
    EdgeFeatures,
    FCNPredictor,
    SegEdgeNet,
    SemanticFeatures,
    ViewNet,
    load_fcn,
    save_fcn,
)
from satloc.labels import NUM_CLASSES
from satloc_env.experiments.train_features import TrainConfig, class_weights, label_boundaries, train_view

# Sanity floors of pixel accuracy of the shipped weights; the held-out accuracies measured by the training
# report (satloc/weights/fcn_report.json) are well above them.
GROUND_FLOOR = 0.75
SATELLITE_FLOOR = 0.7


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """These small workloads run on one torch thread: with two, a busy machine (another process on a core)
    makes every parallel region wait for the descheduled thread, and the module took 45 s instead of 15."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def predictor() -> FCNPredictor:
    return FCNPredictor()


@pytest.fixture(scope="module")
def residential_tile() -> tuple[np.ndarray, np.ndarray]:
    """A 352 x 400 px crop of the residential scene's tile and its labels, from the bottom strip of the tile
    that training holds out."""
    from satloc_env.world.scene import load_scene

    sm = load_scene("residential").satmap
    return np.ascontiguousarray(sm.image[-352:, 900:1300]), sm.labels[-352:, 900:1300]


def _image(h: int, w: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


@pytest.mark.parametrize("shape", [(1, 1), (7, 5), (37, 53), (188, 620)])
@pytest.mark.parametrize("view", ["ground", "satellite"])
def test_shapes_dtypes_and_probabilities(predictor, shape, view):
    img = _image(*shape)
    sem = SemanticFeatures(predictor=predictor)(img, view)
    edge = EdgeFeatures(predictor=predictor)(img, view)
    assert sem.shape == shape + (NUM_CLASSES,) and sem.dtype == np.float32
    assert edge.shape == shape + (1,) and edge.dtype == np.float32
    np.testing.assert_allclose(sem.sum(axis=2), 1.0, atol=1e-5)
    assert sem.min() >= 0 and edge.min() >= 0 and edge.max() <= 1


def test_temperature_flattens(predictor):
    img = _image(40, 60)
    sharp = SemanticFeatures(predictor=predictor)(img, "ground")
    flat = SemanticFeatures(predictor=predictor, temperature=4.0)(img, "ground")
    assert flat.max(axis=2).mean() < sharp.max(axis=2).mean()
    with pytest.raises(ConfigError, match="temperature"):
        SemanticFeatures(temperature=0.0)


def test_one_network_pass_for_semantic_and_edge(predictor, monkeypatch):
    calls = []
    run = predictor._run
    monkeypatch.setattr(predictor, "_run", lambda vn, image: calls.append(1) or run(vn, image))
    stack = FeatureStack([SemanticFeatures(predictor=predictor), EdgeFeatures(predictor=predictor)])
    img = _image(50, 70, seed=1)
    f = stack(img, "ground")
    assert f.shape == (50, 70, NUM_CLASSES + 1) and len(calls) == 1
    stack(img.copy(), "ground")          # same content: cached
    assert len(calls) == 1
    stack(img, "satellite")              # other view: runs again
    img2 = img.copy()
    img2[0, 0, 0] ^= 1                   # other content: runs again
    stack(img2, "satellite")
    assert len(calls) == 3


def test_prefetch_runs_one_batch_that_the_calls_reuse(monkeypatch):
    """FCNPredictor.prefetch (the vector environment's batched localization) runs the network once for several
    images; the feature calls for those images then run nothing, and their features equal the unbatched ones
    up to float rounding of the batched convolutions."""
    predictor, single = FCNPredictor(), FCNPredictor()
    forwards = []
    for vn in predictor.views.values():
        fwd = vn.net.forward_with_edges
        monkeypatch.setattr(vn.net, "forward_with_edges", lambda x, *a, f=fwd, **k: forwards.append(len(x)) or f(x, *a, **k))
    stack = FeatureStack([SemanticFeatures(predictor=predictor), EdgeFeatures(predictor=predictor)])
    imgs = [_image(60, 90, seed=s) for s in range(4)]
    stack.prefetch(imgs + [imgs[0]], "ground")     # a repeated image is run once
    assert forwards == [4]
    ref = FeatureStack([SemanticFeatures(predictor=single), EdgeFeatures(predictor=single)])
    for img in reversed(imgs):
        np.testing.assert_allclose(stack(img, "ground"), ref(img, "ground"), atol=1e-5)
    assert forwards == [4]                          # all four remembered
    stack.prefetch(imgs[:2] + [_image(30, 40, seed=9)], "ground")   # sizes differ: the new one alone
    assert forwards == [4, 1]


def test_localizer_prefetch_passes_the_left_images_once():
    from types import SimpleNamespace

    from satloc.localizers.database import Localizer
    from satloc.sequence import Frame

    seen = []
    ext = SimpleNamespace(prefetch=lambda images, view: seen.append((len(images), view)))
    frames = [Frame(_image(8, 8, s), _image(8, 8, s + 1)) for s in range(3)]
    Localizer.prefetch(SimpleNamespace(extractor=ext), frames)
    Localizer.prefetch(SimpleNamespace(extractor=ext), frames[:1])       # one frame: nothing to batch
    Localizer.prefetch(SimpleNamespace(extractor=object()), frames)      # an extractor that cannot batch
    assert seen == [(3, "ground")]


def test_tiling_matches_whole_image(predictor, residential_tile):
    img = np.ascontiguousarray(residential_tile[0][:300, :260])
    tiled = FCNPredictor(tile=128, margin=24)(img, "satellite")
    whole = predictor(img, "satellite")
    assert tiled.scores.shape == whole.scores.shape == (NUM_CLASSES, 300, 260)
    assert (tiled.scores.argmax(0) == whole.scores.argmax(0)).mean() > 0.95


def test_shipped_weights_load_with_weights_only():
    data = torch.load(DEFAULT_WEIGHTS, map_location="cpu", weights_only=True)
    assert data["format"] == FORMAT and data["num_classes"] == NUM_CLASSES
    assert set(data["views"]) == {"ground", "satellite"}
    assert DEFAULT_WEIGHTS.stat().st_size < 4 * 2**20


def test_ground_accuracy_on_rendered_frame(predictor):
    import gymnasium as gym

    import satloc_env  # noqa: F401  (registers the env)

    env = gym.make("satloc/SatLoc-v0", scene="city", labels=True, localizer=None)
    obs, _ = env.reset(seed=12345, options={"start_s_m": 300.0, "occlusion": 0.4, "appearance": 0.4})
    for _ in range(5):
        obs, *_ = env.step(env.unwrapped.autopilot_action())
    env.close()
    pred = SemanticFeatures(predictor=predictor)(obs["left"], "ground").argmax(axis=2)
    assert (pred == obs["labels"]).mean() > GROUND_FLOOR


def test_satellite_accuracy_on_tile_crop(predictor, residential_tile):
    img, lab = residential_tile
    pred = SemanticFeatures(predictor=predictor)(img, "satellite").argmax(axis=2)
    assert (pred == lab).mean() > SATELLITE_FLOOR


class _Halves(nn.Module):
    """Five-class scores at half resolution: class 0 on the left half, class 3 on the right."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n, _, h, w = x.shape
        s = torch.zeros(n, 5, max(1, h // 2), max(1, w // 2))
        s[:, 0, :, : s.shape[3] // 2] = 10.0
        s[:, 3, :, s.shape[3] // 2:] = 10.0
        return s


def test_plugged_in_module():
    f = SemanticFeatures(model=_Halves())
    assert f.dim == 5
    out = f(_image(20, 40), "satellite")
    assert out.shape == (20, 40, 5) and out.dtype == np.float32
    np.testing.assert_allclose(out.sum(axis=2), 1.0, atol=1e-5)
    assert out[:, :15].argmax(axis=2).max() == 0 and (out[:, 25:].argmax(axis=2) == 3).all()

    class Dict(nn.Module):  # torchvision's segmentation models return {"out": scores}
        def forward(self, x):
            return {"out": _Halves()(x)}

    g = SemanticFeatures(view_models={"ground": Dict()}, num_classes=5)
    assert g(_image(8, 8), "ground").shape == (8, 8, 5)
    with pytest.raises(ConfigError, match="satellite"):
        g(_image(8, 8), "satellite")
    with pytest.raises(ConfigError):
        SemanticFeatures(view_models={"aerial": _Halves()})
    with pytest.raises(ConfigError):
        SemanticFeatures(model=_Halves(), view_models={"ground": _Halves()})


def test_project_net_plugs_in_as_a_module():
    net = SegEdgeNet(NUM_CLASSES, (8, 16)).eval()
    f = SemanticFeatures(model=net)
    assert f.dim == NUM_CLASSES and f(_image(30, 45), "ground").shape == (30, 45, NUM_CLASSES)


def test_save_load_roundtrip(tmp_path):
    torch.manual_seed(0)
    nets = {v: ViewNet(SegEdgeNet(NUM_CLASSES, (8, 16, 24)).eval(), scale)
            for v, scale in (("ground", 0.5), ("satellite", 1.0))}
    path = tmp_path / "w.pt"
    save_fcn(path, nets, {"note": "test"})
    loaded, training = load_fcn(path)
    assert training == {"note": "test"} and loaded["ground"].input_scale == 0.5
    x = torch.rand(1, 3, 40, 50)
    with torch.inference_mode():
        a, b = nets["satellite"].net(x), loaded["satellite"].net(x)
    torch.testing.assert_close(a, b, atol=0.05, rtol=0.05)  # weights are stored as float16


def test_bad_weight_files_raise_format_error(tmp_path):
    damaged = tmp_path / "damaged.pt"
    good = tmp_path / "good.pt"
    save_fcn(good, {"ground": ViewNet(SegEdgeNet(NUM_CLASSES, (8, 16)), 1.0)})
    damaged.write_bytes(good.read_bytes()[:300])
    foreign = tmp_path / "foreign.pt"
    torch.save({"weight": torch.zeros(3)}, foreign)
    pickled = tmp_path / "pickled.pt"
    torch.save({"format": FORMAT, "net": nn.Linear(2, 2)}, pickled)   # needs unpickling code: refused
    other = tmp_path / "other_version.pt"
    data = torch.load(good, weights_only=True)
    data["version"] = 99
    torch.save(data, other)
    text = tmp_path / "text.pt"
    text.write_text("not weights")
    for path in (damaged, foreign, pickled, other, text, tmp_path / "missing.pt"):
        with pytest.raises(FormatError, match=path.name):
            FCNPredictor(path)


def test_edge_model_file_missing_raises_config_error(tmp_path):
    with pytest.raises(ConfigError, match="model.yml.gz"):
        EdgeFeatures(model_file=tmp_path / "model.yml.gz")


@pytest.mark.skipif(hasattr(cv2, "ximgproc"), reason="this OpenCV has ximgproc")
def test_edge_model_file_without_ximgproc_raises_config_error(tmp_path):
    model = tmp_path / "model.yml.gz"
    model.write_bytes(b"")
    with pytest.raises(ConfigError, match="ximgproc"):
        EdgeFeatures(model_file=model)


def test_default_extractors_share_one_predictor():
    assert SemanticFeatures().predictor is EdgeFeatures().predictor


def test_label_boundaries():
    lab = torch.zeros(1, 4, 6, dtype=torch.uint8)
    lab[0, :, 3:] = 2
    edge, valid = label_boundaries(lab)
    assert edge[0, :, 2:4].all() and not edge[0, :, :2].any() and not edge[0, :, 4:].any() and valid.all()
    lab[0, 3, 0] = 255   # ignored pixel: it and its 4-neighbours are invalid
    _, valid = label_boundaries(lab)
    assert not valid[0, 3, 0] and not valid[0, 3, 1] and not valid[0, 2, 0] and valid[0, 2, 1] and valid.sum() == 21


def test_tiny_training_run_decreases_loss():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    palette = np.random.default_rng(1).integers(0, 256, (NUM_CLASSES, 3))

    def batches(r: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Random axis-aligned rectangles, each class with its own colour."""
        lab = np.zeros((4, 32, 32), np.uint8)
        for k in range(4):
            for _ in range(4):
                y, x = r.integers(0, 24, 2)
                lab[k, y:y + r.integers(4, 16), x:x + r.integers(4, 16)] = r.integers(1, NUM_CLASSES)
        return palette[lab].astype(np.uint8), lab

    net = SegEdgeNet(NUM_CLASSES, (8, 16))
    cfg = TrainConfig(lr=1e-2)
    _, lab = batches(np.random.default_rng(2))
    losses = train_view(net, batches, class_weights(lab), 60, cfg, rng, "tiny", progress=False)
    assert np.mean(losses[-10:]) < 0.6 * np.mean(losses[:5])


def test_lane_offset_range_is_a_field_and_bounds_the_draw():
    from satloc.config import from_dict, to_dict
    from satloc.errors import ConfigError
    from satloc_env.experiments.train_features import _episode_options, train_features

    # the shipped weights' configuration (no field) reads as the range they were trained with
    assert from_dict(TrainConfig, {k: v for k, v in to_dict(TrainConfig()).items() if k != "lane_offset_m"},
                     "cfg").lane_offset_m == 3.5
    offsets = [_episode_options(s, 1.0, 2.5)["lane_offset_m"] for s in range(200)]
    assert max(abs(o) for o in offsets) <= 2.5 and max(abs(o) for o in offsets) > 2.0
    assert [_episode_options(s, 1.0)["lane_offset_m"] for s in range(5)] == \
        [_episode_options(s, 1.0, 3.5)["lane_offset_m"] for s in range(5)]
    with pytest.raises(ConfigError, match="lane_offset_m"):
        train_features("unused", ["fcn_train/town_a"], [], {"lane_offset_m": -1.0}, progress=False)


def test_the_feature_identity_hashes_the_weights_the_network_loads():
    from satloc.features import fcn, pixelwise

    assert pixelwise.DEFAULT_WEIGHTS == fcn.DEFAULT_WEIGHTS   # named twice: pixelwise imports no torch
