"""``rsmb bench``: the figures the issues ask for, measured side by side in one run.

Sections (``--sections``):

- ``oracle``: the fast row solver against the exact cvxpy (CLARABEL) eq. 13 on
  row problems from real aerial images (if ``--data`` has them) and synthetic
  scenes: largest relative objective difference, per-row times and their ratio.
- ``speed``: ``detect`` end to end (threads, all cores) on a synthetic pair with
  in-plane motion and the paper's neighbourhoods, with the automatic ones (with
  and without the slow yaw/pitch part), and translation only; ECC homography
  time on the same image; DIS dense flow with rsmb's change rule on the same
  pair (seconds, F-measure, rsmb's time as a ratio of it); each run's
  CPU-seconds per stage (summed over its tasks) as a table.
- ``real``: the rolling-shutter captures of ``--data`` (GS frame against its RS
  frame, no change): registration RMSE of ``detect``, of the ECC and ORB
  homographies and of DIS dense flow on the same pixels; false changes.
- ``yaw``, ``parallax``, ``intensity``: camera yaw and pitch, raised
  structures, clipped highlights and bit depths (:mod:`pipeline.bench._bench_method`).
- ``realclip``: real aerial photographs stretched so that about 1 % of their
  pixels sit at 0 and 1 % at 255, new dark objects on the clipped-white areas
  and bright ones in the clipped-black, 4096^2 (``--quick``: 1024^2): F,
  recall on the objects on clipped areas, pixels with no evidence, seconds,
  beside DIS dense flow with rsmb's change rule (:mod:`pipeline.bench._bench_realclip`).
- ``scale``: GeoTIFF pairs of growing size through ``rsmb detect`` in a
  subprocess, with detect's default tiles and with 512-px tiles: peak resident
  memory (``ru_maxrss`` of the process), throughput against the per-tile
  kernel rate, tasks per tile.

Synthetic pairs are rendered by the independent cubic renderer
(``interpolation="cubic"``), never by the solver's own bilinear warp.
- ``gain``: a smooth gain ramp 0.7 -> 1.3: per-tile gain error and F-measure.
- ``survey``: georeferenced pairing on real aerial images, and a night of
  captures against one large detect (:mod:`pipeline.bench._bench_survey`).
- ``history``: three nights of ``rsmb survey`` into one folder, a change that
  appears, persists and goes and one seen by two overlapping captures: the
  statuses of ``changes.gpkg`` against the truth, and the end-of-night step's
  CPU-seconds (:mod:`pipeline.bench._bench_history`).
- ``ground``: a night whose captures' georeferencing is off by a few metres:
  the distance from each true change to its polygon, and the products against
  the store's ground frame (:mod:`pipeline.bench._bench_ground`).
"""

import contextlib
import json
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from rsmb import ops
from rsmb import tiles
from rsmb.ops.registration._rowproblem import _RowProblem

from ..detection._detect import detect
from ..detection._plan import DetectConfig, default_tile
from .._evaluate import evaluate
from .._synth import write_pair
from ._baseline import dis_flow, ecc_homography, opencv_threads, orb_homography

__all__ = ["SECTIONS", "run_bench"]

SECTIONS = ("oracle", "speed", "real", "yaw", "parallax", "intensity", "realclip", "scale", "gain", "survey",
            "history", "ledger", "ground")
PAPER_INPLANE = dict(axes=("tx", "ty", "rz"), half_width=(3.0, 3.0, 2.0), step=(1.0, 1.0, 0.5))


def _echo(text):
    print(text, flush=True)


# ----------------------------------------------------------------------- oracle


def _row_problems(data, count, width, seed):
    """Row problems (F (N, K), g (N,)) with K = 441 (the paper's in-plane grid):
    a reference (real aerial image or synthetic scene) seen through the forward
    model with blur, noise and a pasted change."""
    rng = np.random.default_rng(seed)
    sources = []
    aerial = sorted(Path(data, "aerial").glob("*.png")) if data else []
    for path in aerial:
        sources.append(("aerial/" + path.name, tiles.read_image(path).data))
    sources.append(("synthetic", ops.aerial_scene((1024, 1024), seed=seed)))
    params = ops.RegistrationParams(**PAPER_INPLANE)
    problems = []
    per_source = int(np.ceil(count / len(sources)))
    for name, image in sources:
        h, w = image.shape
        for q in range(per_source):
            y0, x0 = rng.integers(40, h - 80), rng.integers(40, w - width - 40)
            ref = image[y0 - 40:y0 + 40, x0 - 40:x0 + width + 40].astype(np.float32)
            camera = ops.Camera.for_shape((80, width + 80))
            pose = np.array([rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(-1, 1)])
            path = ops.CameraPath(np.array([0.0, 100.0]),
                                  ops.full_poses(np.stack([pose, pose + [1.5, 0.5, 0.3]]), params.axes))
            seen = ops.render(ref, path, shape=(1, width), camera=camera, exposure=40.0,
                              source_origin_yx=(40, 40), gain=rng.uniform(0.8, 1.2))
            g = seen.image[0] + rng.normal(0, 0.004, width).astype(np.float32)
            if q % 2:
                c = rng.integers(0, width - 40)
                g[c:c + 30] = np.clip(g[c:c + 30] + 0.4, 0, 1.5)
            space = params.resolved(camera).space
            index, poses = space.grid(pose)
            problem = _RowProblem(ref, g[None, :], np.ones((1, width), bool), camera, (-40, -40),
                                                (0, 0), params.axes, space.step, 8)
            a, gg, valid = problem.build([0], index, poses)
            problems.append((name, a.T.copy(), gg))
    return problems[:max(count, len(sources))]


def bench_oracle(data, *, count=60, width=512, seed=0, lam=(1e-3, 0.02)):
    problems = _row_problems(data, count, width, seed)
    worst, fast_t, exact_t, solver_t = 0.0, [], [], []
    by_source = {}
    for name, F, g in problems:
        t = time.perf_counter()
        _, _, fast = ops.solve_row_fast(F, g, lambda_w=lam[0], lambda_chi=lam[1])
        fast_t.append(time.perf_counter() - t)
        exact = ops.solve_row_exact(F, g, lambda_w=lam[0], lambda_chi=lam[1])
        exact_t.append(exact.solve_seconds)
        solver_t.append(exact.solver_seconds)
        rel = (fast - exact.objective) / exact.objective
        worst = max(worst, rel)
        by_source.setdefault(name, []).append(rel)
    out = {
        "problems": len(problems), "poses": int(problems[0][1].shape[1]), "pixels": int(problems[0][1].shape[0]),
        "max_relative_objective_excess": worst,
        "min_relative_objective_difference": float(min(min(v) for v in by_source.values())),
        "per_source": {k: {"count": len(v), "max": float(max(v))} for k, v in by_source.items()},
        "fast_ms_per_row": 1e3 * float(np.median(fast_t)),
        "cvxpy_clarabel_ms_per_row": 1e3 * float(np.median(exact_t)),
        "clarabel_solver_ms_per_row": 1e3 * float(np.median(solver_t)),
    }
    out["speedup"] = out["cvxpy_clarabel_ms_per_row"] / out["fast_ms_per_row"]
    out["speedup_over_solver_alone"] = out["clarabel_solver_ms_per_row"] / out["fast_ms_per_row"]
    _echo(f"oracle: {out['problems']} row problems, K={out['poses']} poses, N={out['pixels']} px: fast objective "
          f"- cvxpy objective <= {worst:.2e} relative (most negative {out['min_relative_objective_difference']:.2e}:"
          f" fast lower); fast {out['fast_ms_per_row']:.2f} ms/row vs cvxpy compile + CLARABEL "
          f"{out['cvxpy_clarabel_ms_per_row']:.0f} ms/row: {out['speedup']:.0f}x (CLARABEL's own solve time "
          f"{out['clarabel_solver_ms_per_row']:.0f} ms/row: {out['speedup_over_solver_alone']:.0f}x)")
    return out


# ------------------------------------------------------------------------ speed


EXPOSURE = 32.0  # row periods: the same blur per pixel whatever the image size


def _pair_files(directory, size, motion="inplane", seed=0, fmt="tif", **kw):
    """A synthetic pair on disk, rendered by the independent cubic renderer
    (the solver's own bilinear warp would flatter it); the exposure is fixed in
    row periods (the synth default, H / 16, would blur rotations more the
    larger the image)."""
    pair = ops.synthesize_pair((size, size), motion=motion, seed=seed, noise=0.002, exposure=EXPOSURE,
                               interpolation="cubic", **kw)
    ref, dist = write_pair(directory, pair, fmt=fmt, overwrite=True)
    return pair, ref, dist


def _detect_rate(ref, dist, store, config, workers):
    summary = detect(ref, dist, store, config=config, workers=workers, overwrite=True)
    return summary


def bench_speed(workdir, *, size=2048, workers=None):
    out = {"size": size}
    pair, ref, dist = _pair_files(Path(workdir, "speed_inplane"), size, changes=30)
    cases = {
        "inplane_paper_neighbourhoods": DetectConfig(registration=ops.RegistrationParams(**PAPER_INPLANE)),
        "inplane_auto_neighbourhoods": DetectConfig(),
        "inplane_without_slow_part": DetectConfig(registration=ops.RegistrationParams(slow_axes=())),
    }
    for name, config in cases.items():
        s = _detect_rate(ref, dist, Path(workdir, f"{name}.zarr"), config, workers)
        scores = evaluate(Path(workdir, f"{name}.zarr"), Path(workdir, "speed_inplane"))
        out[name] = {"megapixels_per_s": s.megapixels_per_s, "seconds": s.timings["total_s"],
                     "f_measure": scores.changes.f_measure, "cpu_s": s.timings["cpu_s"]}
    _dis_beside(out, pair, Path(workdir, "inplane_auto_neighbourhoods.zarr"), workers)
    t = time.perf_counter()
    with opencv_threads(workers):
        ecc = ecc_homography(pair.reference, pair.distorted)
    out["ecc_seconds"] = time.perf_counter() - t
    keep = np.isfinite(ecc.registered) & ~pair.change_mask
    out["ecc_registration_rmse_255"] = float(np.sqrt(np.mean((ecc.registered - pair.distorted)[keep] ** 2)) * 255)
    config = DetectConfig(registration=ops.RegistrationParams(axes=("tx", "ty"), half_width=(3.0, 3.0),
                                                              step=(1.0, 1.0), search=(20.0, 20.0)))
    for side in (size, 2 * size):
        _, ref_t, dist_t = _pair_files(Path(workdir, f"speed_translation_{side}"), side, motion="translation",
                                       changes=30)
        s = _detect_rate(ref_t, dist_t, Path(workdir, f"translation_{side}.zarr"), config, workers)
        out[f"translation_only_{side}"] = {"megapixels_per_s": s.megapixels_per_s,
                                           "seconds": s.timings["total_s"], "cpu_s": s.timings["cpu_s"]}
        shutil.rmtree(Path(workdir, f"speed_translation_{side}"), ignore_errors=True)
        shutil.rmtree(Path(workdir, f"translation_{side}.zarr"), ignore_errors=True)
    out["translation_only"] = out[f"translation_only_{size}"]
    out["slow_part_throughput_ratio"] = (out["inplane_auto_neighbourhoods"]["megapixels_per_s"]
                                         / out["inplane_without_slow_part"]["megapixels_per_s"])
    _echo(f"speed ({size} x {size}, {os.cpu_count()} cores): in-plane, paper neighbourhoods "
          f"{out['inplane_paper_neighbourhoods']['megapixels_per_s']:.2f} MP/s "
          f"(F {out['inplane_paper_neighbourhoods']['f_measure']:.3f}); automatic neighbourhoods "
          f"{out['inplane_auto_neighbourhoods']['megapixels_per_s']:.2f} MP/s "
          f"(F {out['inplane_auto_neighbourhoods']['f_measure']:.3f}; without the slow yaw/pitch part "
          f"{out['inplane_without_slow_part']['megapixels_per_s']:.2f} MP/s, F "
          f"{out['inplane_without_slow_part']['f_measure']:.3f}: the default runs at "
          f"{out['slow_part_throughput_ratio']:.2f}x); translation only "
          f"{out['translation_only']['megapixels_per_s']:.2f} MP/s (at {2 * size} x {2 * size}: "
          f"{out[f'translation_only_{2 * size}']['megapixels_per_s']:.2f} MP/s); ECC homography "
          f"{out['ecc_seconds']:.2f} s "
          f"on the same image (its registration RMSE {out['ecc_registration_rmse_255']:.2f} /255)")
    _echo(f"speed ({size} x {size}): DIS dense flow (medium, OpenCV on {out['dis']['threads']} threads) with "
          f"rsmb's change rule on the same pair "
          f"{out['dis']['seconds']:.2f} s, F {out['dis']['f_measure']:.3f}; rsmb (automatic neighbourhoods) "
          f"{out['inplane_auto_neighbourhoods']['seconds']:.2f} s, F {out['inplane_auto_neighbourhoods']['f_measure']:.3f}:"
          f" {out['rsmb_over_dis_seconds']:.2f}x DIS's time")
    _echo(stage_table({k: v["cpu_s"] for k, v in out.items()
                       if isinstance(v, dict) and "cpu_s" in v and k != "translation_only"}))
    return out


def _dis_beside(out, pair, store, workers):
    """DIS dense flow (medium) with rsmb's change rule on the in-plane pair, in
    the same run (:func:`pipeline.bench._bench_realclip.dis_changes`, OpenCV
    on ``workers`` threads, rsmb's cores): its seconds and F-measure, and
    rsmb's time as a ratio of it."""
    from ._bench_realclip import dis_changes

    factor = ops.IntensityScale.from_dict(tiles.open_result_store(store).attrs["intensity"]).scaled(1.0)
    t = time.perf_counter()
    with opencv_threads(workers) as threads:  # DIS on the cores rsmb had
        mask = dis_changes(np.clip(pair.reference, 0, 1).astype(np.float32),
                           np.clip(pair.distorted, 0, 1).astype(np.float32), factor=factor)
    out["dis"] = {"seconds": time.perf_counter() - t, "threads": threads,
                  "f_measure": ops.confusion(mask, pair.change_mask).f_measure}
    out["rsmb_over_dis_seconds"] = out["inplane_auto_neighbourhoods"]["seconds"] / out["dis"]["seconds"]


def stage_table(runs):
    """Text table of CPU-seconds per stage (rows) and run (columns), summed over
    each run's tasks (``timings["cpu_s"]`` of :func:`detect`)."""
    names = list(runs)
    stages = list(dict.fromkeys(k for r in runs.values() for k in r))
    width = max(len(s) for s in stages + ["stage (CPU s)"])
    lines = ["stage (CPU s)".ljust(width) + "".join(f"  {n[:28]:>28}" for n in names)]
    for stage in stages:
        lines.append(stage.ljust(width) + "".join(f"  {runs[n].get(stage, 0.0):28.2f}" for n in names))
    return "\n".join(lines)


# ------------------------------------------------------------------------- real


REAL_PAIRS = {
    "bsrsc_seq_01": ("rolling_shutter/bsrsc_seq_01/gs_0_m.png", "rolling_shutter/bsrsc_seq_01/rs_0.png"),
    "fastec_seq_01": ("rolling_shutter/fastec_seq_01/gs_1.png", "rolling_shutter/fastec_seq_01/rs_1.png"),
    # the sequence's second pair: no default was chosen on it (held out)
    "bsrsc_seq_01 frame 1": ("rolling_shutter/bsrsc_seq_01/gs_1_m.png", "rolling_shutter/bsrsc_seq_01/rs_1.png"),
}


def bench_real(data, workdir, *, workers=None):
    """Real rolling-shutter captures against their global-shutter frame (no
    change): registration RMSE of rsmb and of what a user would pick instead
    (ECC and ORB homographies, DIS dense flow), all on the pixels every method
    covers; the changes rsmb reports are all false."""
    out = {}
    for name, (ref_rel, dist_rel) in REAL_PAIRS.items():
        ref_path, dist_path = Path(data, ref_rel), Path(data, dist_rel)
        if not (ref_path.exists() and dist_path.exists()):
            continue
        store = Path(workdir, f"real_{name.replace(' ', '_')}.zarr")
        s = detect(ref_path, dist_path, store, workers=workers, overwrite=True)
        reference, distorted = tiles.read_image(ref_path).data, tiles.read_image(dist_path).data
        registered = {"rsmb": tiles.open_result_store(store)["registered"][:]}
        seconds = {"rsmb": s.timings["total_s"]}
        # the same run with --no-layers: the depth map's share of the result
        off = detect(ref_path, dist_path, store, workers=workers, overwrite=True,
                     config=DetectConfig(changes=ops.ChangeParams(layers=False)))
        registered["rsmb --no-layers"] = tiles.open_result_store(store)["registered"][:]
        seconds["rsmb --no-layers"] = off.timings["total_s"]
        for method, run in (("ecc", lambda: ecc_homography(reference, distorted).registered),
                            ("orb", lambda: orb_homography(reference, distorted).registered),
                            ("dis", lambda: dis_flow(reference, distorted))):
            t = time.perf_counter()
            with opencv_threads(workers):  # on the cores rsmb had
                registered[method] = run()
            seconds[method] = time.perf_counter() - t
        common = np.all([np.isfinite(r) for r in registered.values()], axis=0)
        rmse = {k: float(np.sqrt(np.mean((r[common] - distorted[common]) ** 2)) * 255) for k, r in registered.items()}
        best_homography = min(rmse["ecc"], rmse["orb"])
        r = out[name] = {"rmse_255": rmse, "seconds": seconds, "identity_rmse_255": float(
            np.sqrt(np.mean((reference[common] - distorted[common]) ** 2)) * 255), "common_fraction": float(common.mean()),
            "rsmb_over_best_homography": rmse["rsmb"] / best_homography, "rsmb_over_dis": rmse["rsmb"] / rmse["dis"],
            "false_change_fraction": s.changed_fraction, "parallax_fraction": s.parallax_pixels / distorted.size,
            "false_change_fraction_no_layers": off.changed_fraction,
            "clipped_fraction": max(s.clipped_reference, s.clipped_capture), "stage_cpu_s": s.timings["cpu_s"]}
        _echo(f"real {name} ({distorted.shape[1]} x {distorted.shape[0]} px): registration RMSE rsmb {rmse['rsmb']:.2f}, "
              f"ECC homography {rmse['ecc']:.2f}, ORB homography {rmse['orb']:.2f}, DIS dense flow {rmse['dis']:.2f} "
              f"(no registration {r['identity_rmse_255']:.2f}; 0..255 on the {100 * r['common_fraction']:.0f} % all "
              f"cover): rsmb {r['rsmb_over_best_homography']:.2f}x the better homography, {r['rsmb_over_dis']:.2f}x "
              f"DIS; false changes {100 * r['false_change_fraction']:.2f} % of pixels (parallax "
              f"{100 * r['parallax_fraction']:.2f} %); rsmb {seconds['rsmb']:.1f} s, DIS {seconds['dis']:.2f} s; "
              f"with --no-layers: RMSE {rmse['rsmb --no-layers']:.2f}, false changes "
              f"{100 * r['false_change_fraction_no_layers']:.2f} %, {seconds['rsmb --no-layers']:.1f} s")
    if out:  # where each real capture's CPU goes (re-anchoring: the block solves of rows that jumped)
        _echo("real captures, CPU-seconds by stage")
        _echo(stage_table({name: r["stage_cpu_s"] for name, r in out.items()}))
    else:
        _echo(f"real: no rolling-shutter captures under {data}; skipped")
    return out


# ------------------------------------------------------------------------ scale


#: Runs a command and writes its peak resident memory (``ru_maxrss`` from
#: ``os.wait4``) to a file.  A fork keeps the high-water mark of the process
#: it copied, through ``exec``: measured directly, a child of this large
#: process would report this process's size.  Forked from this small launcher,
#: the child reports its own.
_LAUNCHER = ("import os, subprocess, sys\n"
             "proc = subprocess.Popen(sys.argv[2:])\n"
             "_, status, usage = os.wait4(proc.pid, 0)\n"
             "open(sys.argv[1], 'w').write(str(usage.ru_maxrss))\n"
             "sys.exit(os.waitstatus_to_exitcode(status))\n")


def _peak_rss(cmd):
    """Run ``cmd``; return (its stdout, its peak resident memory in MB as the
    operating system accounts it, seconds)."""
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp, "maxrss")
        start = time.perf_counter()
        proc = subprocess.run([sys.executable, "-I", "-c", _LAUNCHER, str(report), *map(str, cmd)],
                              capture_output=True, text=True)
        seconds = time.perf_counter() - start
        if proc.returncode:
            raise RuntimeError(f"{' '.join(map(str, cmd))} failed: {proc.stderr.strip()[-2000:]}")
        maxrss = int(report.read_text())
    kib = maxrss / 1024 if sys.platform == "darwin" else maxrss  # macOS reports bytes
    return proc.stdout, kib * 1024 / 1e6, seconds


def bench_scale(workdir, *, sizes=(2048, 4096, 8192), tiles=(None, 512)):
    """Each size with each tile size (None: detect's default).  The default
    switches from 512 to 1024 px at 4096^2, so one fixed size shows how memory
    follows the image alone."""
    out = {}
    workers = os.cpu_count() or 1
    for size in sizes:
        directory = Path(workdir, f"scale_{size}")
        _pair_files(directory, size, changes=max(8, size * size // 100000))
        runs = {}  # tile side -> result: a fixed size equal to the default is not run twice
        for tile in tiles:
            label = f"{tile}-px tiles" if tile else "default tiles"
            side = tile or default_tile((size, size))
            if side in runs:
                out.setdefault(label, {})[size] = runs[side]
                _echo(f"scale {size} x {size}, {label}: the run above ({side}-px tiles)")
                continue
            store = Path(workdir, f"scale_{size}_{tile or 'default'}.zarr")
            cmd = [sys.executable, "-m", "rsmb", "-q", "detect", str(directory / "reference.tif"),
                   str(directory / "distorted.tif"), "-o", str(store), "--overwrite", "--json"]
            if tile:
                cmd += ["--tile-size", str(tile)]
            stdout, peak, _ = _peak_rss(cmd)
            s = json.loads(stdout)
            t = s["timings"]
            megapixels = size * size / 1e6
            # the per-tile kernels: registration, and the change masks (labels, holes,
            # mapping to the reference); what the run spends beyond them is
            # scheduling and I/O (ingest, zarr reads and writes, idle workers)
            compute = (t["kernel_s_sum"] + t["changes_compute_s_sum"]) / workers
            kernel_rate = megapixels / compute
            registration_rate = megapixels / (t["kernel_s_sum"] / workers)
            scores = evaluate(store, directory)
            shutil.rmtree(store, ignore_errors=True)
            r = runs[side] = out.setdefault(label, {})[size] = {
                "peak_rss_mb": peak, "megapixels_per_s": s["megapixels_per_s"],
                "kernel_megapixels_per_s": kernel_rate, "scheduling_io_fraction": 1 - compute / t["total_s"],
                "registration_megapixels_per_s": registration_rate,
                "beyond_registration_fraction": 1 - s["megapixels_per_s"] / registration_rate, "timings": t,
                "tasks_per_tile": s["tasks_per_tile"], "tiles": s["tiles"], "tile_size": s["tile_size"],
                "halo": s["halo"], "seconds": t["total_s"], "f_measure": scores.changes.f_measure}
            _echo(f"scale {size} x {size}, {label}: peak RSS {r['peak_rss_mb']:.0f} MB, "
                  f"{r['megapixels_per_s']:.2f} MP/s end to end vs {r['kernel_megapixels_per_s']:.2f} MP/s per-tile "
                  f"kernels (registration and change masks) x {workers} workers: scheduling and I/O "
                  f"{100 * r['scheduling_io_fraction']:.1f} % (ingest {t['ingest_s']:.1f} s, change stage "
                  f"{t['changes_s']:.1f} s); registration alone {r['registration_megapixels_per_s']:.2f} MP/s (all "
                  f"else {100 * r['beyond_registration_fraction']:.1f} %); {r['tasks_per_tile']:.1f} tasks/tile, "
                  f"{r['tiles'][0]}x{r['tiles'][1]} tiles of {r['tile_size']} px, halo {r['halo']} px, "
                  f"F {r['f_measure']:.3f}, {r['seconds']:.0f} s")
        shutil.rmtree(directory, ignore_errors=True)
    for label, runs in out.items():
        peaks = " / ".join(f"{r['peak_rss_mb']:.0f}" for r in runs.values())
        _echo(f"scale, {label}: peak RSS {peaks} MB at {' / '.join(f'{n}^2' for n in runs)}")
        smallest = min(runs)
        for size, r in runs.items():
            if size != smallest:
                # issue 17 item 4: a large image at least as fast per megapixel as a small one
                r["rate_vs_smallest"] = r["megapixels_per_s"] / runs[smallest]["megapixels_per_s"]
                r["cpu_per_megapixel_vs_smallest"] = (r["timings"]["cpu_s"]["total"] / size ** 2) / (
                    runs[smallest]["timings"]["cpu_s"]["total"] / smallest ** 2)
                _echo(f"scale, {label}: {size}^2 runs at {r['rate_vs_smallest']:.2f}x {smallest}^2's MP/s end to "
                      f"end and spends {r['cpu_per_megapixel_vs_smallest']:.2f}x its CPU-seconds per megapixel in the "
                      f"stages")
        # where each size spends its CPU per megapixel (summed over the tasks, per stage)
        _echo(f"scale, {label}: CPU-seconds per megapixel by stage")
        _echo(stage_table({f"{size}^2": {k: v / (size * size / 1e6) for k, v in r["timings"]["cpu_s"].items()}
                           for size, r in runs.items()}))
    return out


# ------------------------------------------------------------------------- gain


def bench_gain(workdir, *, size=2048, workers=None):
    """Stored as float: in a 16-bit file the brightest parts of the 30 %
    brighter side (bright pasted objects above all) would sit at the
    saturation value, which carries no evidence by rule."""
    directory = Path(workdir, "gain")
    _, ref, dist = _pair_files(directory, size, gain=(0.7, 1.3), changes=30, fmt="npy")
    store = Path(workdir, "gain.zarr")
    cpu = detect(ref, dist, store, workers=workers, overwrite=True).timings["cpu_s"]
    scores = evaluate(store, directory)
    out = {"max_relative_gain_error": scores.gain["max_relative_error"],
           "f_measure": scores.changes.f_measure, "stage_cpu_s": cpu}
    _echo(f"gain ramp 0.7 -> 1.3 ({size} x {size}): per-tile gain error max "
          f"{100 * out['max_relative_gain_error']:.2f} %, F {out['f_measure']:.3f}; {cpu['total']:.1f} CPU-s, "
          f"re-anchoring {cpu['reanchor']:.1f}, gain-slope rounds {cpu['gain_slope']:.1f}, rows {cpu['rows']:.1f}")
    return out


@contextlib.contextmanager
def _quiet_runs():
    """The runs' own progress lines (INFO) off unless debugging (``-vv``): the
    bench prints its figures."""
    log = logging.getLogger("rsmb")
    level = log.level
    if log.getEffectiveLevel() > logging.DEBUG:
        log.setLevel(max(log.getEffectiveLevel(), logging.WARNING))
    try:
        yield
    finally:
        log.setLevel(level)


def run_bench(*, sections=SECTIONS, data=None, quick=False, workdir=None, sizes=None, workers=None, tile=None):
    """Run the benchmark sections; returns a dict of results (also printed)."""
    data = Path(data) if data else None
    if data is not None and not data.exists():
        _echo(f"bench: data directory {data} not found; real-image parts are skipped")
        data = None
    sections = set(sections)
    results = {"cores": os.cpu_count(), "quick": quick}
    with tempfile.TemporaryDirectory(prefix="rsmb-bench-", dir=workdir) as tmp, _quiet_runs():
        if "oracle" in sections:
            results["oracle"] = bench_oracle(data, count=12 if quick else 60, width=256 if quick else 512)
        if "speed" in sections:
            results["speed"] = bench_speed(tmp, size=512 if quick else 2048, workers=workers)
        if "real" in sections and data is not None:
            results["real"] = bench_real(data, tmp, workers=workers)
        if sections & {"yaw", "parallax", "intensity"}:
            from ._bench_method import bench_intensity, bench_parallax, bench_yaw

            if "yaw" in sections:
                results["yaw"] = bench_yaw(data, tmp, sizes=(512,) if quick else (512, 2048), workers=workers)
            if "parallax" in sections:
                results["parallax"] = bench_parallax(tmp, sizes=(512,) if quick else (512, 1024), workers=workers)
            if "intensity" in sections:
                results["intensity"] = bench_intensity(tmp, size=256 if quick else 1024, workers=workers)
        if "realclip" in sections:
            from ._bench_realclip import bench_realclip

            results["realclip"] = bench_realclip(data, tmp, size=1024 if quick else 4096, workers=workers)
        if "scale" in sections:
            results["scale"] = bench_scale(tmp, sizes=sizes or ((512, 1024) if quick else (2048, 4096, 8192)),
                                           tiles=(tile,) if tile else (None, 512))
        if "gain" in sections:
            results["gain"] = bench_gain(tmp, size=512 if quick else 2048, workers=workers)
        if "survey" in sections:
            from ._bench_survey import bench_survey

            results["survey"] = bench_survey(data, tmp, quick=quick)
        if "history" in sections:
            from ._bench_history import bench_history

            results["history"] = bench_history(tmp)
        if "ledger" in sections:
            from ._bench_ledger import bench_ledger

            results["ledger"] = bench_ledger(tmp, count=1000 if quick else 10_000)
        if "ground" in sections:
            from ._bench_ground import bench_ground

            results["ground"] = bench_ground(data, tmp, quick=quick)
    return results
