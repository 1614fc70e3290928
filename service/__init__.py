"""kincal's application layer: CLI, pipeline, (later) HTTP service and storage."""

import solver  # noqa: F401  (sets BLAS threading defaults before numpy loads)
