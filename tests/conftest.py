"""Test-session settings shared by every test file.

With pytest-xdist (the README's test command runs ``-n 2``) each worker is a process of its own; torch's
thread pool would otherwise start one thread per core in every worker, and the workers' threads then fight
for the same cores (measured on the 2-core CI machine: the suite took 9:58 with the default threads and 8:55
with one thread per worker). Each worker gets its share of the cores instead, unless ``OMP_NUM_THREADS`` is
set already; child processes that tests start inherit it.
"""
import os
import sys

_workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1)
if _workers > 1 and "OMP_NUM_THREADS" not in os.environ:
    _threads = max(1, (os.cpu_count() or 1) // _workers)
    os.environ["OMP_NUM_THREADS"] = str(_threads)
    if "torch" in sys.modules:     # imported before this file (by a plugin): set its pool too
        sys.modules["torch"].set_num_threads(_threads)


import gc  # noqa: E402

import pytest  # noqa: E402

#: per-process caches of built worlds (functions with functools.lru_cache), by module: at variety 1 a scene with
#: its meshes and textures holds 1-2 GB, and one xdist worker that keeps four scenes and two revisit worlds from
#: earlier test files reached 13-15 GB and was killed for memory on the 23 GB machine
_CACHES = {"satloc_env.world.scene": ("_cached_scene",), "satloc_env.world.revisit": ("_changed_world",),
           "satloc_env.envs.auto_localizer": ("_load",)}


def _free_built_worlds() -> None:
    for mod, names in _CACHES.items():
        m = sys.modules.get(mod)
        for name in names if m is not None else ():
            getattr(m, name).cache_clear()
    gc.collect()


@pytest.fixture(autouse=True, scope="module")
def _free_built_worlds_after_each_file():
    """After each test file, drop the worlds the process cached (a later file reads a scene back from the disk
    cache in a fraction of a second), so a worker holds what one file needs, not what every file before it
    built."""
    yield
    _free_built_worlds()


@pytest.fixture()
def free_worlds_after_each_test():
    """The same after each test, for a file whose tests build several worlds each (``pytestmark =
    pytest.mark.usefixtures("free_worlds_after_each_test")``): test_compare's held together took one process to
    18 GB of its peak on the 23 GB machine."""
    yield
    _free_built_worlds()
