"""Keyframe descriptor indexes for loop-closure candidates.

``LshIndex`` — append-only multi-table LSH over 256-bit binary (ORB) descriptors:
each of ``n_tables`` tables keys a descriptor on ``n_bits`` randomly chosen bits (bit
sampling is locality sensitive for the Hamming distance). A keyframe's vote is the number
of query descriptors that share a bucket with one of its descriptors in at least one table.

Storage uses the logarithmic method (docs/references.md §6, the "multi-kd-tree" idea applied to
sorted hash arrays): runs of sorted ``(key, keyframe)`` arrays whose sizes roughly double;
a new keyframe becomes a small run and equal-sized runs are merged. Insertion is amortised
O(log n) per entry and a query costs one binary search per key per run (O(log² n)) plus the
bucket hits, all vectorised with NumPy.

``BruteIndex`` — exhaustive Hamming nearest neighbour against every stored descriptor
(OpenCV BFMatcher); its cost is linear in the map size, kept as the baseline to measure the
LSH index against.
"""

from __future__ import annotations

import cv2
import numpy as np


class LshIndex:
    def __init__(self, n_tables: int = 8, n_bits: int = 16, seed: int = 0, n_desc_bits: int = 256):
        if not 1 <= n_bits <= 40:
            raise ValueError("n_bits must be in 1..40")
        rng = np.random.default_rng(seed)
        self.n_tables = int(n_tables)
        self.n_bits = int(n_bits)
        self.bits = np.stack([rng.choice(n_desc_bits, self.n_bits, replace=False) for _ in range(self.n_tables)])
        self._weights = (1 << np.arange(self.n_bits, dtype=np.int64))
        self._table_offset = np.arange(self.n_tables, dtype=np.int64) << self.n_bits
        self.runs: list[tuple[np.ndarray, np.ndarray]] = []  # (sorted keys int64, keyframe ids int32)
        self.n_keyframes = 0
        self.n_entries = 0

    def keys(self, desc: np.ndarray) -> np.ndarray:
        """(N, n_tables) int64 bucket keys (table id in the high bits) of (N, 32) uint8 descriptors:
        table t's key has bit i set when descriptor bit ``bits[t, i]`` is (packed with
        ``np.packbits``, little bit order, into 8 bytes read as one integer)."""
        desc = np.asarray(desc, np.uint8)
        out = np.empty((len(desc), self.n_tables), np.int64)
        nbytes = (self.n_bits + 7) // 8
        for s in range(0, len(desc), 4096):  # blocks small enough for the cache
            bits = np.unpackbits(desc[s:s + 4096], axis=1)  # (n, 256)
            packed = np.packbits(bits[:, self.bits], axis=-1, bitorder="little")  # (n, L, nbytes)
            wide = np.zeros(packed.shape[:2] + (8,), np.uint8)
            wide[..., :nbytes] = packed
            out[s:s + 4096] = wide.view("<u8")[..., 0].astype(np.int64)
        return out + self._table_offset

    def add(self, kf_id: int, desc: np.ndarray) -> None:
        keys = np.unique(self.keys(desc).ravel())
        run = (keys, np.full(len(keys), kf_id, np.int32))
        self.runs.append(run)
        self.n_keyframes += 1
        self.n_entries += len(keys)
        # merge while the newest run is at least as large as the one before (sizes ~ powers of two)
        while len(self.runs) >= 2 and len(self.runs[-1][0]) >= len(self.runs[-2][0]):
            (k2, v2), (k1, v1) = self.runs.pop(), self.runs.pop()
            k = np.concatenate([k1, k2])
            v = np.concatenate([v1, v2])
            order = np.argsort(k, kind="stable")
            self.runs.append((k[order], v[order]))

    def add_many(self, desc: np.ndarray, starts: np.ndarray) -> None:
        """Keyframes ``n_keyframes, n_keyframes + 1, ...`` at once: keyframe k's descriptors are rows
        ``starts[k]:starts[k + 1]`` of ``desc`` (a loaded map). The same votes as adding them one by
        one, in one pass: the keys of all descriptors, one sort of the (key, keyframe) pairs, one run."""
        starts = np.asarray(starts, np.int64)
        n_new = len(starts) - 1
        if n_new <= 0:
            return
        first = self.n_keyframes
        owner = np.repeat(np.arange(first, first + n_new, dtype=np.int32), np.diff(starts))
        desc = desc[starts[0]:starts[-1]]
        keys = self.keys(desc).ravel()
        owner = np.repeat(owner, self.n_tables)  # rows are in keyframe order
        span = first + n_new
        if (int(self.n_tables) << self.n_bits) * span < 1 << 62:  # (key, keyframe) as one integer: one sort
            pair = np.sort(keys * span + owner)
            keys, owner = pair // span, (pair % span).astype(np.int32)
            new = np.ones(len(pair), bool)
            new[1:] = pair[1:] != pair[:-1]
        else:  # a stable sort keeps keyframe order within a key; drop repeated pairs
            order = np.argsort(keys, kind="stable")
            keys, owner = keys[order], owner[order]
            new = np.ones(len(keys), bool)
            new[1:] = (keys[1:] != keys[:-1]) | (owner[1:] != owner[:-1])
        run = (keys[new], owner[new])
        self.n_keyframes += n_new
        self.n_entries += len(run[0])
        # the new run goes in by size (the logarithmic method's order: larger runs first)
        self.runs.append(run)
        self.runs.sort(key=lambda r: -len(r[0]))

    def votes(self, desc: np.ndarray) -> np.ndarray:
        """Votes per keyframe id (array of length ``n_keyframes``)."""
        out = np.zeros(self.n_keyframes, np.int64)
        if len(desc) == 0 or not self.runs:
            return out
        q = self.keys(desc)  # (N, L)
        qid = np.repeat(np.arange(len(q), dtype=np.int64), self.n_tables)
        q = q.ravel()
        order = np.argsort(q)  # sorted queries make the binary searches cache friendly
        q, qid = q[order], qid[order]
        pairs = []
        for keys, kfs in self.runs:
            lo = np.searchsorted(keys, q, "left")
            hi = np.searchsorted(keys, q, "right")
            cnt = hi - lo
            total = int(cnt.sum())
            if total == 0:
                continue
            start = np.repeat(lo, cnt)
            offs = np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt)
            kf = kfs[start + offs].astype(np.int64)
            pairs.append(np.repeat(qid, cnt) * self.n_keyframes + kf)
        if not pairs:
            return out
        flat = np.concatenate(pairs)  # one vote per (query descriptor, keyframe)
        if len(desc) * self.n_keyframes <= 20_000_000:  # a hit mask is cheaper than sorting
            hit = np.zeros(len(desc) * self.n_keyframes, bool)
            hit[flat] = True
            return hit.reshape(len(desc), self.n_keyframes).sum(axis=0)
        uniq = np.unique(flat)
        return np.bincount(uniq % self.n_keyframes, minlength=self.n_keyframes)

    @property
    def size(self) -> int:
        return self.n_entries


class BruteIndex:
    """Exhaustive baseline: a keyframe's vote = query descriptors whose nearest stored
    descriptor (Hamming) belongs to it and is closer than ``max_hamming``."""

    def __init__(self, max_hamming: int = 64):
        self.max_hamming = int(max_hamming)
        self.desc: list[np.ndarray] = []
        self.owner: list[np.ndarray] = []
        self._all: tuple[np.ndarray, np.ndarray] | None = None
        self.n_keyframes = 0
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)

    def add(self, kf_id: int, desc: np.ndarray) -> None:
        self.desc.append(np.ascontiguousarray(desc, np.uint8))
        self.owner.append(np.full(len(desc), kf_id, np.int64))
        self.n_keyframes += 1
        self._all = None

    def add_many(self, desc: np.ndarray, starts: np.ndarray) -> None:
        """Keyframes ``n_keyframes, ...`` at once (rows ``starts[k]:starts[k + 1]`` of ``desc``)."""
        for k in range(len(starts) - 1):
            self.add(self.n_keyframes, desc[starts[k]:starts[k + 1]])

    def votes(self, desc: np.ndarray) -> np.ndarray:
        out = np.zeros(self.n_keyframes, np.int64)
        if len(desc) == 0 or not self.desc:
            return out
        if self._all is None:
            self._all = (np.concatenate(self.desc), np.concatenate(self.owner))
        train, owner = self._all
        q = np.ascontiguousarray(desc, np.uint8)
        best_d = np.full(len(q), np.inf)
        best_i = np.zeros(len(q), np.int64)
        chunk = 200_000  # OpenCV's matcher indexes at most 2^18 train rows at once
        for s0 in range(0, len(train), chunk):
            ms = self._matcher.match(q, train[s0:s0 + chunk])
            qi = np.array([m.queryIdx for m in ms], np.int64)
            ti = np.array([m.trainIdx for m in ms], np.int64) + s0
            dd = np.array([m.distance for m in ms], float)
            better = dd < best_d[qi]
            best_d[qi[better]] = dd[better]
            best_i[qi[better]] = ti[better]
        ok = best_d < self.max_hamming
        if ok.any():
            out += np.bincount(owner[best_i[ok]], minlength=self.n_keyframes)
        return out

    @property
    def size(self) -> int:
        return int(sum(len(d) for d in self.desc))


def make_index(kind: str, n_tables: int, n_bits: int, seed: int, max_hamming: int = 64):
    if kind == "brute":
        return BruteIndex(max_hamming)
    return LshIndex(n_tables, n_bits, seed)
