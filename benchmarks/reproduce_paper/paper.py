"""The paper's published numbers (LRU2 Jaco2, §V), reported next to the reproduction's for
comparison only, and the size of its manipulation experiment."""

from __future__ import annotations

PAPER_RUNS = 10
"""Runs of the paper's manipulation experiment (§V-C, Table III)."""
PAPER_TABLE_II: dict[str, tuple[tuple[float, ...], tuple[float, ...]]] = {
    "before": (
        (8.40, 6.28, 7.46, 7.49, 8.65, 7.33, 8.15, 7.36, 7.93, 7.13),
        (4.88, 5.61, 4.22, 5.91, 5.68, 5.14, 5.42, 5.47, 3.73, 5.62),
    ),
    "calibrated": (
        (7.10, 4.95, 5.91, 7.38, 7.44, 7.71, 5.57, 6.31, 7.62, 6.48),
        (5.85, 4.06, 2.70, 4.97, 4.13, 4.92, 4.80, 4.30, 3.30, 3.89),
    ),
    "gp": (
        (11.50, 10.46, 9.36, 9.81, 10.25, 9.18, 9.90, 10.9, 10.52, 8.53),
        (5.41, 4.82, 3.27, 4.80, 5.21, 4.73, 5.20, 4.33, 3.11, 4.62),
    ),
}
"""Paper Table II, mm and deg per seed 1..10 (LRU2 Jaco2), for comparison only."""
PAPER_TABLE_III = {
    "ours": (0.00, -0.07, 0.66, -0.05, 0.16, -0.04, 0.68, 0.28, 0.19, 0.67),
    "gp": (-0.04, 0.48, 0.60, -0.14, -0.05, 0.35, -0.09, 0.47, -0.36, -0.09),
}
"""Paper Table III: correlation of the Eq. (23) score with the observed x-y error per run."""
PAPER_SELECTION_MM = (2.495, 4.133)
"""Paper §V-C: mean x-y error of the lowest- and highest-uncertainty approaches (10 runs)."""
PAPER_WINS = 7
