"""rsmb: registration and change detection under rolling shutter and motion blur.

The public Python API.  Each function is the one the command of the same name
calls::

    import rsmb
    summary = rsmb.detect("reference.tif", "capture.tif", "changes.zarr")

The subpackages hold the rest: :mod:`rsmb.ops` (numerical kernels),
:mod:`rsmb.tiles` (tile grids, zarr stores, raster I/O) and
:mod:`rsmb.pipeline` (scheduling, the command line, reports).  They are
imported on first use, so ``import rsmb.ops`` stays light.
"""

import importlib

__all__ = ["detect", "survey", "synth", "evaluate", "report", "SurveyResult", "DetectConfig", "DetectResult", "Evaluation", "PairPaths",
           "__version__"]

# public name -> (module, attribute)
_API = {
    "detect": ("rsmb.pipeline.detection._detect", "detect"),
    "DetectConfig": ("rsmb.pipeline.detection._detect", "DetectConfig"),
    "DetectResult": ("rsmb.pipeline.detection._detect", "DetectResult"),
    "synth": ("rsmb.pipeline._synth", "synth"),
    "PairPaths": ("rsmb.pipeline._synth", "PairPaths"),
    "evaluate": ("rsmb.pipeline._evaluate", "evaluate"),
    "Evaluation": ("rsmb.pipeline._evaluate", "Evaluation"),
    "report": ("rsmb.pipeline.report._report", "write_report"),
    "survey": ("rsmb.pipeline.archive._survey", "survey"),
    "SurveyResult": ("rsmb.pipeline.archive._survey", "SurveyResult"),
}


def __getattr__(name):
    if name == "__version__":
        from importlib.metadata import PackageNotFoundError, version

        try:
            return version("rsmb")
        except PackageNotFoundError:  # running from a source tree that is not installed
            return "0+unknown"
    if name in _API:
        module, attribute = _API[name]
        value = getattr(importlib.import_module(module), attribute)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'rsmb' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))
