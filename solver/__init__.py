"""kincal's maths: numpy in, numpy out (no HTTP, SQL or files).

Where each equation of the paper (Gerstewitz et al.) lives; frames and units follow DESIGN.md §2:

=============================  ==================================================================
Paper                          Function
=============================  ==================================================================
Eq. 5  adjoint Ad_X            :func:`solver.lie.adjoint`, batched in :mod:`solver.batch_chain`
Eq. 6  compliance q̃ = c·τ(q)   :func:`solver.model.gravity_loads` (Pinocchio RNEA),
                               :func:`solver.gravity.static_gravity_loads` (streamed passes)
Eq. 7  product of exponentials :func:`solver.kinematics.forward_kinematics`,
                               :func:`solver.batch_chain.sweep_chain` (batch-last, with Eq. 9)
Eq. 8  residual Log(X⁻¹X_meas)  :func:`solver.kinematics.pose_residuals`
Eq. 9  stacked Jacobian        :func:`solver.kinematics.stacked_jacobian`
Eq. 10 damped (Lev.–Marquardt) :func:`solver.calibration.levenberg_marquardt_iteration` (one
                               iteration, in memory and streamed),
                               :func:`solver.measurement.pose.fit_deterministic`
§V-A   2σ outlier rule         :func:`solver.calibration.within_spread`
Eq. 12 Σ_E(q)                  :func:`solver.covariance.likelihood.ee_covariance_batch` (the one
                               kernel: likelihoods, predictions, rankings' reference); its
                               inverse, log det and Mahalanobis distances for a whole recording:
                               :func:`solver.small_spd.spd_factors`
Eq. 12 other measurements      :func:`solver.measurement.fit.covariance_samples` (sockets,
                               relative base, eye-on-head)
Eq. 13 moment matching         :func:`solver.covariance.statistics.build_moment_statistics`
Eq. 14 its sufficient stats    :class:`solver.covariance.statistics.MomentStatistics`,
                               :func:`solver.covariance.objective.moment_objective`
Eq. 14 solvers                 :func:`solver.covariance.solvers.solve_clarabel` (cvxpy + Clarabel),
                               :func:`~solver.covariance.solvers.solve_nnls` (diagonal Σ)
Eq. 15 projected gradient      :func:`solver.covariance.solvers.solve_pgd` (the paper's baseline)
Eq. 16–17 ML                   :func:`solver.covariance.likelihood.gaussian_nll`,
                               :func:`~solver.covariance.likelihood.fisher_information_ml`
REML (beyond the paper)        :func:`solver.covariance.likelihood.restricted_nll`
ML/REML fit                    :func:`solver.covariance.fitting.fit_likelihood`
§IV-C whole stage              :func:`solver.covariance.estimate.estimate_from_samples` (samples in
                               memory or streamed, :mod:`solver.covariance.samples`)
Eq. 22 task score tr(WΣ_EWᵀ)   :func:`solver.ranking.score_configurations` (without forming Σ_E)
Eq. 23 best configuration      :func:`solver.ranking.ranking_order`
ref. [13] GP baseline          :mod:`solver.gp_baseline`
=============================  ==================================================================

The calibration of a recording, stage by stage and whatever its size, is
:func:`solver.stream.calibrate.calibrate_recording`.

The dense problems here are small (hundreds of columns at most), where multi-threaded BLAS costs
more than it saves and fights with worker processes for cores (measured: a 42×42 ``eigh`` takes
20 ms instead of 0.4 ms on a busy 2-core machine): default to one BLAS thread unless the user set
one of the variables. Environment variables only act before numpy is first imported; when numpy
came first (a script importing it before ``solver``) the running BLAS is limited instead.
"""

import os
import sys

_BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
_user_chose = any(name in os.environ for name in _BLAS_THREAD_VARIABLES)
for _variable in _BLAS_THREAD_VARIABLES:
    os.environ.setdefault(_variable, "1")
if not _user_chose and "numpy" in sys.modules:
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")
