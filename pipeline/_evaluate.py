"""``rsmb evaluate``: scores of an output store against a synthetic truth."""

from dataclasses import dataclass

import numpy as np

from rsmb import ops
from rsmb import tiles
from rsmb.ops import InputError

from ._synth import read_truth

__all__ = ["Evaluation", "evaluate"]


@dataclass(frozen=True)
class Evaluation:
    """Scores of one store against its truth (see :func:`evaluate`).

    Attributes
    ----------
    changes, changes_reference : ops.ConfusionCounts
        Pooled over the whole image, in the capture and the reference grid.
    trajectory : dict
        Per estimated axis, ``{"rmse", "max_abs", ...}`` (axis units).
    gain : dict
        ``max_relative_error``, ``mean_relative_error`` and the per-tile maps.
    registration_rmse_255 : float or None
        Registered against the capture outside true changes, 0..255 units.
    """

    changes: ops.ConfusionCounts
    changes_reference: ops.ConfusionCounts
    trajectory: dict
    gain: dict
    registration_rmse_255: float | None

    def as_dict(self):
        """JSON-ready dict (the confusion counts with their ratios)."""
        return {"changes": self.changes.as_dict(), "changes_reference": self.changes_reference.as_dict(),
                "trajectory": self.trajectory, "gain": self.gain, "registration_rmse_255": self.registration_rmse_255}


def _tile_means(values, row_edges, col_edges):
    out = np.zeros((len(row_edges) - 1, len(col_edges) - 1))
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            out[i, j] = values[row_edges[i]:row_edges[i + 1], col_edges[j]:col_edges[j + 1]].mean()
    return out


#: The store arrays :func:`evaluate` reads.
_READ = ("change_mask", "change_mask_reference", "registered", "trajectory", "gain")


def evaluate(store, truth_dir):
    """Metrics of a ``rsmb detect`` store against ``rsmb synth`` truth.

    Returns
    -------
    Evaluation
        ``changes`` and ``changes_reference`` (precision, recall, PWC, F-measure,
        IoU, pooled over the whole image), ``trajectory`` (RMSE and max error per
        estimated axis, rows whose pixels were all valid), ``gain`` (per-tile
        relative error) and ``registration_rmse_255`` (registered against the
        capture, outside true changes, 0..255 units; needs the capture, so it is
        computed when the store's input path still exists).
    """
    group = tiles.open_result_store(store, required=_READ)
    truth = read_truth(truth_dir)
    mask = group["change_mask"][:] == 1  # 255, no evidence, is not a change
    if mask.shape != truth["change_mask"].shape:
        raise InputError(f"{truth_dir}: truth of shape {truth['change_mask'].shape} does not match the store's "
                         f"{mask.shape}")
    attrs = group.attrs.asdict()
    axes = list(group["trajectory"].attrs["pose_axes"])
    out = {
        "changes": ops.confusion(mask, truth["change_mask"]),
        "changes_reference": ops.confusion(group["change_mask_reference"][:] == 1, truth["change_mask_reference"]),
    }
    idx = [ops.POSE_AXES.index(a) for a in axes]
    registered = group["registered"][:]
    rows_ok = np.isfinite(registered).mean(axis=1) > 0.5
    out["trajectory"] = ops.trajectory_rmse(group["trajectory"][:].astype(np.float64), truth["trajectory"][:, idx],
                                            axes=axes, valid_rows=rows_ok)
    grid = attrs["tile_grid"]
    true_gain = _tile_means(truth["gain"], grid["row_edges"], grid["col_edges"])
    est = group["gain"][:].astype(np.float64)
    rel = np.abs(est - true_gain) / true_gain
    out["gain"] = {"max_relative_error": float(np.nanmax(rel)), "mean_relative_error": float(np.nanmean(rel)),
                   "estimated": est.round(4).tolist(), "true": true_gain.round(4).tolist()}
    try:
        distorted = tiles.read_image(attrs["inputs"]["distorted"]["path"]).data
        keep = np.isfinite(registered) & ~truth["change_mask"]
        out["registration_rmse_255"] = float(np.sqrt(np.mean((registered[keep] - distorted[keep]) ** 2)) * 255)
    except InputError:
        out["registration_rmse_255"] = None
    return Evaluation(**out)
