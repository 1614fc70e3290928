"""Statistics of the manipulation runs: lowest- vs highest-score selection, correlation of score
and observed error (Table III), bootstrap intervals, the acceptance verdicts and diagnostics."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np
from scipy import stats

from benchmarks.reproduce_paper.manipulation import ApproachRun
from solver.arrays import FloatArray, IntArray

METHODS = ("ours", "gp", "oracle")
LABELS = {"ours": "Ours", "gp": "GP [13]", "oracle": "Oracle (true Σ)"}
MIN_REDUCTION_SHARE = 0.8


@dataclasses.dataclass(frozen=True)
class Selection:
    """Lowest- vs highest-score choice of one method over runs (paper §V-C results).

    ``low_mm``/``high_mm``: mean over runs of the observed error of the chosen configurations;
    ``reduction_pct`` = 100·(1 − low/high); ``wins``: runs where the low pick had the lower
    error; ``pearson``/``spearman`` (runs,): correlation of score and observed error per run
    (Table III); ``*_ci``: 95 % bootstrap intervals over runs.
    """

    method: str
    low_mm: float
    high_mm: float
    reduction_pct: float
    reduction_ci: tuple[float, float]
    wins: int
    pearson: FloatArray
    spearman: FloatArray
    pearson_ci: tuple[float, float]

    @property
    def mean_pearson(self) -> float:
        return float(np.nanmean(self.pearson))


@dataclasses.dataclass(frozen=True)
class Comparison:
    """The acceptance quantities on a set of runs, with bootstrap intervals.

    ``share_of_oracle``: our reduction / the oracle's, on the observed error; ``random_share``:
    the same on the random part of the error only (``scatter``); ``pearson_gap``: mean Pearson
    r of ours minus the GP's.
    """

    n_runs: int
    selections: dict[str, Selection]
    share_of_oracle: float
    share_ci: tuple[float, float]
    pearson_gap: float
    pearson_gap_ci: tuple[float, float]
    scatter: dict[str, Selection]
    random_share: float
    random_share_ci: tuple[float, float]

    @property
    def reduction_verdict(self) -> str:
        """Acceptance: the whole 95 % interval of the share at or above 80 % (:func:`_verdict`)."""
        return _verdict(self.share_ci, MIN_REDUCTION_SHARE)

    @property
    def correlation_verdict(self) -> str:
        """Acceptance: the whole 95 % interval of the Pearson gap (ours − GP) above zero."""
        return _verdict(self.pearson_gap_ci, 0.0, strict=True)


def _verdict(interval: tuple[float, float], bar: float, *, strict: bool = False) -> str:
    """ "met" if the whole interval clears the bar, "not met" if it lies below it, otherwise
    "not demonstrated" (the runs cannot tell at 95 %)."""
    low, high = interval
    if low > bar or (low == bar and not strict):
        return "met"
    if high < bar or (high == bar and strict):
        return "not met"
    return "not demonstrated"


def picked_errors(runs: Sequence[ApproachRun], method: str, field: str) -> FloatArray:
    """(runs, 2): observed error (``field``) of the lowest- and highest-score pick."""
    out = []
    for run in runs:
        low, high = run.pick(method)
        values = getattr(run, field)
        out.append((values[low], values[high]))
    return np.array(out)


def _correlation(kind: Callable[..., object], x: FloatArray, y: FloatArray) -> float:
    if np.ptp(x) == 0.0 or np.ptp(y) == 0.0:
        return float("nan")
    return float(kind(x, y).statistic)  # type: ignore[attr-defined]


def _reduction_pct(picked: FloatArray) -> FloatArray:
    """100·(1 − mean low / mean high) over axis −2 of (..., runs, 2)."""
    mean = picked.mean(axis=-2)
    return np.asarray(100.0 * (1.0 - mean[..., 0] / mean[..., 1]), dtype=float)


def _interval(samples: FloatArray) -> tuple[float, float]:
    low, high = np.nanpercentile(samples, [2.5, 97.5])
    return float(low), float(high)


def bootstrap_indices(groups: Sequence[int], n_boot: int, rng: np.random.Generator) -> IntArray:
    """(n_boot, n) resampled run indices: recordings (``groups``, one label per run) with
    replacement, then runs with replacement within each drawn recording (two-level bootstrap).
    One group is the ordinary bootstrap. Groups must be of equal size."""
    labels = np.asarray(groups)
    members = [np.flatnonzero(labels == g) for g in dict.fromkeys(labels.tolist())]
    size = members[0].size
    if any(m.size != size for m in members):
        raise ValueError("two-level bootstrap needs recordings with equal numbers of runs")
    table = np.array(members)  # (G, size)
    chosen = rng.integers(0, len(members), size=(n_boot, len(members)))
    within = rng.integers(0, size, size=(n_boot, len(members), size))
    return np.asarray(table[chosen[:, :, None], within].reshape(n_boot, -1), dtype=np.intp)


def _selection(
    runs: Sequence[ApproachRun], method: str, field: str, resample: IntArray
) -> tuple[Selection, FloatArray, FloatArray]:
    """A method's selection on ``field``, its bootstrap reductions and mean Pearson r."""
    picked = picked_errors(runs, method, field)
    values = [getattr(run, field) for run in runs]
    r = np.array(
        [
            _correlation(stats.pearsonr, run.scores[method], v)
            for run, v in zip(runs, values, strict=True)
        ]
    )
    rho = np.array(
        [
            _correlation(stats.spearmanr, run.scores[method], v)
            for run, v in zip(runs, values, strict=True)
        ]
    )
    boot = _reduction_pct(picked[resample])
    boot_r = np.nanmean(r[resample], axis=1)
    selection = Selection(
        method=method,
        low_mm=float(picked[:, 0].mean()),
        high_mm=float(picked[:, 1].mean()),
        reduction_pct=float(_reduction_pct(picked)),
        reduction_ci=_interval(boot),
        wins=int(np.sum(picked[:, 0] < picked[:, 1])),
        pearson=r,
        spearman=rho,
        pearson_ci=_interval(boot_r),
    )
    return selection, boot, boot_r


def compare(
    runs: Sequence[ApproachRun],
    *,
    bootstrap: int = 2000,
    seed: int = 0,
    groups: Sequence[int] | None = None,
) -> Comparison:
    """Selections of every method, the share of the oracle's reduction ours reaches and the
    Pearson gap to the GP, each with a percentile bootstrap over runs (two-level over
    recordings and runs if ``groups`` labels the recording of every run)."""
    rng = np.random.default_rng(seed)
    resample = bootstrap_indices(groups or [0] * len(runs), bootstrap, rng)
    chosen: dict[str, Selection] = {}
    scatter: dict[str, Selection] = {}
    boot: dict[str, FloatArray] = {}
    boot_r: dict[str, FloatArray] = {}
    for method in METHODS:
        chosen[method], boot[method], boot_r[method] = _selection(
            runs, method, "error_mm", resample
        )
        scatter[method], boot[f"{method} random"], _ = _selection(
            runs, method, "scatter_mm", resample
        )
    with np.errstate(divide="ignore", invalid="ignore"):
        share_boot = boot["ours"] / boot["oracle"]
        random_boot = boot["ours random"] / boot["oracle random"]
    return Comparison(
        n_runs=len(runs),
        selections=chosen,
        share_of_oracle=chosen["ours"].reduction_pct / chosen["oracle"].reduction_pct,
        share_ci=_interval(share_boot),
        pearson_gap=chosen["ours"].mean_pearson - chosen["gp"].mean_pearson,
        pearson_gap_ci=_interval(boot_r["ours"] - boot_r["gp"]),
        scatter=scatter,
        random_share=scatter["ours"].reduction_pct / scatter["oracle"].reduction_pct,
        random_share_ci=_interval(random_boot),
    )


@dataclasses.dataclass(frozen=True)
class Diagnostics:
    """Why the comparison is hard, on the first recording's runs.

    ``spread``: median (10th, 90th percentile) over runs of the ratio of the largest to the
    smallest true x-y σ among the approaches; ``agreement``: mean Spearman ρ of our score and the
    oracle's within a run; ``same_low``/``same_high``: share of runs where ours picks the
    oracle's lowest/highest; ``bias_mm``/``scatter_mm``: mean systematic/random error part.
    """

    spread: tuple[float, float, float]
    agreement: float
    same_low: float
    same_high: float
    bias_mm: float
    scatter_mm: float


def diagnostics(runs: Sequence[ApproachRun]) -> Diagnostics:
    ratio = np.array([r.true_xy_std_mm.max() / r.true_xy_std_mm.min() for r in runs])
    rho = [_correlation(stats.spearmanr, r.scores["ours"], r.scores["oracle"]) for r in runs]
    picks = np.array([(r.pick("ours"), r.pick("oracle")) for r in runs])  # (runs, 2, 2)
    return Diagnostics(
        spread=(
            float(np.median(ratio)),
            float(np.percentile(ratio, 10)),
            float(np.percentile(ratio, 90)),
        ),
        agreement=float(np.nanmean(rho)),
        same_low=float(np.mean(picks[:, 0, 0] == picks[:, 1, 0])),
        same_high=float(np.mean(picks[:, 0, 1] == picks[:, 1, 1])),
        bias_mm=float(np.mean([r.bias_mm.mean() for r in runs])),
        scatter_mm=float(np.mean([r.scatter_mm.mean() for r in runs])),
    )
