"""The ``survey`` section of ``rsmb bench``: georeferenced pairing on real
aerial images, and a night's throughput against one large detect.

- Pairing: a real aerial photograph (``--data``'s ``aerial/``, else a
  procedural scene) is the ground and the reference; a 512 x 512 capture of a
  window of it (the forward model, pasted changes) is run against the
  reference as a larger mosaic, split over two files it straddles, resampled
  to finer (0.4 and 0.25 m) and coarser (0.7 m) pixels, reprojected to EPSG:3857 and EPSG:4326, and
  partly covered; its F-measure is compared with two hand-cut same-grid pairs:
  the scene cut at the capture's grid at full resolution, and the user's own
  rasterio cuts of that case's reference (``rio warp --like``, nearest and
  the resampling rsmb chose; a coarser reference carries less than the
  full-resolution cut).
  A reference elsewhere and a capture 5 km away must exit 2.
- Night: 8 captures of 1024 x 1024 from a 4608 x 4608 scene through ``rsmb
  survey`` in a subprocess (command start to summary written, reports
  included), beside ``rsmb detect`` on one 4096 x 4096 capture of the same
  scene, made the same way, in the same run; then the same night again
  (everything skipped).
"""

import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from rsmb import ops
from rsmb import tiles

from ._archive import CaptureSpec, write_capture, write_reference
from ..detection._detect import detect
from .._evaluate import evaluate

__all__ = ["bench_survey", "stage_cpu_per_megapixel"]

PAIRING_CASES = {
    "larger mosaic": {},
    "two files, straddled": {"split": 2},
    "finer pixels (0.4 m)": {"pixel": 0.4},
    "finer pixels (0.25 m)": {"pixel": 0.25},
    "coarser pixels (0.7 m)": {"pixel": 0.7},
    "EPSG:3857": {"crs": "EPSG:3857"},
    "EPSG:4326": {"crs": "EPSG:4326"},
}


#: The resampling of ``rio warp`` when none is given: the first of the user's own cuts.
USER_DEFAULT = "nearest"


def _echo(text):
    print(text, flush=True)


def _scene(data, shape, seed=5):
    """A real aerial photograph scaled to ``shape`` (bicubic) with its 0.5 and
    99.5 percentiles at 0.05 and 0.75, else a procedural scene."""
    import cv2

    images = sorted(Path(data, "aerial").glob("*.png")) if data else []
    if not images:
        return (0.05 + 0.7 * ops.aerial_scene(shape, seed=seed)).astype(np.float32), "procedural"
    image = tiles.read_image(images[0]).data
    image = cv2.resize(image, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
    lo, hi = np.percentile(image, [0.5, 99.5])
    scene = np.clip(0.05 + 0.7 * (image - lo) / max(float(hi - lo), 1e-6), 0.0, 1.0).astype(np.float32)
    return scene, f"aerial/{images[0].name}"


def _f(store, truth, valid=None):
    """Change counts of ``store`` against the truth, on ``valid`` pixels only when given."""
    if valid is None:
        return evaluate(store, truth).changes
    import cv2

    mask = tiles.open_result_store(store)["change_mask"][:] == 1
    truth_mask = cv2.imread(str(Path(truth, "change_mask.png")), cv2.IMREAD_UNCHANGED) > 0
    return ops.confusion(mask, truth_mask, valid=valid)


def _rsmb(*args):
    return subprocess.run([sys.executable, "-m", "rsmb", *map(str, args)], capture_output=True, text=True)


def _measured(*args, codes=(0,)):
    """:func:`_rsmb` for a run the bench measures: any other exit code than
    ``codes`` stops the bench with the command's own message."""
    proc = _rsmb(*args)
    if proc.returncode not in codes:
        raise RuntimeError(f"rsmb {' '.join(map(str, args))} exited {proc.returncode}: {proc.stderr.strip()[-2000:]}")
    return proc


def _child_cpu():
    """CPU-seconds (user + system) of the finished child processes so far."""
    use = resource.getrusage(resource.RUSAGE_CHILDREN)
    return use.ru_utime + use.ru_stime


def _user_cut(references, capture, target, resampling=USER_DEFAULT):
    """What a user cuts by hand from ``references`` for ``capture``: each file
    reprojected onto the capture's grid with rasterio (``rio warp --like
    capture.tif --resampling RESAMPLING``), the first file with data winning, in
    the references' dtype, 0 = nodata."""
    import rasterio
    from rasterio.warp import Resampling, reproject

    with rasterio.open(capture) as cap:
        profile = cap.profile | dict(nodata=0)
        cut = None
        for path in references:
            with rasterio.open(path) as src:
                warped = np.zeros((cap.height, cap.width), src.dtypes[0])
                reproject(rasterio.band(src, 1), warped, dst_transform=cap.transform, dst_crs=cap.crs,
                          src_nodata=src.nodata, dst_nodata=0, resampling=Resampling[resampling])
            cut = warped if cut is None else np.where(cut == 0, warped, cut)
    with rasterio.open(target, "w", **(profile | dict(dtype=cut.dtype.name))) as dst:
        dst.write(cut, 1)
    return Path(target)


def _metric_pixel(reference, capture):
    """(x, y) size in the capture CRS's units of the reference's centre pixel."""
    import rasterio
    from rasterio.warp import transform

    with rasterio.open(reference) as ref, rasterio.open(capture) as cap:
        c, r = ref.width / 2, ref.height / 2
        xs, ys = ref.transform @ (np.array([c, c + 1, c]), np.array([r, r, r + 1]))
        xs, ys = transform(ref.crs, cap.crs, np.asarray(xs).tolist(), np.asarray(ys).tolist())
    return float(np.hypot(xs[1] - xs[0], ys[1] - ys[0])), float(np.hypot(xs[2] - xs[0], ys[2] - ys[0]))


def _pairing_case(work, name, references, capture, truth, base, valid_from_store=False):
    """F of rsmb on the reference set, of the user's rasterio cuts of the same set
    (``rio warp``'s default resampling and the one rsmb chose), and rsmb's deltas
    against them and against the full-resolution hand cut (``base``: F of a
    callable of the valid pixels, None for all)."""
    slug = name.replace(" ", "_").replace(":", "")
    result = detect(references, capture, work / f"{slug}.zarr")
    valid = np.isfinite(tiles.open_result_store(work / f"{slug}.zarr")["registered"][:]) if valid_from_store else None
    counts = _f(work / f"{slug}.zarr", truth, valid)
    grid = tiles.RasterGrid.from_path(capture)
    how = list(dict.fromkeys(tiles.resampling_for(tiles.RasterGrid.from_path(r), grid) for r in references))
    users = {}
    for resampling in dict.fromkeys([USER_DEFAULT] + [h for h in how if h != "copy"]):
        cut = _user_cut(references, capture, work / f"{slug}_user_{resampling}.tif", resampling)
        detect(cut, capture, work / f"{slug}_user_{resampling}.zarr")
        users[resampling] = _f(work / f"{slug}_user_{resampling}.zarr", truth, valid).f_measure
    full = base(valid)
    return {"f_measure": counts.f_measure, "precision": counts.precision, "recall": counts.recall,
            "full_cut_f": full, "delta": counts.f_measure - full, "user_cut_f": users,
            "delta_user_cut": {k: counts.f_measure - v for k, v in users.items()},
            "coverage": result.reference_coverage, "resampling": ",".join(how),
            "pixel_m": _metric_pixel(references[0], capture)}


def bench_pairing(data, workdir, *, size=512):
    """Georeferenced pairing cases against two kinds of hand-cut pair: the
    full-resolution cut (the scene at the capture's grid) and the user's rasterio
    cuts of the same case's reference (``rio warp --like``, with its default
    resampling, nearest, and with the resampling rsmb chose): their difference is
    what the reference set carries, rsmb's delta to the latter what its pairing
    costs."""
    work = Path(workdir, "pairing")
    scene, source = _scene(data, (1024, 1024))
    spec = CaptureSpec((256, 300), (size, size), seed=7, changes=6, exposure=32.0)
    capture = work / "capture.tif"
    cut = write_capture(capture, scene, spec, hand_cut=work / "cut")
    truth = work / "capture.truth"
    detect(cut.reference, cut.distorted, work / "cut.zarr")
    full = {}

    def base(valid):
        key = None if valid is None else valid.tobytes()
        if key not in full:
            full[key] = _f(work / "cut.zarr", truth, valid).f_measure
        return full[key]

    out = {"scene": source, "hand_cut_f": base(None), "cases": {}}
    for name, kw in PAIRING_CASES.items():
        references = write_reference(work / name.replace(" ", "_"), scene, **kw)
        out["cases"][name] = _pairing_case(work, name, references, capture, truth, base)
    references = write_reference(work / "partial", scene[:, :300 + size * 2 // 3])
    out["cases"]["partial overlap"] = _pairing_case(work, "partial overlap", references, capture, truth, base,
                                                    valid_from_store=True)
    far = write_reference(work / "far", scene[:200, :200])
    moved = work / "moved.tif"
    write_capture(moved, scene, spec, offset_m=(5000.0, 0.0))
    codes = {"no overlap": _rsmb("detect", far[0], capture, "-o", work / "x.zarr"),
             "5 km apart": _rsmb("detect", cut.reference, moved, "-o", work / "y.zarr")}
    out["refused"] = {k: {"exit": p.returncode, "message": p.stderr.strip()} for k, p in codes.items()}
    _echo(f"survey pairing ({source}, {size} x {size} capture): F against the full-resolution hand cut "
          f"(F {out['hand_cut_f']:.3f}) and against the user's own rasterio cuts of the same reference "
          f"(rio warp --like capture.tif, {USER_DEFAULT} and the resampling rsmb chose)")
    for name, r in out["cases"].items():
        part = " on the covered part" if r["coverage"] < 1.0 else ""
        users = ", ".join(f"{r['delta_user_cut'][k]:+.3f} vs {k} cut {v:.3f}" for k, v in r["user_cut_f"].items())
        _echo(f"  {name:24s} F {r['f_measure']:.3f} ({r['delta']:+.3f} vs full-res cut {r['full_cut_f']:.3f}; "
              f"{users}){part}; reference {r['pixel_m'][0]:.2f} x {r['pixel_m'][1]:.2f} m, rsmb "
              f"{r['resampling']}, coverage {r['coverage']:.2f}")
    for name, r in out["refused"].items():
        _echo(f"  {name:24s} exit {r['exit']}: {r['message']}")
    return out


def stage_cpu_per_megapixel(stores):
    """The tile tasks' CPU-seconds per megapixel by stage (the stores'
    ``summary.timings.cpu_s``, :data:`~rsmb.pipeline.detection._detect.CPU_STAGES`
    and ``total``) summed over ``stores`` (detect stores) and divided by
    their pixels: where a night's small captures spend more per megapixel
    than one large capture (a start search and a slow part per capture) and
    where less."""
    totals, pixels = {}, 0
    for store in stores:
        group = tiles.open_result_store(store)
        for stage, seconds in group.attrs["summary"]["timings"]["cpu_s"].items():
            totals[stage] = totals.get(stage, 0.0) + float(seconds)
        pixels += int(np.prod(group["change_mask"].shape))
    return {stage: seconds / (pixels / 1e6) for stage, seconds in totals.items()} if pixels else {}


def bench_night(data, workdir, *, captures=8, side=1024, detect_side=4096):
    """A night of ``captures`` captures against one large detect, end to end.

    Both are windows of one scene made the same way (the forward model, the
    same motion, exposure and change density): the night's per-megapixel rate
    is compared with the large capture's on the same kind of content."""
    work = Path(workdir, "night")
    size = detect_side + side // 2
    scene, source = _scene(data, (size, size))
    references = write_reference(work / "reference", scene, split=2)
    spots = np.linspace(side // 8, size - side - side // 8, 3).astype(int)
    origins = [(int(r), int(c)) for r in spots for c in spots][:captures]
    for k, origin in enumerate(origins):
        write_capture(work / "incoming" / f"capture_{k}.tif", scene, CaptureSpec(origin, (side, side), seed=40 + k,
                                                                                 changes=10, exposure=32.0))
    large = write_capture(work / "large" / "capture.tif", scene,
                          CaptureSpec((side // 4, side // 4), (detect_side, detect_side), seed=39,
                                      changes=10 * (detect_side // side) ** 2, exposure=32.0),
                          hand_cut=work / "large" / "pair")
    megapixels = captures * side * side / 1e6

    def night_cmd(out, *extra):
        return ["survey", *references, "--captures", work / "incoming" / "*.tif", "-o", out, "--json", "--settle", "0",
                *extra]

    cmd = night_cmd(work / "out")
    start, cpu = time.perf_counter(), _child_cpu()
    first = _measured("-q", *cmd, codes=(0, 3))  # 3: some captures failed (counted below)
    night_s, night_cpu = time.perf_counter() - start, _child_cpu() - cpu
    summary = json.loads(first.stdout)
    start, cpu = time.perf_counter(), _child_cpu()
    again = json.loads(_measured("-q", *cmd, codes=(0, 3)).stdout)
    rerun_s, rerun_cpu = time.perf_counter() - start, _child_cpu() - cpu
    # the same night without the captures' HTML reports: the reports' share of the night
    start, cpu = time.perf_counter(), _child_cpu()
    _measured("-q", *night_cmd(work / "out_no_report", "--no-report"), codes=(0, 3))
    no_report_s, no_report_cpu = time.perf_counter() - start, _child_cpu() - cpu
    ref, dist = large.reference, large.distorted
    start, cpu = time.perf_counter(), _child_cpu()
    single = _measured("-q", "detect", ref, dist, "-o", work / "large.zarr")
    detect_s, detect_cpu = time.perf_counter() - start, _child_cpu() - cpu
    scores = [evaluate(c["output"] + "/changes.zarr", Path(c["capture"]).with_suffix(".truth")).changes.f_measure
              for c in summary["captures"] if c["status"] == "done"]
    out = {"scene": source, "captures": captures, "side": side, "night_s": night_s,
           "night_megapixels_per_s": megapixels / night_s, "done": summary["done"], "failed": summary["failed"],
           "rerun_s": rerun_s, "rerun_skipped": again["skipped"], "no_report_s": no_report_s,
           "no_report_cpu_s": no_report_cpu, "detect_side": detect_side, "detect_s": detect_s,
           "detect_megapixels_per_s": detect_side ** 2 / 1e6 / detect_s, "detect_exit": single.returncode,
           "f_measure_min": min(scores) if scores else float("nan"),
           "detect_f_measure": evaluate(work / "large.zarr", work / "large" / "capture.truth").changes.f_measure}
    out["ratio"] = out["night_megapixels_per_s"] / out["detect_megapixels_per_s"]
    # CPU-seconds per megapixel of each command (its process and the processes it waited for):
    # what the machine spends, whatever else runs beside
    out["night_cpu_s_per_megapixel"] = night_cpu / megapixels
    out["detect_cpu_s_per_megapixel"] = detect_cpu / (detect_side ** 2 / 1e6)
    out["cpu_ratio"] = out["detect_cpu_s_per_megapixel"] / out["night_cpu_s_per_megapixel"]
    out["rerun_cpu_s"] = rerun_cpu  # the night's own fixed cost: start, imports, decisions, end of night
    out["night_stage_cpu_s_per_megapixel"] = stage_cpu_per_megapixel(
        [c["output"] + "/changes.zarr" for c in summary["captures"] if c["status"] == "done"])
    out["detect_stage_cpu_s_per_megapixel"] = stage_cpu_per_megapixel([work / "large.zarr"])
    _echo(f"survey night ({source}): {captures} captures of {side} x {side} in {night_s:.1f} s end to end "
          f"({out['night_megapixels_per_s']:.2f} MP/s, {out['done']} done, F >= {out['f_measure_min']:.3f}) vs "
          f"rsmb detect on one {detect_side} x {detect_side} capture of the same scene {detect_s:.1f} s "
          f"({out['detect_megapixels_per_s']:.2f} MP/s, F {out['detect_f_measure']:.3f}): {100 * out['ratio']:.0f} %; the night again "
          f"{rerun_s:.1f} s ({100 * rerun_s / night_s:.0f} % of the first, {out['rerun_skipped']} skipped)")
    _echo(f"survey night, CPU-seconds per megapixel (user + system of each command): the night "
          f"{out['night_cpu_s_per_megapixel']:.2f}, detect {out['detect_cpu_s_per_megapixel']:.2f}: the night's rate "
          f"per CPU-second {100 * out['cpu_ratio']:.0f} % of detect's; the night again (nothing to run) "
          f"{rerun_cpu:.1f} CPU-s")
    rate = megapixels / no_report_s
    _echo(f"survey night without the captures' reports (--no-report): {no_report_s:.1f} s, {no_report_cpu:.1f} CPU-s "
          f"({rate:.2f} MP/s, {100 * rate / out['detect_megapixels_per_s']:.0f} % of detect's rate): the reports "
          f"take {100 * (1 - no_report_cpu / night_cpu):.0f} % of the night's CPU-seconds")
    night, large = out["night_stage_cpu_s_per_megapixel"], out["detect_stage_cpu_s_per_megapixel"]
    if night and large:  # the rest of each command's CPU is outside the tile tasks: products, report, I/O, imports
        stages = sorted((s for s in large if s != "total"), key=lambda s: -abs(night.get(s, 0.0) - large[s]))
        _echo("survey night, tile tasks' CPU-seconds per megapixel by stage, night vs detect: total "
              f"{night.get('total', 0.0):.2f} vs {large['total']:.2f} ("
              + ", ".join(f"{s} {night.get(s, 0.0):.3f} vs {large[s]:.3f}" for s in stages[:6]) + "); outside "
              f"the tile tasks {out['night_cpu_s_per_megapixel'] - night.get('total', 0.0):.2f} vs "
              f"{out['detect_cpu_s_per_megapixel'] - large['total']:.2f}")
    return out


def bench_survey(data, workdir, *, quick=False):
    out = {"pairing": bench_pairing(data, workdir, size=256 if quick else 512)}
    out["night"] = bench_night(data, workdir, captures=3 if quick else 8, side=512 if quick else 1024,
                               detect_side=1024 if quick else 4096)
    return out
