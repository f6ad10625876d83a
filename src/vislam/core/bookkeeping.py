"""Per-landmark bookkeeping of the estimators, sized by what is in view.

A drive of ``T`` frames has tens of thousands of landmark ids, but only a hundred or so
are tracked at any frame. Everything here therefore keeps rows for the *live* ids only
(tracks in progress, landmarks waiting for initialization, the previous frame's
pixels), so the working memory of a run does not grow with the length of the drive or
the number of ids in the dataset:

* :class:`IdTable` — columns of per-id values for the live ids; a lookup is a binary
  search in the sorted live ids; freed rows are reused.
* :class:`TrackTable` — the gate and observation counters of each track in progress.
* :class:`RepeatDetector` — flags observations that repeat the previous frame's pixels.
* :class:`MapBuilder` — the estimated map, in fixed-size chunks (it is the output).

The one thing that cannot be bounded is the output itself: the trajectory (one pose per
frame) and the map (one entry per track).
"""

from __future__ import annotations

import numpy as np

from vislam.core.results import LandmarkMap, RunStats

__all__ = ["IdTable", "TrackTable", "RepeatDetector", "MapBuilder", "in_sorted", "sorted_positions", "sorted_lookup",
           "admitted_count"]


def sorted_positions(a: np.ndarray, sorted_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(position in the increasing ``sorted_b`` of each element of ``a``, whether it is
    there). Positions of absent elements are clipped into range (all 0, and not valid
    indices, when ``sorted_b`` is empty)."""
    if sorted_b.size == 0:
        return np.zeros(np.shape(a), dtype=np.int64), np.zeros(np.shape(a), dtype=bool)
    pos = sorted_b.searchsorted(a)  # (the method: numpy's function wrapper costs as much as the search here)
    np.minimum(pos, sorted_b.size - 1, out=pos)
    return pos, sorted_b[pos] == a


def sorted_lookup(a: np.ndarray, sorted_keys: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``values[i]`` where ``a == sorted_keys[i]`` (keys increasing), −1 where ``a`` is absent."""
    pos, hit = sorted_positions(np.asarray(a, dtype=np.int64), sorted_keys)
    return np.where(hit, values[pos], -1) if sorted_keys.size else np.full(np.shape(a), -1, dtype=np.int64)


def in_sorted(a: np.ndarray, sorted_b: np.ndarray) -> np.ndarray:
    """``np.isin(a, sorted_b)`` for an increasing ``sorted_b``, by binary search (the
    sizes here are a few hundred, where this is several times faster)."""
    return sorted_positions(a, sorted_b)[1]


#: Column specification: name -> (shape of one row, dtype, initial value of a new row).
ColumnSpec = dict[str, tuple[tuple[int, ...], type, object]]


class IdTable:
    """Rows of per-id columns for a changing set of live ids.

    ``rows(ids)`` maps ids to row indices (−1 when not live); ``table[name][rows]``
    reads or writes a column. Columns are reallocated when the table grows (by 25 %,
    so capacity stays near the largest number of ids live at once): index them through
    ``table[name]`` after every :meth:`add`, never keep a column across one.
    """

    GROWTH = 1.25

    def __init__(self, columns: ColumnSpec, capacity: int = 64):
        self._spec = dict(columns)
        capacity = max(int(capacity), 1)
        self._cols = {name: np.full((capacity,) + shape, fill, dtype=dt) for name, (shape, dt, fill) in self._spec.items()}
        self._free = np.ones(capacity, dtype=bool)
        self._keys = np.zeros(0, dtype=np.int64)  # live ids, sorted
        self._rows = np.zeros(0, dtype=np.int64)  # row of each live id

    def __len__(self) -> int:
        return int(self._keys.size)

    def __getitem__(self, name: str) -> np.ndarray:
        return self._cols[name]

    @property
    def capacity(self) -> int:
        return int(self._free.size)

    @property
    def ids(self) -> np.ndarray:
        """(L,) the live ids, sorted."""
        return self._keys

    @property
    def live_rows(self) -> np.ndarray:
        """(L,) the row of each of :attr:`ids`."""
        return self._rows

    def rows(self, ids: np.ndarray) -> np.ndarray:
        """Row of each id, −1 for ids that are not live."""
        return sorted_lookup(ids, self._keys, self._rows)

    def add(self, ids: np.ndarray) -> np.ndarray:
        """Make ``ids`` (distinct, not live) live with every column at its initial value;
        return their rows."""
        ids = np.asarray(ids, dtype=np.int64).ravel()
        k = ids.size
        if k == 0:
            return np.zeros(0, dtype=np.int64)
        free = np.flatnonzero(self._free)
        if free.size < k:
            self._grow(self.capacity + k - free.size)
            free = np.flatnonzero(self._free)
        rows = free[:k]
        self._free[rows] = False
        for name, (_, _, fill) in self._spec.items():
            self._cols[name][rows] = fill
        keys = np.concatenate([self._keys, ids])
        order = np.argsort(keys, kind="stable")
        self._keys = keys[order]
        self._rows = np.concatenate([self._rows, rows])[order]
        return rows

    def remove(self, ids: np.ndarray) -> None:
        """Forget ``ids`` (those that are not live are ignored); their rows are reused."""
        ids = np.asarray(ids, dtype=np.int64).ravel()
        if ids.size == 0 or self._keys.size == 0:
            return
        pos, hit = sorted_positions(ids, self._keys)
        gone = np.zeros(self._keys.size, dtype=bool)
        gone[pos[hit]] = True
        self._free[self._rows[gone]] = True
        self._keys = self._keys[~gone]
        self._rows = self._rows[~gone]

    def _grow(self, needed: int) -> None:
        capacity = max(int(needed), int(np.ceil(self.GROWTH * self.capacity)))
        for name, (shape, dt, fill) in self._spec.items():
            col = np.full((capacity,) + shape, fill, dtype=dt)
            col[: self.capacity] = self._cols[name]
            self._cols[name] = col
        free = np.ones(capacity, dtype=bool)
        free[: self._free.size] = self._free
        self._free = free


class TrackTable(IdTable):
    """The tracks in progress: observation and gate counters, first and last frame.

    A rejected landmark keeps its row (flag ``rejected``) while its track goes on, so
    that its later observations are ignored; :meth:`end_unseen_rejections` drops it
    once it is out of view (seen again later, it would start a new track).
    ``extra`` adds estimator-specific columns (e.g. the drift test's sums).
    """

    COLUMNS: ColumnSpec = {"nobs": ((), np.int64, 0), "ngated": ((), np.int64, 0),
                           "consecutive": ((), np.int64, 0), "first": ((), np.int64, -1),
                           "last": ((), np.int64, -1), "rejected": ((), np.bool_, False)}

    def __init__(self, extra: ColumnSpec | None = None, capacity: int = 64):
        super().__init__({**self.COLUMNS, **(extra or {})}, capacity)

    def lookup(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row of each id's track, −1 when none; whether that track is rejected)."""
        rows = self.rows(ids)
        return rows, (rows >= 0) & self["rejected"][np.maximum(rows, 0)]

    def started(self, ids: np.ndarray, t: int) -> np.ndarray:
        """Start tracks for ``ids`` at frame t (their first observation); return their rows."""
        rows = self.add(ids)
        self["nobs"][rows] = 1
        self["first"][rows] = t
        self["last"][rows] = t
        return rows

    def updated(self, ids: np.ndarray, ok: np.ndarray, t: int, stats: RunStats, max_consecutive: int,
                rows: np.ndarray | None = None) -> np.ndarray:
        """Record the gate outcome of one observation per id (``rows``: their rows, if
        known); return the ids to reject (flagged rejected here)."""
        rows = self.rows(ids) if rows is None else rows
        good, gated = rows[ok], rows[~ok]
        self["nobs"][good] += 1
        self["last"][good] = t
        self["ngated"][gated] += 1
        self["consecutive"][good] = 0
        self["consecutive"][gated] += 1
        stats.observations_used += int(ok.sum())
        stats.observations_gated += int((~ok).sum())
        if not max_consecutive:
            return ids[:0]
        bad = self["consecutive"][rows] >= max_consecutive
        self["rejected"][rows[bad]] = True
        stats.landmarks_rejected += int(bad.sum())
        return ids[bad]

    def entry(self, ids: np.ndarray, rows: np.ndarray | None = None) -> tuple:
        """(n_observations, n_gated, first_frame, last_frame) of the tracks of ``ids``
        (``rows``: their rows, if known)."""
        rows = self.rows(ids) if rows is None else rows
        return self["nobs"][rows], self["ngated"][rows], self["first"][rows], self["last"][rows]

    def end_unseen_rejections(self, ids_seen: np.ndarray) -> None:
        """Drop the rejected tracks whose landmark is not observed in this frame
        (``ids_seen`` increasing)."""
        rejected = self._keys[self["rejected"][self._rows]]
        if rejected.size:
            self.remove(rejected[~in_sorted(rejected, ids_seen)])


class FrameRepeats:
    """The repeat rule of :meth:`vislam.core.sequence.StereoObservations.repeated_mask`,
    online: called frame by frame with ``(t, ids, z)``, it returns the (n,) repeat mask
    of the frame. It keeps the previous frame's observations and the median motion of
    its tracks; :meth:`set_motion` gives it the odometry of the next interval (with a
    ``camera``; without one, integer pixels count as repeats only where new tracks
    start). Memory: the previous frame's observations."""

    def __init__(self, camera=None):
        self.camera = camera
        self._t = -2
        self._ids = np.zeros(0, dtype=np.int64)
        self._z = np.zeros((0, 4))
        self._flow = float("nan")
        self._flow_inputs = None
        self._motion = None

    def set_motion(self, dt_s: float, linear_velocity, angular_velocity) -> None:
        """The interval (s) and IMU sample that end at the next frame."""
        if self.camera is not None:  # the norms are taken only when a frame has repeats (_motion_now)
            self._motion = (float(dt_s), np.array(linear_velocity, dtype=np.float64),
                            np.array(angular_velocity, dtype=np.float64))

    def _motion_now(self):
        """(τ, |v|, |ω|, camera) of the interval set by :meth:`set_motion`, or None."""
        if self._motion is None:
            return None
        dt, v, w = self._motion
        return dt, float(np.linalg.norm(v)), float(np.linalg.norm(w)), self.camera

    def _previous_flow(self) -> float:
        """Median pixel motion (uL, vL) of the tracks continuing at the previous call (NaN: none)."""
        if self._flow_inputs is not None:
            cur, prev = self._flow_inputs
            flow = np.hypot(cur[:, 0] - prev[:, 0], cur[:, 1] - prev[:, 1])
            self._flow = float(np.median(flow)) if flow.size else float("nan")
            self._flow_inputs = None
        return self._flow

    def __call__(self, t: int, ids: np.ndarray, z: np.ndarray) -> np.ndarray:
        from vislam.core.sequence import repeat_decision

        rep = np.zeros(ids.size, dtype=bool)
        flow = None
        if self._t == t - 1 and ids.size and self._ids.size:
            pos, hit = sorted_positions(ids, self._ids)
            c = np.flatnonzero(hit)
            prev = self._z[pos[c]]
            cur = z[c]
            equal = (prev == cur).all(axis=1)
            if equal.any():
                rep[c], _ = repeat_decision(cur, equal, int(ids.size - c.size), self._previous_flow(), self._motion_now())
            flow = (cur, prev)
        # the median motion of this step's tracks is needed only if the next frame has
        # bit-identical pixels: kept as its inputs, computed then (_previous_flow)
        self._flow, self._flow_inputs = float("nan"), flow
        self._t, self._ids, self._z = t, ids, z
        self._motion = None
        return rep


class RepeatDetector(FrameRepeats):
    """Flags, frame by frame, observations that repeat the same landmark's observation
    in the previous frame (:class:`FrameRepeats`, the rule of
    :meth:`vislam.core.sequence.StereoObservations.repeated_mask`) and counts them in
    ``stats.observations_repeated``. Memory: the previous frame's observations."""

    def __init__(self, enabled: bool, stats: RunStats, camera=None):
        super().__init__(camera)
        self.enabled = enabled
        self.stats = stats

    def __call__(self, t: int, ids: np.ndarray, z: np.ndarray) -> np.ndarray:
        """``ids`` strictly increasing (as in :class:`StereoObservations`), ``z`` (n, 4)."""
        if not self.enabled:
            return np.zeros(ids.size, dtype=bool)
        rep = super().__call__(t, ids, z)
        self.stats.observations_repeated += int(rep.sum())
        return rep


class MapBuilder:
    """Collects frozen landmark entries (marginalized, rejected or final) in fixed-size
    chunks of columns: no per-entry small arrays, no doubling slack, and :meth:`build`
    frees each column's chunks as soon as its sorted copy exists.

    The ``track`` number of an entry is its rank among the entries of the same id,
    ordered by first frame (tracks of one id never overlap)."""

    _COLUMNS = {"ids": ((), np.int64), "p": ((3,), np.float64),
                "cov": ((3, 3), np.float64), "nobs": ((), np.int64), "ngated": ((), np.int64),
                "first": ((), np.int64), "last": ((), np.int64), "status": ((), np.uint8),
                "v": ((3,), np.float64)}
    CHUNK = 4096

    def __init__(self):
        self.n = 0
        self._chunks: list[dict[str, np.ndarray]] = []

    def _new_chunk(self) -> dict[str, np.ndarray]:
        chunk = {k: np.zeros((self.CHUNK,) + shape, dtype=dt) for k, (shape, dt) in self._COLUMNS.items()}
        self._chunks.append(chunk)
        return chunk

    def add(self, ids, p, cov, nobs, ngated, first, last, status, v=None) -> None:
        """Append k entries: ``ids`` (k,), ``p`` (k, 3), ``cov`` (k, 3, 3), the counts and
        frames (k,) or scalars, ``status`` one value or (k,), ``v`` (k, 3) or None (zero)."""
        ids = np.asarray(ids)
        k = ids.size
        values = {"ids": ids, "p": np.asarray(p).reshape(k, 3), "cov": np.asarray(cov).reshape(k, 3, 3),
                  "nobs": np.asarray(nobs), "ngated": np.asarray(ngated), "first": np.asarray(first),
                  "last": np.asarray(last), "status": np.asarray(status),
                  "v": np.zeros(()) if v is None else np.asarray(v).reshape(k, 3)}
        done = 0
        while done < k:
            offset = self.n % self.CHUNK
            chunk = self._chunks[-1] if offset else self._new_chunk()
            m = min(k - done, self.CHUNK - offset)
            for key, value in values.items():
                # arrays are sliced, scalars (one status for all, no velocities) broadcast
                chunk[key][offset:offset + m] = value[done:done + m] if value.ndim else value
            done += m
            self.n += m

    def snapshot(self) -> LandmarkMap:
        """The map so far, sorted as by :meth:`build`, leaving the builder as it is."""
        copy = MapBuilder()
        copy.n = self.n
        copy._chunks = [{k: v.copy() for k, v in chunk.items()} for chunk in self._chunks]
        return copy.build()

    def build(self) -> LandmarkMap:
        """The map sorted by (id, track); each column's chunks are released once its
        sorted copy exists."""
        n = self.n

        def column(key: str) -> np.ndarray:
            shape, dt = self._COLUMNS[key]
            parts = [c.pop(key) for c in self._chunks]
            return np.concatenate(parts)[:n] if parts else np.zeros((0,) + shape, dtype=dt)

        ids, first = column("ids"), column("first")
        order = np.lexsort((first, ids))
        out = {"ids": ids[order], "first": first[order]}
        del ids, first
        # rank within each id: position minus the position of the id's first entry
        starts = np.flatnonzero(np.r_[True, out["ids"][1:] != out["ids"][:-1]]) if n else np.zeros(0, dtype=np.int64)
        track = np.arange(n, dtype=np.int64)
        if n:
            track -= np.repeat(starts, np.diff(np.r_[starts, n]))
        for key in self._COLUMNS:
            if key not in out:
                out[key] = column(key)[order]
        self._chunks, self.n = [], 0
        return LandmarkMap(ids=out["ids"], track=track, p_lm_in_world=out["p"], covariance=out["cov"],
                           n_observations=out["nobs"], n_gated=out["ngated"], first_frame=out["first"],
                           last_frame=out["last"], status=out["status"], v_lm_in_world=out["v"])


def admitted_count(n_candidates: int, room: int | None, stats: RunStats) -> int:
    """How many of ``n_candidates`` new landmarks (ids increasing: the lowest first) enter a
    state or window with ``room`` free places (None: all of them); the others wait, counted
    in ``stats.observations_state_full`` and ``stats.frames_state_full``
    (``max_landmarks_in_state``, the SLAM EKF and the smoother alike)."""
    if room is None or n_candidates <= room:
        return n_candidates
    stats.observations_state_full += int(n_candidates - room)
    stats.frames_state_full += 1
    return room
