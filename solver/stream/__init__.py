"""Calibration over chunks of a recording: chunks in, sums out (paper Eq. 8–14).

Both calibration stages reduce to sums over samples: the Gauss–Newton normal equations
``JᵀJ, Jᵀr, rᵀr`` of Eq. (10) at each iterate, the residual spread of the 2σ rule (§V-A), the
error statistics, and the covariance statistics ``G, h, c`` of Eq. (13–14). Each pass maps one
function over the chunks of the recording (:mod:`solver.executors`: in-process, local processes
or Dask) and adds the per-chunk sums in chunk order, so the numbers do not depend on where a
chunk ran. A worker holds one chunk at a time (plus an optional, bounded cache of prepared
chunks), so memory does not grow with the number of samples.

The maths is the in-memory code's: the iteration is
:func:`solver.calibration.levenberg_marquardt_iteration`, the outlier rule
:func:`solver.calibration.within_spread` of a merged :class:`~solver.calibration.ResidualSpread`,
the covariance statistics those of :mod:`solver.covariance.statistics` per chunk, merged by
``+``. Per chunk, FK, Jacobians and residuals come from :mod:`solver.batch_chain` (the
batch-last sweep, equal to :mod:`solver.kinematics` to rounding; only the columns a pass needs)
and gravity loads from :mod:`solver.gravity` (equal to the RNEA loads to 1e-10 N·m). Samples
the outlier rule drops get zero rows (no gather), and the normal equations use the columns'
zero structure (:func:`_normal_equations`).

Passes over the data (a 10⁶-pose recording: 6, of which the last touches 5 % of the rows):
preparing the chunks (while the driver fits the head rows), the first fit's two, then the
refit and the "before" fit side by side (:func:`fit_streamed_together`: each of their passes
evaluates both), the refit's later passes also taking the covariance statistics along, and the
sandwich pass of the standard errors.

What differs from the in-memory pipeline, and why:

- **Warm start and pruning.** The closed-form alignment pairs samples across the whole
  recording, and the column-pivoted QR needs the stacked Jacobian; neither streams. Both run,
  unchanged, on the first ``warm_start_rows`` rows
  (:func:`solver.measurement.pose.fit_deterministic` there), whose fitted parameters start the
  streamed iteration and whose kept columns are the streamed fit's. More data only adds to the
  Gram, so every kept column stays identifiable; a column the first rows cannot see is reported
  as removed. The condition number is the full recording's (from its normal equations). With at
  most ``warm_start_rows`` rows the start and the pruning are exactly the in-memory ones.
- **Outliers (2σ rule).** The first fit's final pass also sums the residual spread
  (mean, M2 per component, merged exactly) and leaves each chunk's residuals in its worker;
  the rule (first fit's parameters, mean, σ) is applied to them (or, without the chunk cache,
  to one forward pass) and the per-chunk keep mask is cached for every later pass. The refit
  and the "before" fit are warm-started, and pruned, like the first fit, on the head rows the
  rule keeps — as the in-memory pipeline refits the kept rows.
- **Covariances.** Moment matching (Eq. 13–14) streams exactly: ``G, h, c`` (and the Jacobian
  range for the constant-Jacobian warning) at the refit's solution — taken along by its last
  pass, or by a pass of their own when the refit stopped at its start —, the solve, one pass
  for the sandwich ``Σ K̃ᵀK̃`` of the standard errors (over every s-th row beyond 50 000 used
  rows, scaled; only those rows are swept). ML/REML need a pass per scoring step and
  line-search trial; a streamed calibration uses the moment estimator and says so in its
  warnings (at 10⁵⁺ samples the REML correction is O(p/N)).
- **Deterministic standard errors** come from the final pass's ``JᵀJ`` and ``rᵀr`` exactly as
  in memory.
"""
