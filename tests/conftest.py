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
