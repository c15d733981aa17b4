"""Where torch runs: the ``device`` setting of FCN training, projection learning and feature extraction.

A setting is ``"auto"`` (the default: the current CUDA device when ``torch.cuda.is_available()``, else the
CPU), ``"cpu"``, ``"cuda"`` or ``"cuda:N"``. Models and tensors go to the device; results come back as numpy
arrays on the CPU, and saved weights stay CPU tensors. On the CPU the computation is the one it always was
(torch's thread settings, e.g. :func:`satloc.features.fcn.torch_threads`, still apply).

The device is how a stage runs, not what it makes: the configs mark it with :func:`device_field`, and
:func:`satloc.config.to_dict` with ``runtime=False`` leaves it out of the keys of cached stages.

Checking a setting's spelling (:func:`check_device`, in the configs' ``__post_init__``) does not import
torch; :func:`resolve_device` does, and only it asks whether CUDA is there, so a config naming ``"cuda"``
can be read on a machine without one.
"""
from __future__ import annotations

import dataclasses
import re
from typing import TYPE_CHECKING, Any

from .errors import ConfigError

if TYPE_CHECKING:
    import torch

#: the allowed values, as error messages name them
DEVICES = '"auto", "cpu", "cuda" or "cuda:N"'
_SPELLING = re.compile(r"auto|cpu|cuda(:[0-9]+)?")
#: the help of the command line's --device options
HELP = "where torch runs: auto (the default: CUDA when it is available, else the CPU), cpu, cuda or cuda:N"


def device_field() -> Any:
    """A config's ``device: str = device_field()``: ``"auto"`` by default, marked as a runtime setting."""
    return dataclasses.field(default="auto", metadata={"runtime": True})


def check_device(spec: Any, name: str = "device") -> str:
    """``spec`` if it is spelled as a device setting; else :class:`ConfigError` naming field ``name``."""
    if not isinstance(spec, str) or not _SPELLING.fullmatch(spec):
        raise ConfigError(f"{name}: expected {DEVICES}, got {spec!r}")
    return spec


def resolve_device(spec: "str | torch.device", name: str = "device") -> "torch.device":
    """The torch device of a setting: ``"auto"`` is ``cuda`` (torch's current CUDA device) if CUDA is
    available, else the CPU.

    A setting asking for CUDA where it is not available, or for a CUDA device this machine does not have,
    raises :class:`ConfigError` naming field ``name``, as does a misspelled one. Where torch is built with
    CUDA, asking whether it is available starts the CUDA driver, after which a ``fork``-ed child cannot use
    CUDA (torch's "poisoned fork"): in such a child ``"auto"`` is the CPU and ``"cuda"`` an error (children
    started with ``spawn`` can use it). A CPU-only torch build asks nothing of a driver."""
    import torch

    spec = check_device(str(spec) if isinstance(spec, torch.device) else spec, name)
    if spec == "cpu":
        return torch.device("cpu")
    available = torch.cuda.is_available()
    bad_fork = available and getattr(torch.cuda, "_is_in_bad_fork", lambda: False)()
    if spec == "auto":
        return torch.device("cuda" if available and not bad_fork else "cpu")
    if not available:
        raise ConfigError(f"{name}: {spec!r} asks for CUDA, and CUDA is not available here (torch "
                          f"{torch.__version__}, built for CUDA {torch.version.cuda or 'none'}); use \"auto\" or "
                          f"\"cpu\"")
    if bad_fork:
        raise ConfigError(f"{name}: {spec!r}: this process was forked from one that has used CUDA, where CUDA "
                          f"cannot start again; start it with spawn, or use \"auto\" or \"cpu\"")
    dev = torch.device(spec)
    if dev.index is not None and dev.index >= torch.cuda.device_count():
        raise ConfigError(f"{name}: {spec!r}: this machine has {torch.cuda.device_count()} CUDA device(s), "
                          f"cuda:0 to cuda:{torch.cuda.device_count() - 1}")
    return dev
