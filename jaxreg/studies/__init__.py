"""Studies: sweeps of many registrations that each answer one question: the basin of
attraction of ICP, the repeatability tiers with their error budget, the hand-eye correction
that makes viewpoints agree, the calibration of the reported error bars against the real
error, and the pipeline run on every target of a BOP dataset split with its estimates scored
by BOP's metrics.

May import every package but :mod:`jaxreg.cli`.
"""

from jaxreg.core._lazy import exports
from jaxreg.studies._hand_eye import (
    HandEyeCorrection as HandEyeCorrection,
    estimate_hand_eye_correction as estimate_hand_eye_correction,
)
from jaxreg.studies._repeatability import (
    Repeatability as Repeatability,
    repeatability as repeatability,
)
from jaxreg.studies.basin import (
    BasinSweep as BasinSweep,
    basin_radius as basin_radius,
    basin_starts as basin_starts,
    basin_sweep as basin_sweep,
    lesson_cube as lesson_cube,
)
from jaxreg.studies.bop_run import (
    gather_bop_results as gather_bop_results,
    run_bop as run_bop,
)
from jaxreg.studies.bop_scores import (
    BopScores as BopScores,
    TargetErrors as TargetErrors,
    bop_scores as bop_scores,
)
from jaxreg.studies.budget_calibration import calibrate as calibrate
from jaxreg.studies.calibration import (
    CalibrationStudy as CalibrationStudy,
    FrameOutcome as FrameOutcome,
    calibration_study as calibration_study,
)

# jaxreg.studies.<module> without importing it first; dir() lists the public names
__getattr__, __dir__ = exports(__name__, {})
