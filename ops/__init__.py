"""Numerical kernels of rsmb: camera model, pose spaces, the RSMB forward model,
the per-row solvers of eq. 13, registration, change masks and metrics.

Pure numpy (with numba-compiled inner loops); no I/O, no dask, no zarr.
"""

from ._camera import AXIS_UNITS, POSE_AXES, Camera, full_poses, pose_homographies
from .changes._changes import (
    RESIDUAL_BINS,
    SCORE_BINS,
    ChangeParams,
    ChangeResult,
    ScoreHistogram,
    change_candidates,
    change_mask,
    change_score,
    change_threshold,
    changes_to_reference,
    detect_changes,
    fill_holes,
    keep_components,
    label_components,
    large_components,
    reference_lookup,
    residual_median,
    sample_at,
    score_histogram,
    NO_EVIDENCE,
    GroundFrame,
    evidence_mask,
    to_ground,
)
from ._errors import InputError, ParameterError, RSMBError, RunError, SolverError
from ._forward import CameraPath, RenderResult, render
from ._intensity import IntensityScale, fill_zeros, intensity_scale
from ._method import MethodResult, method_changes, run_method
from .depth._depthmap import DepthMapParams, DepthMapResult, depth_map, model_values
from .depth._depthsolve import AlternateParams, depth_step
from .depth._layers import LayerParams, LayerResult, depth_layers
from .changes._bounds import ModelBounds, bounded_score, model_bounds
from .changes._metrics import ConfusionCounts, confusion, trajectory_rmse
from ._oracle import ExactRowSolution, huber_objective, optimal_chi, row_objective, solve_row_exact
from ._posespace import PoseSpace
from .registration._params import RegistrationParams, auto_step
from .registration._register import Registration, find_start, register
from .registration._reground import reground
from .registration._rowsolve import solve_row_fast
from .registration._start import StartPose
from .synthetic._scene import aerial_scene, paste_changes
from .registration._slow import SlowPath, estimate_slow
from .synthetic._synth import MOTIONS, SyntheticPair, motion_path, synthesize_pair
from .changes._threshold import kapur_threshold, kapur_threshold_histogram

#: Version of the kernels' results: raised whenever a change to ops alters what
#: a run computes, so that ``--resume`` never mixes tiles of two versions.
KERNEL_VERSION = 25

__all__ = [
    "KERNEL_VERSION",
    "AXIS_UNITS",
    "POSE_AXES",
    "Camera",
    "full_poses",
    "pose_homographies",
    "PoseSpace",
    "CameraPath",
    "RenderResult",
    "render",
    "RegistrationParams",
    "IntensityScale",
    "intensity_scale",
    "fill_zeros",
    "LayerParams",
    "LayerResult",
    "depth_layers",
    "DepthMapParams",
    "DepthMapResult",
    "depth_map",
    "model_values",
    "ModelBounds",
    "model_bounds",
    "bounded_score",
    "AlternateParams",
    "depth_step",
    "Registration",
    "register",
    "find_start",
    "StartPose",
    "reground",
    "SlowPath",
    "estimate_slow",
    "auto_step",
    "solve_row_fast",
    "solve_row_exact",
    "ExactRowSolution",
    "row_objective",
    "huber_objective",
    "optimal_chi",
    "ChangeParams",
    "ChangeResult",
    "detect_changes",
    "run_method",
    "MethodResult",
    "method_changes",
    "change_score",
    "ScoreHistogram",
    "score_histogram",
    "change_threshold",
    "residual_median",
    "RESIDUAL_BINS",
    "SCORE_BINS",
    "change_mask",
    "change_candidates",
    "label_components",
    "keep_components",
    "large_components",
    "fill_holes",
    "changes_to_reference",
    "reference_lookup",
    "sample_at",
    "NO_EVIDENCE",
    "GroundFrame",
    "evidence_mask",
    "to_ground",
    "kapur_threshold",
    "kapur_threshold_histogram",
    "ConfusionCounts",
    "confusion",
    "trajectory_rmse",
    "aerial_scene",
    "paste_changes",
    "MOTIONS",
    "SyntheticPair",
    "motion_path",
    "synthesize_pair",
    "RSMBError",
    "InputError",
    "ParameterError",
    "SolverError",
    "RunError",
]
