"""The descriptor database: every training view's descriptor with its object and pose, and the
nearest-neighbour search behind recognition.

Search goes through a small registry of indexes with one interface (:class:`DescriptorIndex`):
``exact`` (brute force, numpy; exact and fast enough for the ~10^4 views of a few objects) and
``faiss`` (an HNSW graph from the optional ``faiss-cpu`` package, for databases of 10^5-10^7
views). ``auto`` uses exact below :data:`EXACT_LIMIT` entries.

Recognition (:meth:`DescriptorDB.query`): the k nearest descriptors vote for the object, each
with weight 1 / (distance + eps); the pose is the one of the nearest neighbour of the winning
object (its rotation and offset in the patch's virtual camera, see :mod:`recog.patches`).
"""
from __future__ import annotations

import os
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_tools.errors import ConfigError, FormatError

__all__ = ["DescriptorDB", "DescriptorIndex", "INDEXES", "make_index", "Match", "EXACT_LIMIT"]

EXACT_LIMIT = 200_000
"""Databases up to this size use the exact index under ``auto``."""


class DescriptorIndex(ABC):
    """k-nearest-neighbour search over (N, d) float32 descriptors (squared L2 distances)."""

    name = ""

    @abstractmethod
    def __init__(self, descriptors: np.ndarray):
        ...

    @abstractmethod
    def search(self, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(squared distances (Q, k), indices (Q, k)), nearest first."""


class ExactIndex(DescriptorIndex):
    name = "exact"

    def __init__(self, descriptors: np.ndarray):
        self.x = np.ascontiguousarray(descriptors, dtype=np.float32)
        self.sq = (self.x.astype(np.float64) ** 2).sum(1)

    def search(self, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        q = np.ascontiguousarray(queries, dtype=np.float32)
        d = (q.astype(np.float64) ** 2).sum(1)[:, None] + self.sq[None] - 2.0 * (q @ self.x.T).astype(np.float64)
        k = min(k, len(self.x))
        idx = np.argpartition(d, k - 1, axis=1)[:, :k]
        dd = np.take_along_axis(d, idx, 1)
        o = np.argsort(dd, axis=1, kind="stable")
        return np.maximum(np.take_along_axis(dd, o, 1), 0.0), np.take_along_axis(idx, o, 1)


class FaissIndex(DescriptorIndex):
    name = "faiss"

    def __init__(self, descriptors: np.ndarray):
        try:
            import faiss
        except ImportError:
            raise ConfigError("the faiss index needs the optional package faiss-cpu (pip install faiss-cpu); "
                              "or use --index exact") from None
        x = np.ascontiguousarray(descriptors, dtype=np.float32)
        self.index = faiss.IndexHNSWFlat(x.shape[1], 32)
        self.index.hnsw.efSearch = 128
        self.index.add(x)

    def search(self, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        d, i = self.index.search(np.ascontiguousarray(queries, dtype=np.float32), k)
        return d, i


INDEXES = {"exact": ExactIndex, "faiss": FaissIndex}


def make_index(name: str, descriptors: np.ndarray) -> DescriptorIndex:
    if name == "auto":
        name = "exact" if len(descriptors) <= EXACT_LIMIT else "faiss"
    if name not in INDEXES:
        raise ConfigError(f"unknown index {name!r}; choose one of auto, {', '.join(INDEXES)}")
    return INDEXES[name](descriptors)


@dataclass
class Match:
    """The answer of the database for one query descriptor."""

    object_index: int
    """Winning object (index into the recogniser's objects)."""
    votes: dict
    """Object index -> summed vote weight of the k neighbours."""
    nearest: int
    """Database row of the nearest neighbour of the winning object."""
    distance: float
    """Descriptor distance (L2, not squared) to that neighbour."""
    nearest_by_object: dict = None
    """Object index -> (database row, distance) of its nearest entry among the searched neighbours."""
    poses_by_object: dict = None
    """Object index -> [(row, distance), ...]: its nearest entries with poses at least ``min_angle_deg``
    apart (up to ``per_object``), nearest first: several starting poses for verification."""


@dataclass
class DescriptorDB:
    """Descriptors of the training views with their labels."""

    descriptors: np.ndarray
    """(N, d) float32."""
    obj: np.ndarray
    """(N,) int object index."""
    R_local: np.ndarray
    """(N, 3, 3) rotation in the patch's virtual camera."""
    offset: np.ndarray
    """(N, 3) object centre minus the patch's reference point, virtual camera frame, metres."""
    view: np.ndarray
    """(N,) view index in the training grid."""
    index_name: str = "auto"

    def __post_init__(self):
        self._index: DescriptorIndex | None = None

    def __len__(self) -> int:
        return len(self.obj)

    @property
    def index(self) -> DescriptorIndex:
        if self._index is None:
            self._index = make_index(self.index_name, self.descriptors)
        return self._index

    def query(self, q: np.ndarray, k: int = 5, search: int = 400, per_object: int = 1,
              min_angle_deg: float = 10.0) -> list[Match]:
        """Matches of (Q, d) query descriptors (see the module docstring): the ``k`` nearest vote;
        the ``search`` nearest give each object's nearest entries (for verification)."""
        q = np.atleast_2d(np.asarray(q, np.float32))
        k = max(int(k), 1)
        d2, idx = self.index.search(q, max(k, int(search)))
        out = []
        for drow, irow in zip(d2, idx):
            w: dict[int, float] = {}
            for dd, ii in zip(drow[:k], irow[:k]):
                o = int(self.obj[ii])
                w[o] = w.get(o, 0.0) + 1.0 / (float(np.sqrt(max(dd, 0.0))) + 1e-6)
            near: dict[int, tuple[int, float]] = {}
            poses: dict[int, list[tuple[int, float]]] = {}
            cos_min = np.cos(np.radians(min_angle_deg))
            for dd, ii in zip(drow, irow):
                o, ii = int(self.obj[ii]), int(ii)
                entry = (ii, float(np.sqrt(max(dd, 0.0))))
                near.setdefault(o, entry)
                lst = poses.setdefault(o, [])
                if len(lst) < per_object and all((np.trace(self.R_local[ii].T @ self.R_local[j]) - 1) / 2 < cos_min
                                                 for j, _ in lst):
                    lst.append(entry)
            best = max(w, key=w.get)
            out.append(Match(best, w, near[best][0], near[best][1], near, poses))
        return out

    def save(self, path: str | os.PathLike) -> None:
        import io

        from data_tools.results import atomic_write_bytes
        buf = io.BytesIO()
        np.savez_compressed(buf, descriptors=self.descriptors, obj=self.obj, R_local=self.R_local,
                            offset=self.offset, view=self.view)
        atomic_write_bytes(path, buf.getvalue())

    @classmethod
    def load(cls, path: str | os.PathLike, index_name: str = "auto") -> "DescriptorDB":
        p = Path(path)
        try:
            z = np.load(p)
            db = cls(z["descriptors"].astype(np.float32), z["obj"], z["R_local"], z["offset"], z["view"], index_name)
        except (OSError, ValueError, KeyError) as e:
            raise FormatError(p, f"not a descriptor database ({type(e).__name__})") from None
        if db.descriptors.ndim != 2 or len(db.obj) != len(db.descriptors):
            raise FormatError(p, "descriptor database arrays do not match")
        return db
