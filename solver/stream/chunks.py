"""Chunks of a recording and what each worker process keeps of them between passes.

A :class:`StreamProblem` names the chain, the chunk references and a picklable loader; each
worker prepares a chunk once (joint motions, gravity loads, measured poses, batch-last) and may
keep it, and the masks and residuals later passes reuse, in its own caches.
"""

from __future__ import annotations

import dataclasses
import functools
import threading
import uuid
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from solver import lie
from solver.arrays import BoolArray, FloatArray, IntArray
from solver.batch_chain import (
    joint_motions,
    quaternion_rotation,
)
from solver.errors import CalibrationError
from solver.executors import Executor
from solver.gravity import StaticGravityModel, static_gravity_loads
from solver.measurement.models import FullPose
from solver.model import STANDARD_GRAVITY_BASE, KinematicChain

MiB = 1024 * 1024


# --- data: chunks of a recording -----------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ChunkArrays:
    """One chunk of a recording, as arrays (DESIGN.md §3 dataset contract).

    ``joint_positions`` (n, k) rad (m if prismatic), chain order; ``position_m`` (n, 3) marker
    position and ``quaternion_xyzw`` (n, 4) its orientation (scalar last) in the measurement
    frame, None if position-only; ``payload_kg`` (n,) or None; ``first_row``: 0-based index of
    the chunk's first row in the recording.
    """

    joint_positions: FloatArray
    position_m: FloatArray
    quaternion_xyzw: FloatArray | None
    payload_kg: FloatArray | None
    first_row: int

    @property
    def n_rows(self) -> int:
        return int(self.joint_positions.shape[0])


ChunkLoader = Callable[[Any], ChunkArrays]
"""Picklable callable: chunk reference -> :class:`ChunkArrays` (e.g. a Parquet row-group
reader from :mod:`schemas.dataset`; the solver never opens files itself)."""


def row_ranges(n_rows: int, chunk_rows: int) -> tuple[tuple[int, int], ...]:
    """``(start, stop)`` of consecutive chunks of at most ``chunk_rows`` rows."""
    if chunk_rows < 1:
        raise CalibrationError(f"chunk_rows must be positive, got {chunk_rows}")
    return tuple((a, min(a + chunk_rows, n_rows)) for a in range(0, n_rows, chunk_rows))


@dataclass(frozen=True, eq=False)
class ArrayChunks:
    """A :data:`ChunkLoader` over arrays already in memory; references are ``(start, stop)``.

    It carries the arrays, so other processes receive all of them with every pass: for tests
    and small data; large recordings go through a file loader."""

    joint_positions: FloatArray
    position_m: FloatArray
    quaternion_xyzw: FloatArray | None
    payload_kg: FloatArray | None = None

    def __call__(self, ref: tuple[int, int]) -> ChunkArrays:
        a, b = ref
        return ChunkArrays(
            self.joint_positions[a:b],
            self.position_m[a:b],
            None if self.quaternion_xyzw is None else self.quaternion_xyzw[a:b],
            None if self.payload_kg is None else self.payload_kg[a:b],
            a,
        )


@dataclass(frozen=True, eq=False)
class StreamProblem:
    """A recording to calibrate chunk by chunk, and how.

    ``refs``: chunk references in row order for ``load``; ``gravity_base_m_s2`` (3,) in the
    base frame; ``payload_kg`` for chunks without a payload column; ``block_rows``: samples per
    vectorised block inside a chunk (cache-sized working arrays); ``cache_bytes``: prepared
    chunks (joint motions, loads, measured poses, ~290 B/sample for 6 joints) each worker
    process may keep between passes, 0 = re-read every pass (memory then independent of N);
    ``measurement``: what a row measures, :class:`~solver.measurement.FullPose` or
    :class:`~solver.measurement.Position` (the other measurement models are calibrated in
    memory, :mod:`solver.measurement.fit`).
    """

    chain: KinematicChain
    load: ChunkLoader
    refs: tuple[Any, ...]
    measurement: FullPose
    gravity_base_m_s2: FloatArray = field(default_factory=lambda: STANDARD_GRAVITY_BASE.copy())
    payload_kg: float = 0.0
    block_rows: int = 8192
    cache_bytes: int = 512 * MiB
    token: str = field(default_factory=lambda: uuid.uuid4().hex)

    @property
    def residual_dim(self) -> int:
        return self.measurement.dim


# --- per-process caches (one per worker; never shared between processes) -------------------


@dataclass(frozen=True, eq=False)
class Block:
    """A block of prepared samples, batch-last: everything that does not depend on the
    parameters. ``rotation`` (3, 3, b) / ``translation`` (3, b): measured pose."""

    first_row: int
    motions: list[lie.ScrewMotion]
    loads_nm: FloatArray
    rotation: FloatArray | None
    translation: FloatArray

    @property
    def n(self) -> int:
        return int(self.translation.shape[1])

    @property
    def nbytes(self) -> int:
        arrays = [self.loads_nm, self.translation]
        arrays += [self.rotation] if self.rotation is not None else []
        for m in self.motions:
            arrays += [m.angle, m.cos, m.sin]
            arrays += [m.translation] if m.translation is not None else []
        return sum(a.nbytes for a in arrays)

    def subset(self, index: IntArray) -> Block:
        """The samples ``index`` of this block (their own first row is not kept)."""
        motions = [
            dataclasses.replace(
                m,
                angle=m.angle[index],
                cos=m.cos[index],
                sin=m.sin[index],
                translation=None if m.translation is None else m.translation[:, index],
            )
            for m in self.motions
        ]
        rotation = None if self.rotation is None else self.rotation[:, :, index]
        return Block(-1, motions, self.loads_nm[index], rotation, self.translation[:, index])


_PREPARED: OrderedDict[tuple[str, Any], list[Block]] = OrderedDict()
_MASKS: dict[tuple[str, Any, str], list[BoolArray]] = {}
_RESIDUALS: dict[tuple[str, Any], tuple[bytes, list[FloatArray]]] = {}
_GRAVITY: dict[str, StaticGravityModel] = {}
_DERIVED: dict[tuple[str, Any, str], tuple[int, Any]] = {}
_LOCK = threading.Lock()  # Dask may run several tasks of one process in threads


def forget(token: str) -> None:
    """Drop this process's caches of the problem ``token`` (call on every worker when done)."""
    with _LOCK:
        for key in [k for k in _PREPARED if k[0] == token]:
            del _PREPARED[key]
        for mask_key in [k for k in _MASKS if k[0] == token]:
            del _MASKS[mask_key]
        for chunk_key in [k for k in _RESIDUALS if k[0] == token]:
            del _RESIDUALS[chunk_key]
        for derived_key in [k for k in _DERIVED if k[0] == token]:
            del _DERIVED[derived_key]
        _GRAVITY.pop(token, None)


def gravity_model(problem: StreamProblem) -> StaticGravityModel:
    with _LOCK:
        model = _GRAVITY.get(problem.token)
        if model is None:
            model = _GRAVITY[problem.token] = StaticGravityModel.from_chain(problem.chain)
        return model


def prepared_blocks(problem: StreamProblem, ref: Any) -> list[Block]:
    """Load a chunk and prepare its blocks (from this process's cache when possible)."""
    key = (problem.token, ref)
    with _LOCK:
        cached = _PREPARED.get(key)
        if cached is not None:
            _PREPARED.move_to_end(key)
            return cached
    chunk = problem.load(ref)
    gravity = gravity_model(problem)
    blocks = []
    for a in range(0, chunk.n_rows, problem.block_rows):
        b = min(a + problem.block_rows, chunk.n_rows)
        q = np.ascontiguousarray(chunk.joint_positions[a:b])
        motions = joint_motions(problem.chain, q)
        payload = problem.payload_kg if chunk.payload_kg is None else chunk.payload_kg[a:b]
        loads = static_gravity_loads(
            gravity, q, gravity_base=problem.gravity_base_m_s2, payload_kg=payload, motions=motions
        )
        quaternion = chunk.quaternion_xyzw
        rotation = None if quaternion is None else quaternion_rotation(quaternion[a:b])
        translation = np.ascontiguousarray(chunk.position_m[a:b].T)
        blocks.append(Block(chunk.first_row + a, motions, loads, rotation, translation))
    size = sum(block.nbytes for block in blocks)
    if size <= problem.cache_bytes:
        with _LOCK:
            _PREPARED[key] = blocks
            held = sum(block.nbytes for value in _PREPARED.values() for block in value)
            while held > problem.cache_bytes and len(_PREPARED) > 1:
                old, dropped = _PREPARED.popitem(last=False)
                _RESIDUALS.pop(old, None)
                held -= sum(block.nbytes for block in dropped)
    return blocks


def keep_residuals(
    problem: StreamProblem, ref: Any, blocks: list[Block], key: bytes, residuals: list[FloatArray]
) -> None:
    """Remember a chunk's residuals (per block, (d, b)) at the parameters digested as ``key``,
    only beside a cached chunk: without the cache memory stays flat."""
    with _LOCK:
        if _PREPARED.get((problem.token, ref)) is blocks:
            _RESIDUALS[(problem.token, ref)] = (key, residuals)


def take_residuals(problem: StreamProblem, ref: Any) -> tuple[bytes, list[FloatArray]] | None:
    """The residuals :func:`keep_residuals` left for a chunk (and forget them), or None."""
    with _LOCK:
        return _RESIDUALS.pop((problem.token, ref), None)


def cached_masks(problem: StreamProblem, ref: Any, rule_token: str) -> list[BoolArray] | None:
    """The keep masks (per block) of a chunk under the rule ``rule_token``, or None."""
    with _LOCK:
        return _MASKS.get((problem.token, ref, rule_token))


def cache_masks(problem: StreamProblem, ref: Any, rule_token: str, masks: list[BoolArray]) -> None:
    """Remember the keep masks of a chunk under a rule for the later passes."""
    with _LOCK:
        _MASKS[(problem.token, ref, rule_token)] = masks


def cached_derived(problem: StreamProblem, ref: Any, key: str) -> Any | None:
    """What :func:`cache_derived` kept of chunk ``ref`` under ``key``, or None."""
    with _LOCK:
        entry = _DERIVED.get((problem.token, ref, key))
    return None if entry is None else entry[1]


def cache_derived(problem: StreamProblem, ref: Any, key: str, value: Any, nbytes: int) -> None:
    """Keep ``value`` (``nbytes`` large), derived from chunk ``ref`` for the passes of one
    computation named ``key`` (e.g. the samples of the covariance stage at the calibrated
    parameters), when this process's caches of the problem stay within its budget."""
    with _LOCK:
        held = sum(b.nbytes for k, v in _PREPARED.items() if k[0] == problem.token for b in v)
        held += sum(size for k, (size, _) in _DERIVED.items() if k[0] == problem.token)
        if held + nbytes <= problem.cache_bytes:
            _DERIVED[(problem.token, ref, key)] = (nbytes, value)


def count_chunk_rows(problem: StreamProblem, ref: Any) -> int:
    return sum(block.n for block in prepared_blocks(problem, ref))


def scan(problem: StreamProblem, executor: Executor) -> int:
    """Read and prepare every chunk once (filling the caches); the number of rows."""
    return int(sum(executor.map(count_chunk_rows, problem, problem.refs)))


def release(problem: StreamProblem, executor: Executor) -> None:
    """Free the problem's cached chunks and masks in every worker."""
    executor.run_on_workers(functools.partial(forget, problem.token))
