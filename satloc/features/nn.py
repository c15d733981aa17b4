"""Nearest-neighbour search over feature vectors (faiss).

Exact search (``IndexFlatL2``) up to ``exact_max`` vectors (brute force costs a query batch about N x D flops, too slow
at query time beyond a few ten thousand entries); above that an HNSW graph (faiss measured fastest
here at high recall, see ``../shared/NOTES-platform.md``). Distances returned are Euclidean (not squared).
"""
from __future__ import annotations

import faiss
import numpy as np

from ..errors import ConfigError


class NNIndex:
    def __init__(self, data: np.ndarray, exact_max: int = 30_000, hnsw_m: int = 32, ef_search: int = 96):
        data = np.ascontiguousarray(data, dtype=np.float32)
        if data.ndim != 2 or len(data) == 0:
            raise ConfigError(f"nearest-neighbour index: need a non-empty (N, D) array, got shape {data.shape}")
        self.n, self.dim = data.shape
        if self.n <= exact_max:
            self.kind = "flat"
            self.index = faiss.IndexFlatL2(self.dim)
        else:
            self.kind = "hnsw"
            self.index = faiss.IndexHNSWFlat(self.dim, hnsw_m)
            self.index.hnsw.efConstruction = 64
            self.index.hnsw.efSearch = ef_search
        # one thread while adding: a multi-threaded HNSW build links the graph in a racy order, and the same
        # data must give the same index (reproducible localizations)
        prev = faiss.omp_get_max_threads()
        faiss.omp_set_num_threads(1)
        try:
            self.index.add(data)
        finally:
            faiss.omp_set_num_threads(prev)

    def search(self, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Distances (Q, k) float32 and ids (Q, k) int64 of the ``k`` nearest neighbours of each query
        (id -1 and distance inf where fewer than ``k`` exist)."""
        q = np.ascontiguousarray(queries, dtype=np.float32)
        if q.ndim != 2 or q.shape[1] != self.dim:
            raise ConfigError(f"nearest-neighbour search: queries of shape {q.shape}, index dimension {self.dim}")
        if len(q) == 0:
            return np.zeros((0, k), np.float32), np.zeros((0, k), np.int64)
        if len(q) < 4096:  # small batches: one thread (OpenMP start-up and spinning cost more than they save)
            prev = faiss.omp_get_max_threads()
            faiss.omp_set_num_threads(1)
            try:
                d2, ids = self.index.search(q, k)
            finally:
                faiss.omp_set_num_threads(prev)
        else:
            d2, ids = self.index.search(q, k)
        d = np.sqrt(np.maximum(d2, 0.0))
        d[ids < 0] = np.inf
        return d, ids
