"""Packages whose public names are imported on first use (:mod:`solver.lazy_exports`): every
name resolves to its module's object, an unknown one is an AttributeError, and importing the
package loads none of its heavy modules."""

from __future__ import annotations

import importlib
import subprocess
import sys

import pytest

from solver.lazy_exports import lazy_exports

LAZY = {
    "schemas.dataset": "schemas.dataset.readers",
    "solver.discovery": "solver.discovery.loop",
    "solver.measurement": "solver.measurement.fit",
    "service.api": "service.api.app",
}
"""Each package with lazy names, and a heavy module of it that importing it must not load."""


@pytest.mark.parametrize("package", sorted(LAZY))
def test_every_exported_name_resolves_and_an_unknown_one_is_an_attribute_error(
    package: str,
) -> None:
    module = importlib.import_module(package)
    for name in module.__all__:
        assert getattr(module, name) is not None, name
    with pytest.raises(AttributeError, match=f"module '{package}' has no attribute 'nowhere'"):
        module.nowhere  # noqa: B018


def test_a_name_comes_from_the_module_the_table_names() -> None:
    get = lazy_exports("solver", {"rotation_angle_rad": "lie"})
    from solver.lie import rotation_angle_rad

    assert get("rotation_angle_rad") is rotation_angle_rad
    with pytest.raises(AttributeError):
        get("se3_log")  # in solver.lie, but not in the table


def test_importing_the_packages_loads_none_of_their_heavy_modules() -> None:
    code = (
        f"import sys; import {', '.join(LAZY)}; "
        f"print([m for m in {sorted(LAZY.values())!r} if m in sys.modules])"
    )
    loaded = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.strip()
    assert loaded == "[]", loaded
