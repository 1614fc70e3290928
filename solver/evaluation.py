"""Evaluation protocol of DESIGN.md §4 / paper §V-A: repeated 90/10 train/test splits.

Each method is a function ``(train_indices, test_indices) -> predicted test poses`` so that the
nominal baseline, kincal's calibration and learned baselines are scored on identical splits.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from solver.arrays import FloatArray, IntArray
from solver.calibration import pose_errors

Method = Callable[[IntArray, IntArray], FloatArray]

PAPER_SEEDS = tuple(range(1, 11))


def split_indices(n: int, seed: int, train_fraction: float = 0.9) -> tuple[IntArray, IntArray]:
    """Random permutation with ``default_rng(seed)``; first ``round(fraction n)`` rows train."""
    order = np.random.default_rng(seed).permutation(n)
    n_train = round(train_fraction * n)
    n_train = min(max(n_train, 1), n - 1)
    return np.sort(order[:n_train]), np.sort(order[n_train:])


@dataclass(frozen=True)
class SplitError:
    """Mean held-out error of one method on one split (rotation None when the rows measure
    positions only)."""

    method: str
    seed: int
    n_train: int
    n_test: int
    translation_mm: float
    rotation_deg: float | None


def cross_validate(
    measured_pose: FloatArray,
    methods: Mapping[str, Method],
    *,
    rotation: bool,
    seeds: Iterable[int] = PAPER_SEEDS,
    train_fraction: float = 0.9,
) -> list[SplitError]:
    """Score every method on the same splits; one :class:`SplitError` per (method, seed);
    ``rotation``: the rows measure rotations too (the measurement model's
    :attr:`~solver.measurement.FullPose.measures_rotation`)."""
    n = measured_pose.shape[0]
    seeds = list(seeds)
    predictions = {}
    for seed in seeds:
        train, test = split_indices(n, seed, train_fraction)
        for name, method in methods.items():
            predictions[seed, name] = method(train, test)
    return score_splits(
        measured_pose,
        predictions,
        list(methods),
        rotation=rotation,
        seeds=seeds,
        train_fraction=train_fraction,
    )


def score_splits(
    measured_pose: FloatArray,
    predictions: Mapping[tuple[int, str], FloatArray],
    methods: Sequence[str],
    *,
    rotation: bool,
    seeds: Iterable[int],
    train_fraction: float,
) -> list[SplitError]:
    """One :class:`SplitError` per (method, seed) from the predicted test poses
    ``predictions[seed, method]`` (n_test, 4, 4) of :func:`split_indices`' splits."""
    n = measured_pose.shape[0]
    out: list[SplitError] = []
    for seed in seeds:
        train, test = split_indices(n, seed, train_fraction)
        for name in methods:
            translation_mm, rotation_deg = pose_errors(
                predictions[seed, name], measured_pose[test], rotation=rotation
            )
            out.append(
                SplitError(
                    method=name,
                    seed=seed,
                    n_train=train.size,
                    n_test=test.size,
                    translation_mm=float(translation_mm.mean()),
                    rotation_deg=None if rotation_deg is None else float(rotation_deg.mean()),
                )
            )
    return out
