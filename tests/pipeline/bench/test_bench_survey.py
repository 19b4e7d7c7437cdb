"""The survey section's per-stage split of the tile tasks' CPU time."""

import numpy as np
import pytest
import zarr

from rsmb.pipeline.bench._bench_survey import stage_cpu_per_megapixel


def _store(path, shape, cpu_s):
    group = zarr.open_group(str(path), mode="w")
    group.create_array("change_mask", shape=shape, dtype="uint8", chunks=shape)
    group.attrs["summary"] = {"timings": {"cpu_s": cpu_s}}
    return path


def test_stage_cpu_is_summed_over_stores_and_divided_by_their_pixels(tmp_path):
    a = _store(tmp_path / "a.zarr", (1000, 500), {"start": 0.3, "rows": 0.2, "total": 0.5})
    b = _store(tmp_path / "b.zarr", (500, 1000), {"start": 0.1, "rows": 0.6, "total": 0.7})
    per_mp = stage_cpu_per_megapixel([a, b])  # 1 MP in all
    assert per_mp == pytest.approx({"start": 0.4, "rows": 0.8, "total": 1.2})
    assert stage_cpu_per_megapixel([a]) == pytest.approx({"start": 0.6, "rows": 0.4, "total": 1.0})
    assert stage_cpu_per_megapixel([]) == {}
    assert np.isfinite(list(per_mp.values())).all()
