"""How fast the viewer (``ne-jax view``) answers (docs/viewer.md): frames per second of a ``tiny`` model
and an edit of its cloud resampled to 100,000 points, step by step; with ``--reference-path REF`` (``git
worktree add REF COMMIT``) against older code. Writes ``experiments/results/bench_view.{json,md}``.
``--screenshot PNG`` takes the docs' picture of the viewer in headless Chromium (selenium; the ``view``
and ``test`` extras, Debian's ``chromium`` and ``chromium-driver``)::

    python -m experiments.bench_view --run RUN          # RUN: a tiny model (`ne-jax train ... --preset tiny`)
    python -m experiments.bench_view --run RUN --reference-path REF
    python -m experiments.bench_view                    # trains one first (tiny blocks, a few minutes)
    python -m experiments.bench_view --run RUN --screenshot docs/images/viewer.png
"""

from __future__ import annotations

import argparse
import functools
import json
import operator
import os
import platform
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from experiments.common import RESULTS, ROOT, against_reference, entry, json_from, write_results


def _tiny_run(work: Path) -> Path:
    from ne_jax.benchmark.generate import PRESETS, generate_scene
    from ne_jax.train import RunConfig, train

    run = work / "run"
    if not (run / "config.json").is_file():
        if not (work / "bench" / "blocks" / "scene.json").is_file():
            generate_scene("blocks", PRESETS["tiny"], work / "bench", seed=0)
        train(RunConfig.tiny(), work / "bench" / "blocks", run, progress=False, log=print)
    return run


def _orbit(model, n: int):
    """``n`` OpenCV ``(wxyz, position)`` cameras on a circle around the cloud, looking at its centre,
    at the middle of the model's depth range (the benchmark's cameras: the object fills the view)."""
    try:
        from ne_jax.view.frames import look_at
    except ImportError:  # a reference checkout from before frames.look_at
        from ne_jax.view.edits import matrix_to_quat

        def look_at(position, target):
            fwd = (target - position) / np.linalg.norm(target - position)
            right = np.cross(fwd, (0, 0, 1.0))
            right /= np.linalg.norm(right)
            return matrix_to_quat(np.stack([right, np.cross(fwd, right), fwd], 1))

    xyz = np.asarray(model.scene.points.xyz)[np.asarray(model.scene.points.alive)]
    center = 0.5 * (xyz.min(0) + xyz.max(0))
    radius = 0.5 * (model.near + model.far) / np.linalg.norm([1.0, 0.5])  # the 0.5 below: elevation
    cams = []
    for a in np.linspace(0, 2 * np.pi, n, endpoint=False):
        pos = center + radius * np.array([np.cos(a), np.sin(a), 0.5])
        cams.append((look_at(pos, center), pos))
    return cams


def _fps(model, size: int, frames: int) -> dict:
    from ne_jax.view.frames import camera_from_viewer, render_frame

    cams = [camera_from_viewer(w, p, np.deg2rad(40), size, size) for w, p in _orbit(model, frames)]
    _, first = render_frame(model, cams[0])  # compiles
    times = [render_frame(model, c)[1] for c in cams]
    return {"size": size, "frames": frames, "first_frame_s": round(first, 3),
            "median_frame_s": round(float(np.median(times)), 4), "fps": round(1.0 / float(np.median(times)), 2),
            "min_frame_s": round(min(times), 4)}


def _resampled(model, n: int, seed: int = 0):
    """``model`` with its cloud resampled to ``n`` points (copies of alive points, jittered)."""
    import jax.numpy as jnp

    from ne_jax.geometry.points import PointState
    from ne_jax.render.renderer import PointScene

    pts = model.state.point_state(model.scene.points)
    alive = np.flatnonzero(np.asarray(pts.alive))
    rng = np.random.default_rng(seed)
    pick = np.concatenate([alive, rng.choice(alive, n - alive.size)]) if n > alive.size else alive[:n]
    xyz = np.asarray(pts.xyz)[pick]
    from scipy.spatial import cKDTree

    d, _ = cKDTree(xyz[: alive.size]).query(xyz[: alive.size], k=2)
    jitter = 0.1 * float(np.median(d[:, 1]))
    xyz = xyz + rng.normal(scale=jitter, size=xyz.shape) * (np.arange(n) >= alive.size)[:, None]
    big = PointState(xyz=jnp.asarray(xyz, pts.xyz.dtype), alive=jnp.ones(n, bool),
                     feature=jnp.asarray(np.asarray(pts.feature)[pick]),
                     conf_logit=jnp.asarray(np.asarray(pts.conf_logit)[pick]),
                     normal=jnp.asarray(np.asarray(pts.normal)[pick]), ist=jnp.asarray(np.asarray(pts.ist)[pick]))
    state = model.state.with_points(big, np.zeros(n, bool)) if n >= pts.capacity else None
    if state is None:
        raise SystemExit(f"--points {n}: expected more points than the model's capacity {pts.capacity}")
    t0 = time.perf_counter()
    scene = PointScene.build(big, model.run.render, model.scene.capacities)
    return model.replace(state=state, scene=scene, run_dir=None), time.perf_counter() - t0


def _edit_100k(model, n: int, size: int) -> dict:
    from ne_jax.edit.model import edit_model, model_edit_context
    from ne_jax.view import edits as E
    from ne_jax.view.frames import camera_from_viewer, render_frame

    big, build_s = _resampled(model, n)
    (wxyz, pos), = _orbit(big, 1)
    cam = camera_from_viewer(wxyz, pos, np.deg2rad(40), size, size)
    _, first = render_frame(big, cam)
    _, unedited = render_frame(big, cam)
    pts = big.state.point_state(big.scene.points)
    edit = E.ViewEdit.identity(pts)
    xyz = edit.xyz[edit.remaining]
    lo, hi = xyz.min(0), xyz.max(0)
    t0 = time.perf_counter()
    region = E.Region.make("box", (lo + hi) / 2 + (0, 0, 0.25 * (hi - lo)[2]), (hi - lo) * (1.1, 1.1, 0.5))
    sel = E.select_region(edit, region)
    t1 = time.perf_counter()
    turn = E.Transform.from_euler(E.selection_center(edit, sel), (0.05, 0, 0), (0, 0, 30))
    moved = E.move_points(edit, sel, turn)
    t2 = time.perf_counter()
    context = model_edit_context(big)  # made by the viewer's first edit and kept (Viewer._edit_context)
    edited, report = edit_model(big, moved.rows(), label="bench_view", context=context)
    t3 = time.perf_counter()
    _, render_first = render_frame(edited, cam)
    _, render_again = render_frame(edited, cam)
    # a second edit, as in the viewer after its warm-up compiled the edit path: another part moved
    t4 = time.perf_counter()
    region2 = E.Region.make("box", (lo + hi) / 2 - (0, 0, 0.25 * (hi - lo)[2]), (hi - lo) * (1.1, 1.1, 0.5))
    sel2 = E.select_region(moved, region2)
    moved2 = E.move_points(moved, sel2, E.Transform.from_euler(E.selection_center(moved, sel2), (0, 0.05, 0),
                                                               (0, 0, -20)))
    edited2, _ = edit_model(big, moved2.rows(), label="bench_view", context=context)
    t5 = time.perf_counter()
    _, render_warm = render_frame(edited2, cam)
    return {"points": n, "selected": int(sel.size), "tree_build_s": round(build_s, 2),
            "select_s": round(t1 - t0, 4), "move_s": round(t2 - t1, 4), "edit_model_s": round(t3 - t2, 2),
            "edit_report": {k: report[k] for k in ("moved", "deleted", "good", "filled", "seconds") if k in report},
            "render_edited_first_s": round(render_first, 2), "render_edited_s": round(render_again, 3),
            "render_unedited_first_s": round(first, 2), "render_unedited_s": round(unedited, 3), "size": size,
            "select_move_rerender_s": round((t3 - t0) + render_first, 2),
            "warm": {"selected": int(sel2.size), "edit_model_s": round(t5 - t4, 2), "render_s": round(render_warm, 3),
                     "select_move_rerender_s": round((t5 - t4) + render_warm, 2)}}


def measure(run: Path, size: int, frames: int, points: int) -> dict:
    """Frames per second (full and preview) and the 100,000-point edit, with this process's ``ne_jax``."""
    from ne_jax.train.model import load_trained

    model = load_trained(run)
    fps = [_fps(model, size, frames), _fps(model, max(1, size // 4), frames)]
    for row in fps:
        print(row, file=sys.stderr, flush=True)
    return {"fps": fps, "edit": _edit_100k(model, points, size)}


def _measure_in(path: str, run: Path, size: int, frames: int, points: int) -> dict:
    """:func:`measure` in a fresh process (nothing compiled yet) with the ``ne_jax`` of the checkout
    at ``path``, and that checkout's commit."""
    args = ["--run", str(Path(run).resolve()), "--size", str(size), "--frames", str(frames), "--points", str(points),
            "--json-only"]
    from ne_jax.provenance import git

    return {**json_from("bench_view", args, path), "commit": git("-C", path, "rev-parse", "HEAD")}


def _best(a, b, key: str = ""):
    """Field by field the better of two measurements: the lower time (``*_s``), the higher ``fps``."""
    if isinstance(a, dict):
        return {k: _best(v, b[k], k) for k, v in a.items()}
    if isinstance(a, list):
        return [_best(x, y) for x, y in zip(a, b)]
    if isinstance(a, (int, float)) and key.endswith("_s"):
        return min(a, b)
    return max(a, b) if isinstance(a, (int, float)) and key == "fps" else a


def _table(new: dict, ref: dict | None) -> list[str]:
    """Markdown rows of the frames and the edit, new against reference when there is one."""
    cols = "| | this code | reference | ratio |" if ref else "| | s |"
    rule = "|---|---:|---:|---:|" if ref else "|---|---:|"

    def row(label, *path, better="lower"):  # the field at ``path`` of each measurement
        a = functools.reduce(operator.getitem, path, new)
        if ref is None:
            return f"| {label} | {a} |"
        b = functools.reduce(operator.getitem, path, ref)
        return f"| {label} | {a} | {b} | {(b / a) if better == 'lower' else (a / b):.2f}x |"

    size, psize, e = new["fps"][0]["size"], new["fps"][1]["size"], new["edit"]
    return ["Frames of the tiny model (median over an orbit; the ratio is how many times faster this code is):", "",
            cols.replace(" s |", " frames/s |"), rule,
            row(f"{size} x {size} (full), frames/s", "fps", 0, "fps", better="higher"),
            row(f"{psize} x {psize} (preview), frames/s", "fps", 1, "fps", better="higher"),
            row(f"{size} x {size}, first frame (compiles), s", "fps", 0, "first_frame_s"), "",
            f"Edit of the cloud resampled to {e['points']} points ({e['selected']} selected by a box, moved and "
            f"turned 30 degrees; then a second edit, {e['warm']['selected']} points):", "", cols, rule,
            row("select (box region), s", "edit", "select_s"), row("move, s", "edit", "move_s"),
            row("edited model (normals, IST, carried tree), s", "edit", "edit_model_s"),
            row(f"first render of the edit at {size} x {size} (compiles), s", "edit", "render_edited_first_s"),
            row("**select + move + re-render** (the first edit: compiles the edit path), s", "edit",
                "select_move_rerender_s"),
            row("second edit: select, move, edited model, s", "edit", "warm", "edit_model_s"),
            row("its render, s", "edit", "warm", "render_s"),
            row("**select + move + re-render, compiled** (the viewer warms up at start), s", "edit", "warm",
                "select_move_rerender_s"),
            row("next render of the first edit, s", "edit", "render_edited_s"),
            row(f"render of the unedited {e['points']}-point model, s", "edit", "render_unedited_s"), ""]


def _wait(cond, what: str, timeout: float = 300.0) -> None:
    t0 = time.time()
    while time.time() - t0 < timeout:
        if cond():
            return
        time.sleep(0.2)
    raise TimeoutError(f"bench_view: timed out after {timeout:.0f} s waiting for {what}")


def screenshot(run: Path, out: Path, window: str, max_side: int) -> int:
    """``--screenshot``: the viewer on ``run`` in a headless Chromium window of ``window`` (``W,H``)
    pixels, its frames ``max_side`` pixels, points selected; the window saved to ``out``."""
    chromium, driver_bin = shutil.which("chromium") or shutil.which("chromium-browser"), shutil.which("chromedriver")
    if chromium is None or driver_bin is None:
        print("bench_view --screenshot: expected chromium and chromedriver on PATH (Debian: apt-get install "
              "chromium chromium-driver), found none", file=sys.stderr)
        return 2
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By

    from ne_jax.atomic import atomic_write_bytes
    from ne_jax.view.viewer import Viewer

    opts = webdriver.ChromeOptions()
    opts.binary_location = chromium
    for a in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", f"--window-size={window}",
              "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"):
        opts.add_argument(a)
    viewer = Viewer(run, port=0, max_side=max_side)
    driver = webdriver.Chrome(service=Service(driver_bin), options=opts)
    try:
        driver.get(viewer.url)
        _wait(lambda: viewer.frames >= 1 and "full" in viewer._gui_time.content, "a full-resolution frame")
        driver.find_element(By.XPATH, "//button[normalize-space()='Select in region']").click()
        _wait(lambda: viewer.selection.size > 0, "a selection")
        time.sleep(3.0)  # let the page draw the selection and the last frame
        png = driver.get_screenshot_as_png()
    finally:
        driver.quit()
        viewer.stop()
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out, png)
    print(f"wrote {out} ({len(png)} bytes)")
    return 0


def main(argv=None) -> int | None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", default=None, help="a tiny model's run directory (default: train one in --work)")
    ap.add_argument("--work", default="outputs/bench_view", help="where a model is trained when --run is not given")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--points", type=int, default=100_000)
    ap.add_argument("--reference-path", default=None,
                    help="a checkout of older code, timed first in a subprocess (git worktree add REF COMMIT)")
    ap.add_argument("--rounds", type=int, default=2,
                    help="with --reference-path: measurements of each version (alternating; the best of each kept)")
    ap.add_argument("--json-only", action="store_true", help=argparse.SUPPRESS)  # the reference's subprocess
    ap.add_argument("--screenshot", type=Path, metavar="PNG", help="save a screenshot of the viewer instead")
    ap.add_argument("--window", default="1200,760", help="with --screenshot: the browser window's WIDTH,HEIGHT")
    ap.add_argument("--max-side", type=int, default=256, help="with --screenshot: the viewer's full frame size")
    args = ap.parse_args(argv)
    run = Path(args.run) if args.run else _tiny_run(Path(args.work))
    if args.screenshot:
        return screenshot(run, args.screenshot, args.window, args.max_side)
    if args.json_only:
        print(json.dumps(measure(run, args.size, args.frames, args.points)))
        return

    import jax

    from ne_jax import provenance
    from ne_jax.config_json import config_key
    from ne_jax.train.model import load_trained

    model = load_trained(run)
    t_start = time.perf_counter()
    load = os.getloadavg()[0]
    ref = None
    if args.reference_path:
        versions = {"reference": args.reference_path, "new": str(ROOT)}
        rounds = against_reference(lambda name: _measure_in(versions[name], run, args.size, args.frames, args.points),
                                   args.rounds)
        ref, new = (functools.reduce(_best, rounds[name]) for name in ("reference", "new"))
    else:
        new = measure(run, args.size, args.frames, args.points)
    print(new, flush=True)
    load_after = os.getloadavg()[0]
    command = "python -m experiments.bench_view" + (" --run RUN" if args.run else "") + \
        f" --size {args.size} --frames {args.frames} --points {args.points}" + \
        (f" --reference-path REF --rounds {args.rounds}" if ref else "")
    modified = provenance.modified()
    report = {"what": "ne-jax view: frames/s of a tiny model and a select+move+re-render on a resampled cloud",
              "commit": provenance.commit(), "worktree_modified": modified, "command": command,
              "model": {"run_config": model.run.name, "config_key": config_key(model.run),
                        "points": int(np.asarray(model.scene.points.alive).sum())},
              **new, "reference": ref, "seconds": round(time.perf_counter() - t_start, 1),
              "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(),
                          "device": jax.devices()[0].platform, "jax": jax.__version__,
                          "load_before": round(load, 2), "load_after": round(load_after, 2)}}
    against = (f" against the reference {ref['commit'][:12]} in the same run ({args.rounds} alternating rounds of "
               "each, in fresh processes; the best of each)") if ref else ""
    lines = [f"`ne-jax view` on {os.cpu_count()} CPU cores ({jax.devices()[0].platform}, JAX {jax.__version__}; "
             f"1-minute load average {load:.1f} at the start, {load_after:.1f} at the end: above 0 other jobs "
             f"shared the cores). Model `{model.run.name}` (config key {report['model']['config_key']}, "
             f"{report['model']['points']} points). Commit {report['commit'][:12]}"
             f"{' (work tree modified)' if modified else ''}{against}; re-run: `{command}`.", "", *_table(new, ref)]
    write_results(RESULTS, "bench_view", report, "\n".join(lines))


if __name__ == "__main__":
    entry(main)
