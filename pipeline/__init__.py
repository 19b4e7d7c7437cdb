"""Running rsmb: dask scheduling of tile tasks, the click CLI, demo, reports."""

from .detection._detect import detect
from .detection._plan import VERSION, DetectConfig, DetectResult, default_overlap
from ._evaluate import Evaluation, evaluate
from .report._report import write_report
from .archive._survey import SurveyResult, survey
from ._synth import PairPaths, read_truth, synth, write_pair

__all__ = ["VERSION", "DetectConfig", "DetectResult", "Evaluation", "PairPaths", "default_overlap", "detect", "evaluate",
           "read_truth", "survey", "SurveyResult", "synth", "write_pair", "write_report"]
