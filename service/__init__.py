"""kincal's application layer: rooms by role (docs/architecture.md) — the kincal command
(``cli``), the HTTP service (``api``), the use cases (``app``), rendering of results
(``render``), jobs and processes (``jobs``), storage, settings and security.

:func:`kincal_version` is here because every room stamps it and it imports nothing heavy (the
``kincal serve`` supervisor imports no solver or web code)."""

import functools

import solver  # noqa: F401  (sets BLAS threading defaults before numpy loads)


@functools.cache  # reading package metadata costs milliseconds; rankings stamp every answer
def kincal_version() -> str:
    from importlib import metadata  # 40 ms: not at import (kincal --help)

    try:
        return metadata.version("kincal")
    except metadata.PackageNotFoundError:
        return "0+unknown"
