"""Sizes and seeds of the paper reproduction (:class:`StudySettings`)."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class StudySettings:
    """Sizes and seeds. ``n_recordings`` recordings (seeds ``seed``, ``seed + 1``, …) of
    ``n_samples`` each; per recording ``n_runs`` manipulation runs of ``n_approaches``
    configurations, each executed ``n_executions`` times; ``splits`` are the held-out seeds of the
    first recording (Table II, Fig. 4b); ``ablation_samples`` are the sizes of larger recordings
    of the same robot whose covariances re-score the first recording's candidates."""

    n_samples: int = 154
    seed: int = 1
    n_recordings: int = 4
    n_runs: int = 150
    n_approaches: int = 10
    n_executions: int = 500
    splits: tuple[int, ...] = tuple(range(1, 11))
    split_covariances: bool = True
    gp_table: bool = True
    paper_estimator_ablation: bool = True
    ablation_samples: tuple[int, ...] = (500, 2000)
    bootstrap: int = 2000

    @classmethod
    def quick(cls) -> StudySettings:
        """A reduced study for the test: one recording, 2 splits, 40 runs, no GP Table II column
        (tested in tests/service/test_rank_cli.py) and no costly ablations."""
        return cls(
            n_recordings=1,
            n_runs=40,
            n_executions=200,
            splits=(1, 2),
            split_covariances=False,
            gp_table=False,
            paper_estimator_ablation=False,
            ablation_samples=(),
            bootstrap=1000,
        )
