"""Running rsmb: dask scheduling of tile tasks, the click CLI, demo, reports."""

from ._detect import VERSION, DetectConfig, default_overlap, detect
from ._evaluate import evaluate
from ._report import write_report
from ._synth import read_truth, write_pair

__all__ = ["VERSION", "DetectConfig", "default_overlap", "detect", "evaluate", "read_truth", "write_pair", "write_report"]
