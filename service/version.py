"""kincal's installed version, without importing anything heavy (the ``kincal serve``
supervisor stamps it and imports no solver or web code)."""

from __future__ import annotations

import functools
from importlib import metadata


@functools.cache  # reading package metadata costs milliseconds; rankings stamp every answer
def kincal_version() -> str:
    try:
        return metadata.version("kincal")
    except metadata.PackageNotFoundError:
        return "0+unknown"
