"""Pose and position rows (DESIGN.md §2: the marker pose, or its position alone, in the
measurement frame): their measurement model, the closed-form start and the deterministic
calibration of paper Eq. (8)–(10) as :func:`solver.measurement.fit.fit_measurement` of these
models — the in-memory fit; :mod:`solver.stream` streams the same iteration."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from solver.arrays import FloatArray
from solver.calibration import DeterministicFit, FitOptions, check_sample_count
from solver.kinematics import ChainParameters
from solver.measurement import models as measurement_models
from solver.measurement.fit import fit_measurement, refit_from
from solver.model import KinematicChain


def pose_measurement(*, rotation: bool) -> measurement_models.FullPose:
    """The measurement model of a pose recording: :class:`~solver.measurement.FullPose` when
    its rows carry the marker's rotation (quaternion columns), else
    :class:`~solver.measurement.Position`. The one place a recording's columns become the
    model the pose paths take (issue 35)."""
    return measurement_models.FullPose() if rotation else measurement_models.Position()


def initial_parameters(
    chain: KinematicChain,
    joint_positions: FloatArray,
    measured_pose: FloatArray,
    *,
    measurement: measurement_models.FullPose,
) -> ChainParameters:
    """Nominal geometry; closed-form measurement frame folded into L_1, tool into L_{k+1}
    (:meth:`solver.measurement.FullPose.start`)."""
    rows = measurement_models.MeasurementRows.of(
        joint_positions, np.zeros((joint_positions.shape[0], 0)), measured_pose
    )
    start = measurement.start(chain, rows)
    return ChainParameters(start.links, start.compliance_rad_per_nm)


def fit_deterministic(
    chain: KinematicChain,
    joint_positions: FloatArray,
    measured_pose: FloatArray,
    loads_nm: FloatArray,
    *,
    measurement: measurement_models.FullPose,
    options: FitOptions = FitOptions(),
    start: ChainParameters | None = None,
    estimated: Sequence[str] | None = None,
) -> DeterministicFit:
    """Paper Eq. (10): iterate ``x_w = A_w^+ y_w`` and re-linearise until the cost settles.

    ``measured_pose`` (N, 4, 4) in the measurement frame (rotation ignored when
    ``measurement`` is :class:`~solver.measurement.Position`); ``loads_nm`` (N, n_axes) from
    :func:`solver.model.gravity_loads`. The fit of the pose measurement model
    (:func:`solver.measurement.fit_measurement`), after the sample count is checked against
    the chain; with ``estimated`` (the parameters of the fit ``start`` came from) one
    Gauss–Newton step from ``start`` over them (:func:`solver.measurement.fit.refit_from`).
    """
    check_sample_count(chain, joint_positions.shape[0], dim=measurement.dim, options=options)
    rows = measurement_models.MeasurementRows.of(joint_positions, loads_nm, measured_pose)
    begin = (
        None
        if start is None
        else measurement_models.ModelParameters(start.links, start.compliance_rad_per_nm)
    )
    if estimated is not None and begin is not None:
        fit = refit_from(chain, measurement, rows, options, begin, estimated)
    else:
        fit = fit_measurement(chain, measurement, rows, options, start=begin)
    shared = {f.name: getattr(fit, f.name) for f in dataclasses.fields(DeterministicFit)}
    params = ChainParameters(fit.params.links, fit.params.compliance_rad_per_nm)
    return DeterministicFit(**{**shared, "params": params})
