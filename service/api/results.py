"""In-process LRU cache of calibration results, keyed by calibration id.

Results never change once a job succeeded, so a cached entry is valid forever; it remembers
its tenant so that a hit needs no database query at all (the rankings hot path). Each entry
also memoises objects derived from the result (e.g. the rebuilt chain / uncertainty model a
ranking needs), built once per calibration instead of once per request.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

from schemas.calibration import CalibrationResult
from service.storage.files import FileStore
from service.storage.models import Job

T = TypeVar("T")


@dataclass
class CachedResult:
    tenant_id: str
    result: CalibrationResult
    _derived: dict[str, Any] = field(default_factory=dict, repr=False)

    def has(self, key: str) -> bool:
        """Whether ``memo(key, ...)`` has been built (so calling it costs nothing)."""
        return key in self._derived

    def memo(self, key: str, build: Callable[[CalibrationResult], T]) -> T:
        """``build(result)``, once per entry and key (a race may build it twice, harmlessly)."""
        try:
            return self._derived[key]  # type: ignore[no-any-return]
        except KeyError:
            value = build(self.result)
            self._derived[key] = value
            return value


class ResultCache:
    def __init__(self, files: FileStore, maxsize: int) -> None:
        self._files = files
        self._maxsize = maxsize
        self._entries: OrderedDict[str, CachedResult] = OrderedDict()
        self._lock = threading.Lock()
        self.hits = 0
        self.misses = 0

    def entry(
        self, tenant_id: str, calibration_id: str, load_job: Callable[[], Job | None]
    ) -> CachedResult | None:
        """The cache entry of a succeeded calibration of ``tenant_id``, or None.

        ``load_job`` is called only on a miss; it must return the tenant's succeeded job (or
        raise the problem that explains why there is no result).
        """
        with self._lock:
            entry = self._entries.get(calibration_id)
            if entry is not None and entry.tenant_id == tenant_id:
                self._entries.move_to_end(calibration_id)
                self.hits += 1
                return entry
        job = load_job()
        if job is None or job.tenant_id != tenant_id or "result" not in job.artifacts:
            return None
        result = CalibrationResult.model_validate_json(self._files.read(job.artifacts["result"]))
        entry = CachedResult(tenant_id, result)
        with self._lock:
            self.misses += 1
            self._entries[calibration_id] = entry
            self._entries.move_to_end(calibration_id)
            while len(self._entries) > self._maxsize:
                self._entries.popitem(last=False)
        return entry

    def peek(self, tenant_id: str, calibration_id: str) -> CachedResult | None:
        """The entry if it is cached for ``tenant_id`` (no loading: safe in the event loop)."""
        with self._lock:
            entry = self._entries.get(calibration_id)
            if entry is None or entry.tenant_id != tenant_id:
                return None
            self._entries.move_to_end(calibration_id)
            self.hits += 1
            return entry

    def get(
        self, tenant_id: str, calibration_id: str, load_job: Callable[[], Job | None]
    ) -> CalibrationResult | None:
        entry = self.entry(tenant_id, calibration_id, load_job)
        return None if entry is None else entry.result

    def __len__(self) -> int:
        return len(self._entries)
