"""``python -m benchmarks.reproduce_paper [--out DIR] [--figures DIR] [--runs N] [--recordings N]
[--executions N] [--quick]``: the paper reproduction (the study: the package docstring)."""

from __future__ import annotations

import benchmarks.reproduce_paper as reproduce_paper
from benchmarks.reproduce_paper.cli import run

if __name__ == "__main__":
    run((reproduce_paper.__doc__ or "").splitlines()[0])
