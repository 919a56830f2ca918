"""Pose uncertainty: measurement noise models (isotropic, per-point, depth-camera), statistics
of repeated pose estimates, the error budget, and a parallel-jaw grasp's predicted success
(:mod:`jaxreg.uncertainty.grasp`).

Covariances are of the right perturbation ``T_true = T_est @ exp(delta)``, tangent order
``(v, w)``. May import :mod:`jaxreg.core` and :mod:`jaxreg.geometry`.
"""

from jaxreg.core._lazy import exports
from jaxreg.uncertainty._pose_statistics import (
    GroupStatistics as GroupStatistics,
    PoseStatistics as PoseStatistics,
    pose_statistics as pose_statistics,
)
from jaxreg.uncertainty.calibrated import (
    BudgetCalibration as BudgetCalibration,
    fit_budget_calibration as fit_budget_calibration,
)
from jaxreg.uncertainty.grasp import (
    GraspPrediction as GraspPrediction,
    grasp_axis as grasp_axis,
    grasp_margin as grasp_margin,
    grasp_prediction as grasp_prediction,
    grasp_success_probability as grasp_success_probability,
)
from jaxreg.uncertainty.noise import (
    AbstractPointNoise as AbstractPointNoise,
    DepthNoise as DepthNoise,
    ErrorBudget as ErrorBudget,
    IsotropicNoise as IsotropicNoise,
    PointCovariance as PointCovariance,
    error_budget as error_budget,
)

# The budget's names, its module imported on first use; jaxreg.uncertainty.<module> too.
__getattr__, __dir__ = exports(
    __name__,
    {
        "jaxreg.uncertainty.budget": (
            "PoseBudget",
            "lateral_sigma",
            "mahalanobis",
            "region_contains",
        ),
    },
)
