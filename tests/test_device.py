"""The ``device`` setting (satloc.device): "auto" (CUDA when available, else the CPU), "cpu", "cuda", "cuda:N".

Here (and on CI) there is no CUDA: "auto" is the CPU and must compute exactly what "cpu" computes; asking for
CUDA is a one-line configuration error. The tests at the end run only where CUDA is available."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from test_method import synthetic_dictionary

from satloc import ConfigError
from satloc.config import from_dict, to_dict
from satloc.device import check_device, resolve_device
from satloc.features import make_extractor
from satloc.features.fcn import FCNPredictor, SegEdgeNet, ViewNet, default_predictor, load_fcn, save_fcn
from satloc.features.projection import ProjectionConfig, train_projections
from satloc.labels import NUM_CLASSES
from satloc.localizers.database import LocalizerConfig
from satloc.pipeline import BuildConfig
from satloc_env.cli import main
from satloc_env.experiments.train_features import TrainConfig, class_weights, train_features, train_view

CUDA = torch.cuda.is_available()
no_cuda = pytest.mark.skipif(CUDA, reason="CUDA is available here")
needs_cuda = pytest.mark.skipif(not CUDA, reason="needs CUDA")
CONFIGS = (BuildConfig, ProjectionConfig, LocalizerConfig, TrainConfig)


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _image(h: int, w: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def test_resolve_device():
    assert resolve_device("auto").type == ("cuda" if CUDA else "cpu")
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(torch.device("cpu")) == torch.device("cpu")
    for bad in ("bogus", "CPU", "cuda:", "cuda:x", "gpu", "", " cpu", None, 0):
        with pytest.raises(ConfigError, match=r'^train\.device: expected "auto", "cpu", "cuda" or "cuda:N", got'):
            resolve_device(bad, "train.device")
    assert check_device("cuda:1") == "cuda:1"     # the spelling is checked without asking for CUDA


@no_cuda
@pytest.mark.parametrize("spec", ["cuda", "cuda:0", "cuda:3"])
def test_cuda_without_cuda_is_a_config_error_naming_the_field(spec):
    with pytest.raises(ConfigError, match=rf"^projection\.device: '{spec}' asks for CUDA, and CUDA is not available"):
        resolve_device(spec, "projection.device")


def test_resolution_where_cuda_is_there(monkeypatch):
    """The CUDA branches, with torch's answers faked (nothing runs on a GPU)."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    monkeypatch.setattr(torch.cuda, "_is_in_bad_fork", lambda: False)
    assert resolve_device("auto") == resolve_device("cuda") == torch.device("cuda")
    assert resolve_device("cuda:1") == torch.device("cuda", 1) and resolve_device("cpu") == torch.device("cpu")
    with pytest.raises(ConfigError, match=r"^device: 'cuda:2': this machine has 2 CUDA device\(s\), cuda:0 to cuda:1"):
        resolve_device("cuda:2")
    # a child forked from a process that has used CUDA cannot start it again: auto falls back to the CPU
    monkeypatch.setattr(torch.cuda, "_is_in_bad_fork", lambda: True)
    assert resolve_device("auto") == torch.device("cpu")
    with pytest.raises(ConfigError, match=r"^device: 'cuda': this process was forked from one that has used CUDA"):
        resolve_device("cuda")


@pytest.mark.parametrize("cls", CONFIGS)
def test_configs_have_a_device_field(cls):
    assert cls().device == "auto" and from_dict(cls, {"device": "cpu"}).device == "cpu"
    assert from_dict(cls, {"device": "cuda:0"}).device == "cuda:0"   # read anywhere, resolved where used
    with pytest.raises(ConfigError, match="unknown key"):
        from_dict(cls, {"devices": "cpu"})
    with pytest.raises(ConfigError, match="expected a string"):
        from_dict(cls, {"device": 0})
    # the device is how a stage runs, not what it makes: cached stages' keys leave it out
    assert "device" in to_dict(cls()) and "device" not in to_dict(cls(), runtime=False)


@pytest.mark.parametrize("cls", (BuildConfig, ProjectionConfig, LocalizerConfig))
def test_frozen_configs_check_the_spelling(cls):
    with pytest.raises(ConfigError, match=r"config\.device: expected .*got 'bogus'"):
        from_dict(cls, {"device": "bogus"})


def test_cache_keys_do_not_depend_on_the_device():
    from satloc_env.envs.auto_localizer import cache_key

    a = cache_key("city", max_frames=20)
    assert a == cache_key("city", max_frames=20, build_config=BuildConfig(device="cpu"),
                          projection_config=ProjectionConfig(device="cuda"))
    assert "device" not in json.dumps(a)


@pytest.mark.skipif(CUDA, reason="auto is CUDA here")
def test_auto_and_cpu_give_identical_fcn_outputs():
    auto, cpu = FCNPredictor(), FCNPredictor(device="cpu")
    assert auto.device == cpu.device == torch.device("cpu")
    for view, img in (("ground", _image(188, 620)), ("satellite", _image(300, 260, 1))):
        a, c = auto(img, view), cpu(img, view)
        assert np.array_equal(a.scores, c.scores) and np.array_equal(a.edge, c.edge)
    a = FCNPredictor(tile=128, margin=24)(_image(300, 260, 1), "satellite")
    c = FCNPredictor(tile=128, margin=24, device="cpu")(_image(300, 260, 1), "satellite")
    assert np.array_equal(a.scores, c.scores) and np.array_equal(a.edge, c.edge)
    assert default_predictor() is default_predictor("cpu")   # one shared predictor per resolved device
    img = _image(60, 90, 2)
    assert np.array_equal(make_extractor("default")(img, "ground"), make_extractor("default", "cpu")(img, "ground"))


@pytest.mark.skipif(CUDA, reason="auto is CUDA here")
def test_auto_and_cpu_give_identical_projections_and_training_steps():
    d = synthetic_dictionary(1500)
    cfg = dict(max_anchors=1000, max_epochs=4, alpha=0.01, lr=0.02)
    a = train_projections(d, ProjectionConfig(**cfg), progress=False)
    c = train_projections(d, ProjectionConfig(**cfg, device="cpu"), progress=False)
    assert np.array_equal(a.W_g, c.W_g) and np.array_equal(a.W_s, c.W_s) and a.loss_curve == c.loss_curve

    imgs, labs = _image(2 * 48, 64, 3).reshape(2, 48, 64, 3), np.random.default_rng(4).integers(0, 5, (2, 48, 64))
    labs = labs.astype(np.uint8)
    states = []
    for device in ("auto", "cpu"):
        torch.manual_seed(0)
        net = SegEdgeNet(NUM_CLASSES, (8, 12)).to(resolve_device(device))
        losses = train_view(net, lambda r: (imgs.copy(), labs.copy()), class_weights(labs), 3, TrainConfig(),
                            np.random.default_rng(5), "t", progress=False)
        states.append((losses, net.state_dict()))
    assert states[0][0] == states[1][0]
    assert all(torch.equal(v, states[1][1][k]) for k, v in states[0][1].items())


@no_cuda
def test_asking_for_cuda_without_it_fails_before_any_work(tmp_path):
    for make in (lambda: FCNPredictor(device="cuda"), lambda: make_extractor("default", "cuda"),
                 lambda: train_projections(synthetic_dictionary(100), ProjectionConfig(device="cuda"), progress=False),
                 lambda: train_features(tmp_path, config={"device": "cuda"}, progress=False)):
        with pytest.raises(ConfigError, match=r"^device: 'cuda' asks for CUDA, and CUDA is not available"):
            make()
    assert not any(tmp_path.iterdir())


def _one_line_error(capsys, pattern: str) -> None:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and pattern in err, err


def test_cli_device_flags_check_their_value(tmp_path, capsys):
    nowhere = str(tmp_path / "nowhere")
    assert main(["build", "--database", nowhere, "--map", nowhere, "--out", nowhere, "--device", "bogus"]) == 2
    _one_line_error(capsys, """satloc: error: config.device: expected "auto", "cpu", "cuda" or "cuda:N", got 'bogus'""")
    assert main(["train-projection", nowhere, "--device", "gpu"]) == 2
    _one_line_error(capsys, "satloc: error: config.device: expected")
    assert main(["localize", nowhere, "--queries", nowhere, "--device", "cuda:x"]) == 2
    _one_line_error(capsys, "satloc: error: config.device: expected")
    assert main(["train-features", "--out", nowhere, "--device", "bogus"]) == 2
    _one_line_error(capsys, "satloc train-features: error: device: expected")
    assert main(["bench", "localize", "--work", nowhere, "--device", "bogus", "--quiet"]) == 2
    _one_line_error(capsys, "satloc: error: device: expected")
    assert not (tmp_path / "nowhere").exists()


@no_cuda
def test_cli_cuda_without_cuda_is_a_one_line_error(tmp_path, capsys):
    assert main(["train-features", "--out", str(tmp_path), "--device", "cuda", "--quiet"]) == 2
    _one_line_error(capsys, "satloc train-features: error: device: 'cuda' asks for CUDA, and CUDA is not available")
    assert main(["bench", "localize", "--work", str(tmp_path), "--device", "cuda", "--quiet"]) == 2
    _one_line_error(capsys, "satloc: error: device: 'cuda' asks for CUDA")


# --- where CUDA is available ------------------------------------------------------------------------------
@needs_cuda
def test_cuda_and_cpu_fcn_outputs_agree(monkeypatch):
    """Probabilities and edge potentials within 1e-3 (cuDNN's convolutions sum in another order), with
    TensorFloat-32 convolutions off (torch's default turns them on for cuDNN: about 1e-3 relative per layer)."""
    monkeypatch.setattr(torch.backends.cudnn, "allow_tf32", False)
    cpu, gpu = FCNPredictor(device="cpu"), FCNPredictor(device="cuda")
    assert next(gpu.views["ground"].net.parameters()).is_cuda
    for view, img in (("ground", _image(188, 620)), ("satellite", _image(300, 260, 1))):
        for tile in (1024, 128):
            cpu.tile = gpu.tile = tile
            cpu.margin = gpu.margin = 24
            a, b = cpu._run(cpu.views[view], img), gpu._run(gpu.views[view], img)
            assert isinstance(b.scores, np.ndarray) and b.scores.dtype == np.float32
            pa, pb = (torch.softmax(torch.from_numpy(s), 0) for s in (a.scores, b.scores))
            assert float((pa - pb).abs().max()) < 1e-3
            assert float((torch.sigmoid(torch.from_numpy(a.edge)) - torch.sigmoid(torch.from_numpy(b.edge))).abs().max()) < 1e-3
    img = _image(60, 90, 2)
    np.testing.assert_allclose(make_extractor("default", "cuda")(img, "ground"),
                               make_extractor("default", "cpu")(img, "ground"), atol=1e-3)


@needs_cuda
def test_projection_learning_and_fcn_training_run_on_cuda(tmp_path):
    d = synthetic_dictionary()
    cfg = dict(max_anchors=2000, max_epochs=8, alpha=0.01, lr=0.02)
    g = train_projections(d, ProjectionConfig(**cfg, device="cuda"), progress=False)
    c = train_projections(d, ProjectionConfig(**cfg, device="cpu"), progress=False)
    assert isinstance(g.W_g, np.ndarray) and g.W_g.dtype == np.float32 and np.all(np.isfinite(g.W_g))
    assert g.loss_curve[-1] < g.loss_curve[0]
    assert g.loss_curve[0] == pytest.approx(c.loss_curve[0], rel=1e-2)   # the same first epoch, up to rounding
    g.save(tmp_path / "p.pt")
    assert torch.load(tmp_path / "p.pt", weights_only=True)["W_g"].device.type == "cpu"

    imgs = _image(2 * 48, 64, 3).reshape(2, 48, 64, 3)
    labs = np.random.default_rng(4).integers(0, 5, (2, 48, 64)).astype(np.uint8)
    net = SegEdgeNet(NUM_CLASSES, (8, 12)).to("cuda")
    losses = train_view(net, lambda r: (imgs.copy(), labs.copy()), class_weights(labs), 3, TrainConfig(),
                        np.random.default_rng(5), "t", progress=False)
    assert len(losses) == 3 and np.all(np.isfinite(losses))
    save_fcn(tmp_path / "w.pt", {"ground": ViewNet(net, 1.0)})        # saved as CPU tensors
    assert next(load_fcn(tmp_path / "w.pt")[0]["ground"].net.parameters()).device.type == "cpu"
