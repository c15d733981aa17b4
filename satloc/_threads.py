"""Thread-pool hygiene for the per-query hot path.

numpy's OpenBLAS (and the other BLAS builds that torch, faiss and scipy bring along) start their worker
threads on the first matrix product large enough to split, and those workers then busy-wait for the next
one. On a 2-core machine a spinning BLAS worker takes a core from the torch network and OpenCV's stereo
matcher that run next: measured here, the FCN went from 17 ms to 40-47 ms per ground frame inside the
localization loop. The per-query products are small (a few hundred samples times a few dozen dimensions),
so they run on one BLAS thread; the large ones (satellite table, training) keep the default.
"""
from __future__ import annotations

import contextlib
import functools
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterable, Iterator, TypeVar

T = TypeVar("T")
R = TypeVar("R")


@functools.lru_cache(maxsize=1)
def _controller():
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


@contextlib.contextmanager
def single_threaded_blas() -> Iterator[None]:
    """Run the block with every loaded BLAS library limited to one thread (restored afterwards).

    Meant for one thread at a time: some BLAS builds keep the setting per thread (OpenMP ones), others per
    process, so blocks overlapping in several threads can leave a process-wide one at a single thread, which
    costs speed, not correctness. :meth:`Localizer.localize_stream` sets it from the consuming thread only."""
    with _controller().limit(limits=1, user_api="blas"):
        yield


_END = object()  # the end of an iterator, where None may be a value


def overlapped(fn: Callable[[T], R], items: Iterable[T], enabled: bool = True) -> Iterator[R]:
    """``fn(item)`` for each item, in order, with the next item's ``fn`` (and the fetch of the item itself)
    running on a worker thread while the caller works on the current result.

    Most of a query's work after its features (nearest-neighbour search, scoring) runs on one core; the
    next query's stereo and network run meanwhile on the other. Thread settings are left as they are, so
    ``fn`` computes exactly what it computes in the caller's thread (measured on city: the same posteriors,
    bit for bit, 8.6 -> 11 queries/s on 2 cores). ``enabled=False``: plain sequential evaluation."""
    it = iter(items)
    if not enabled:
        for x in it:
            yield fn(x)
        return

    def task():
        try:
            x = next(it)
        except StopIteration:
            return _END
        return fn(x)

    with ThreadPoolExecutor(1, thread_name_prefix="satloc-overlap") as pool:
        fut = pool.submit(task)
        while True:
            r = fut.result()
            if r is _END:
                return
            fut = pool.submit(task)
            yield r
