"""The ``ne-jax`` command line: thin wrappers over library functions.

Sub-commands:
  demo            the main job on the built-in default scene: make the tiny procedural benchmark,
                  train one scene, evaluate its test views and render an orbit video
  make-benchmark  generate the procedural editing benchmark for a preset
  make-photos     photos of a built-in scene with known cameras, to try process-images on
  process-images  structure from motion: a folder of photos to a COLMAP scene folder
  train           train a model of a scene folder (NeRF Synthetic, nerfstudio, COLMAP, NSVF, LLFF)
  eval            PSNR, SSIM and LPIPS of a trained run on a split (per view and mean), with the images
  render          render a trained run's split views to PNGs, or a camera orbit to MP4/GIF
  export          write a trained run's point cloud (normals, confidences, colours) to PLY
  edit            move/delete a trained run's points (a benchmark edit by name, or a .npy/.ply file)
                  into an edited model that renders zero-shot (evaluated on the edit's ground truth)
  finetune        fine-tune an edited model on the edited scene's training views
  morph           morph one trained run into another: both models rendered through intermediate
                  clouds, blended by the morph ratio, to PNG frames, a video and smoothness figures
  view            look at a trained run in the browser and edit it there (a viser web page; the `view` extra)
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import sys
import time
from pathlib import Path

SCENE_SPLITS = ("train", "val", "test")


def _cmd_make_benchmark(args) -> int:
    from ne_jax.benchmark.generate import generate_benchmark
    from ne_jax.viz import contact_sheet

    report = generate_benchmark(args.out, args.preset, args.scenes, args.seed)
    scenes = "" if args.scenes is None else f", scenes {' '.join(args.scenes)}"
    sheet = contact_sheet(args.out, Path(args.out) / "contact_sheet.png", title=(
        f"ne_jax procedural benchmark, preset {args.preset!r}{scenes} (test view at 45 degrees)"))
    print(f"benchmark[{args.preset}]: {len(report['scenes'])} scenes in {report['seconds']:.1f} s -> {args.out}")
    print(f"contact sheet: {sheet}")
    return 0


def _cmd_make_photos(args) -> int:
    from ne_jax.benchmark.photos import write_photos

    report = write_photos(Path(args.out), args.resolution, args.spp)
    print(f"make-photos: {report['photos']} photos of the blocks scene in {report['seconds']:.0f} s -> {args.out} "
          f"(true cameras in cameras.json; next: `ne-jax process-images {args.out} --out SCENE`)")
    return 0


def _cmd_process_images(args) -> int:
    from ne_jax.data.sfm import process_images

    report = process_images(args.photos, args.out, matcher=args.matcher, camera_model=args.camera_model,
                            single_camera=not args.camera_per_image, max_image_size=args.max_image_size,
                            num_threads=args.threads, overwrite=args.overwrite, verbose=args.verbose)
    print(f"process-images: {report['registered']} of {report['images']} photos registered, {report['points']} "
          f"points -> {args.out} (a COLMAP scene: `ne-jax train {args.out} --out RUN`)")
    return 0


def _run_config(args):
    """The preset with the command line's changes applied (``--set`` last)."""
    from ne_jax.config_json import config_set
    from ne_jax.train.run import get_run_preset

    run = get_run_preset(args.preset)
    sets = getattr(args, "set", [])
    if args.epochs is not None or args.steps_per_epoch is not None:
        run = run.with_schedule(args.epochs, args.steps_per_epoch)
    if args.batch_size is not None:
        run = run.replace(sampler=run.sampler.replace(batch_size=args.batch_size))
    if args.downscale != 1:
        run = run.replace(downscale=args.downscale)
    if args.init != run.init.source or args.ply is not None:
        if args.ply is not None and args.init != "ply":
            raise ValueError(f"--ply: given with --init {args.init!r}; use --init ply")
        ply = args.ply
        if args.init == "ply" and ply is None:  # also accepted as --set init.ply_path=FILE, read as --set reads it
            ply = config_set(run, *(s for s in sets if s.startswith("init.ply_path="))).init.ply_path
            if not ply:
                raise ValueError("--init ply: expected the initial cloud as --ply FILE, found none")
        run = run.replace(init=dataclasses.replace(run.init, source=args.init, ply_path=ply))
    return config_set(run.replace(background=args.background, seed=args.seed), *sets)


def _evaluate(model, scene_dir: Path, split_name: str, out: Path, progress=True, views: int | None = None) -> dict:
    """Render and score a split of ``model``; write ``out/metrics.json`` and ``out/images/*.png``.
    ``views``: score only this many views, evenly spaced over the split, and report the time a view
    took and the projected time of the whole split."""
    from ne_jax.atomic import atomic_write_json
    from ne_jax.data.nerf_synthetic import composite
    from ne_jax.data.scene import check_recorded_split, load_split
    from ne_jax.eval import evaluate_model, save_images
    from ne_jax.eval.regions import error_map_picture, split_regions, view_shares

    split = load_split(scene_dir, split_name, model.run.downscale)
    if model.run_dir is not None and model.scene_dir is not None and \
            Path(scene_dir).resolve() == Path(model.scene_dir).resolve():  # the scene it was trained on
        check_recorded_split(model.run_dir, split)
    whole = split.num_views
    chosen = list(range(whole))
    if views is not None:
        if views < 1:
            raise ValueError(f"--views: expected at least 1 view, found {views}")
        chosen = sorted({round(i * (whole - 1) / max(views - 1, 1)) for i in range(min(views, whole))})
        split = split.take(chosen)
    t0 = time.perf_counter()
    report, images, depths = evaluate_model(model, split, progress=progress, with_depth=True)
    seconds = time.perf_counter() - t0
    report["seconds"] = round(seconds, 2)
    if split.num_views < whole:  # an upper bound: the first view compiles
        per_view = seconds / split.num_views
        report["subset"] = {"views": split.num_views, "of": whole, "seconds_per_view": round(per_view, 2),
                            "projected_split_seconds": round(per_view * whole, 1)}
    report["regions"], labels = split_regions(split, images, model.background, depths=depths)
    for view, share in zip(report["views"], view_shares(labels, "hole")):
        view["hole_pixels"] = round(float(share), 6)
    truth = composite(split.images, report["background"])
    names = [f"{i:03d}_{Path(p).name}" for i, p in zip(chosen, split.file_paths)]
    save_images(images, out / "images", names)
    save_images([error_map_picture(t, p, lab) for t, p, lab in zip(truth, images, labels)], out / "error_maps", names)
    atomic_write_json(out / "metrics.json", report)
    return report


def _print_eval(report: dict, out: Path) -> None:
    lp = report.get("lpips")
    lpips = "" if lp is None else f", LPIPS {lp:.4f} ({report.get('lpips_net')})"
    print(f"{report['split']}: PSNR {report['psnr']:.2f} dB, SSIM {report['ssim']:.4f}{lpips} "
          f"(mean of {report['num_views']} views, background {report['background']}) -> {out}")
    if "subset" in report:
        sub = report["subset"]
        print(f"  {sub['views']} of {sub['of']} views scored, {sub['seconds_per_view']} s a view (the first one "
              f"compiling): the whole split would take at most {sub['projected_split_seconds'] / 60:.1f} min")
    if "regions" in report:  # the largest shares of the squared error first
        parts = sorted(report["regions"].items(), key=lambda kv: -kv[1]["error"])
        print("  error by region: " + ", ".join(f"{k} {100 * v['error']:.0f}% ({100 * v['pixels']:.0f}% of pixels)"
                                                 for k, v in parts if v["error"] >= 0.005)
              + f"; pictures in {out / 'error_maps'}")
        worst = max(report["views"], key=lambda v: v.get("hole_pixels", 0.0))
        if worst.get("hole_pixels"):
            print(f"  holes: {100 * worst['hole_pixels']:.2f}% of the pixels of {worst['view']}, the most of any view")


def _declared(run, scene_dir: Path, spec: str):
    """``run`` with the effects ``spec`` declares (:mod:`ne_jax.train.effects`), and the record."""
    from ne_jax.data.scene import detect_format
    from ne_jax.train.effects import declare_effects, scene_effects

    if spec.strip() == "scene" and scene_effects(scene_dir) is None and detect_format(scene_dir) != "nerf_synthetic":
        spec = "auto"  # a capture declares nothing: decide from its images (a background sphere where opaque)
    split = cloud = None
    if spec.strip() == "auto":  # decided from the training views and the initial cloud
        from ne_jax.data.scene import load_split
        from ne_jax.pointcloud.init import CarvingError, Views
        from ne_jax.train.loop import initial_cloud

        split = load_split(scene_dir, "train", run.downscale)
        with contextlib.suppress(CarvingError):  # images without masks: no cloud, specular stays on
            cloud = initial_cloud(run.init, scene_dir, Views.from_split(split)).xyz
    render, record = declare_effects(run.render, spec, scene_dir, split, cloud)
    return run.replace(render=render), record


def _cmd_train(args) -> int:
    from ne_jax.data.scene import split_names
    from ne_jax.train.loop import train

    scene_dir, out = Path(args.scene), Path(args.out)
    run, effects = _declared(_run_config(args), scene_dir, args.effects)
    print("effects: " + ", ".join(f"{k}={v}" for k, v in effects["effects"].items()) + f" ({effects['source']})")
    t0 = time.perf_counter()
    result = train(run, scene_dir, out, resume=not args.restart, progress=not args.quiet, notes={"effects": effects})
    print(f"trained {run.total_steps} steps in {time.perf_counter() - t0:.1f} s -> {out}")
    if not args.no_eval and "test" in split_names(scene_dir):
        report = _evaluate(result, scene_dir, "test", out / "eval_test", progress=not args.quiet)
        _print_eval(report, out / "eval_test")
    return 0


def _load(args):
    from ne_jax.train.model import load_trained

    model = load_trained(args.run)
    scene_dir = Path(args.scene) if getattr(args, "scene", None) else model.scene_dir
    return model, scene_dir


def _source_scene(run_dir) -> Path | None:
    """The scene an edited run's source model was trained on (its cameras serve a render of an edit
    that has no ground truth), from ``metrics.json``'s ``source``; ``None`` when not recorded."""
    import json

    file = Path(run_dir) / "metrics.json"
    found = json.loads(file.read_text(encoding="utf-8")).get("source", {}) if file.is_file() else {}
    return Path(found["scene_dir"]) if isinstance(found, dict) and found.get("scene_dir") else None


def _need_scene(scene_dir, run) -> Path:
    if scene_dir is None:
        raise FileNotFoundError(f"{run}: no scene folder recorded in metrics.json; pass --scene DIR")
    return Path(scene_dir)


def _cmd_eval(args) -> int:
    model, scene_dir = _load(args)
    scene_dir = _need_scene(scene_dir, args.run)
    if args.background:
        model = model.replace(run=model.run.replace(background=args.background))
    out = Path(args.out) if args.out else Path(args.run) / f"eval_{args.split}"
    report = _evaluate(model, scene_dir, args.split, out, views=args.views)
    _print_eval(report, out)
    return 0


def _cmd_render(args) -> int:
    from ne_jax.data.scene import load_split
    from ne_jax.eval import orbit_cameras_for, render_views, save_images, write_video

    model, scene_dir = _load(args)
    run = model.run
    background = args.background or run.background
    split = load_split(_need_scene(scene_dir or _source_scene(args.run), args.run), args.split, run.downscale)
    if args.orbit:
        cameras = orbit_cameras_for(split, args.orbit, args.elevation)
        frames = render_views(run.render, model.state.params, model.scene, cameras, background, run.sampler.near,
                              run.sampler.far)
        path = write_video(frames, Path(args.out) if args.out else Path(args.run) / "orbit.mp4", fps=args.fps)
        print(f"orbit: {len(cameras)} frames -> {path}")
    else:
        cameras = [split.camera(i) for i in range(split.num_views)]
        images = render_views(run.render, model.state.params, model.scene, cameras, background, run.sampler.near,
                              run.sampler.far)
        out = Path(args.out) if args.out else Path(args.run) / f"render_{args.split}"
        names = [f"{i:03d}_{Path(p).name}" for i, p in enumerate(split.file_paths)]
        save_images(images, out, names)
        print(f"{args.split}: {len(names)} images -> {out}")
    return 0


def _cmd_export(args) -> int:
    from ne_jax.pointcloud.export import export_ply

    model, _ = _load(args)
    n = export_ply(args.out, model.run.render.shading, model.state.params, model.scene.points, model.frame)
    frame = "" if model.frame.is_identity else ", in the capture's coordinates"
    print(f"exported {n} points (xyz, normals, confidence, colour, index{frame}) -> {args.out}")
    return 0


def _cmd_edit(args) -> int:
    from ne_jax.benchmark.edits import resolve_edit
    from ne_jax.edit.model import edit_model

    model, scene_dir = _load(args)
    model = dataclasses.replace(model, scene_dir=scene_dir)
    edit, label, truth = resolve_edit(scene_dir, args.edit)
    out = Path(args.out)
    edited, report = edit_model(model, edit, out, ist=not args.no_ist, label=label,
                                scene_dir=args.edited_scene if args.edited_scene is not None else truth)
    print(f"edit {report['edit']!r}: {report['moved']} points moved, {report['deleted']} deleted, "
          f"{report['alive']} alive; "
          f"IST from {report['good']} frames, {report['filled']} filled from neighbours, {report['identity']} identity "
          f"({report['seconds']:.1f} s) -> {out}")
    if edited.scene_dir is not None and not args.no_eval:
        ev = _evaluate(edited, edited.scene_dir, "test", out / "eval_test")
        print("zero-shot ", end="")
        _print_eval(ev, out / "eval_test")
    elif edited.scene_dir is None:
        print("no ground truth of the edited scene (pass --edited-scene DIR to evaluate and fine-tune)")
    return 0


def _cmd_finetune(args) -> int:
    from ne_jax.edit.model import finetune

    model, scene_dir = _load(args)
    scene_dir = _need_scene(scene_dir, args.run)
    out = Path(args.out)
    t0 = time.perf_counter()
    result = finetune(model, out, args.epochs, scene_dir=scene_dir, steps_per_epoch=args.steps_per_epoch,
                      train_ist=args.train_ist, rounds=args.rounds, resume=not args.restart,
                      progress=not args.quiet)
    print(f"fine-tuned {result.run.total_steps} steps in {time.perf_counter() - t0:.1f} s -> {out}")
    if not args.no_eval:
        ev = _evaluate(result, scene_dir, "test", out / "eval_test", progress=not args.quiet)
        _print_eval(ev, out / "eval_test")
    return 0


def _cmd_morph(args) -> int:
    from ne_jax.data.scene import load_split
    from ne_jax.eval import orbit_cameras_for
    from ne_jax.morph import MorphSettings, morph_models
    from ne_jax.train.model import load_trained

    a, b = load_trained(args.run_a), load_trained(args.run_b)
    scene_dir = _need_scene(Path(args.scene) if args.scene else a.scene_dir, args.run_a)
    split = load_split(scene_dir, args.split, a.run.downscale)
    if not 0 <= args.view < split.num_views:
        raise ValueError(f"--view: expected a view of the {args.split} split in [0, {split.num_views}), "
                         f"found {args.view}")
    if args.scale < 1:
        raise ValueError(f"--scale: expected a downscale factor >= 1, found {args.scale}")
    camera = split.camera(args.view).scaled(args.scale) if args.scale > 1 else split.camera(args.view)
    steps = args.steps if not args.intermediate else len(args.intermediate) + 2
    if args.orbit:
        camera = orbit_cameras_for(camera, steps, args.elevation)
    settings = MorphSettings(steps=args.steps, seed=args.seed, video=f"morph.{args.format}", fps=args.fps)
    report, _ = morph_models(a, b, args.out, camera, settings, args.intermediate, args.background,
                             progress=not args.quiet, labels=(str(args.run_a), str(args.run_b)))
    sm = report["smoothness"]
    print(f"morph: {report['frames']} frames of {report['points']['matched']} matched points in "
          f"{report['seconds']:.1f} s; frame-to-frame change mean {sm['mean']:.4f}, max {sm['max']:.4f}, "
          f"path ratio {sm['path_ratio']:.2f} -> {args.out} (frames/, morph.{args.format}, strip.png, morph.json)")
    return 0


def _cmd_view(args) -> int:
    try:
        from ne_jax.view.viewer import Viewer
    except ImportError as e:
        raise ValueError(f"the viewer needs the 'view' extra (viser): pip install -e '.[view]' ({e})") from None

    viewer = Viewer(args.run, port=args.port, host=args.host, max_side=args.max_side)
    print(f"ne-jax view: serving {args.run} at {viewer.url} (open it in a browser; Ctrl+C stops)")
    if args.host in ("127.0.0.1", "localhost", "::1"):
        print(f"on a remote machine, forward the port first: ssh -N -L {viewer.port}:localhost:{viewer.port} "
              f"USER@MACHINE, then open http://localhost:{viewer.port} on your own")
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        print("ne-jax view: stopping (Ctrl+C)")
    finally:
        viewer.stop()
    return 0


def _cmd_demo(args) -> int:
    from ne_jax.benchmark.generate import generate_benchmark
    from ne_jax.benchmark.scenes import get_scene
    from ne_jax.data.nerf_synthetic import load_split
    from ne_jax.eval import orbit_cameras_for, render_views, write_video
    from ne_jax.train.loop import train
    from ne_jax.train.run import get_run_preset
    from ne_jax.viz import contact_sheet

    out = Path(args.out)
    t0 = time.perf_counter()
    print(f"[1/4] generating the procedural benchmark (preset {args.preset!r}) in {out / 'benchmark'}")
    report = generate_benchmark(out / "benchmark", args.preset, None, args.seed)
    sheet = contact_sheet(out / "benchmark", out / "contact_sheet.png",
                          title=f"ne_jax procedural benchmark, preset {args.preset!r} (test view at 45 degrees)")
    edits = len(get_scene(next(iter(report["scenes"]))).edits)
    print(f"      {len(report['scenes'])} scenes x (original + {edits} edits) in {report['seconds']:.1f} s")
    scene_dir = out / "benchmark" / args.scene
    run, effects = _declared(get_run_preset("tiny").replace(seed=args.seed), scene_dir, "scene")  # as `train` does
    print(f"[2/4] training scene {args.scene!r} (preset 'tiny': {run.epochs} epochs x {run.steps_per_epoch} steps, "
          f"initial cloud by visual-hull carving)")
    print("      effects: " + ", ".join(f"{k}={v}" for k, v in effects["effects"].items()) + f" ({effects['source']})")
    result = train(run, scene_dir, out / "run", resume=False, notes={"effects": effects})
    print("[3/4] evaluating the test views")
    ev = _evaluate(result, scene_dir, "test", out / "run" / "eval_test")
    _print_eval(ev, out / "run" / "eval_test")
    print("[4/4] rendering an orbit")
    cameras = orbit_cameras_for(load_split(scene_dir, "test"), args.orbit_frames)
    frames = render_views(run.render, result.state.params, result.scene, cameras, run.background, run.sampler.near,
                          run.sampler.far)
    video = write_video(frames, out / "run" / "orbit.gif", fps=12)
    print(f"done in {time.perf_counter() - t0:.1f} s")
    print(f"  scenes (NeRF Synthetic layout): {out / 'benchmark'}")
    print(f"  contact sheet:                  {sheet}")
    print(f"  training run (config, metrics, checkpoints): {out / 'run'}")
    print(f"  test-view renders and metrics:  {out / 'run' / 'eval_test'}")
    print(f"  orbit video:                    {video}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ne-jax", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--host-devices", type=int, default=None, metavar="N",
                        help="CPU only: split rays over N host devices (default: NE_JAX_HOST_DEVICES, else one per "
                             "usable core; 1: one device; a count given to JAX itself in XLA_FLAGS wins)")
    multi = parser.add_argument_group("multi-host (jax.distributed; one process per host, the same flags on each)")
    multi.add_argument("--coordinator", default=None, metavar="HOST:PORT", help="address of process 0")
    multi.add_argument("--num-processes", type=int, default=1, help="number of processes (hosts)")
    multi.add_argument("--process-id", type=int, default=0, help="this process's index, 0 .. N-1")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="run the main job on the built-in default scene")
    demo.add_argument("--out", default="outputs/demo", help="output folder (default: outputs/demo)")
    demo.add_argument("--preset", default="tiny", choices=["tiny", "default"], help="benchmark preset (default: tiny)")
    demo.add_argument("--scene", default="blocks", choices=["stool", "cup", "blocks", "glossy"],
                      help="the scene to train (default: blocks)")
    demo.add_argument("--orbit-frames", type=int, default=36, help="frames of the orbit video (default: 36)")
    demo.add_argument("--seed", type=int, default=0)
    demo.set_defaults(func=_cmd_demo)

    mb = sub.add_parser("make-benchmark", help="generate the procedural editing benchmark")
    mb.add_argument("--preset", default="tiny",
                    choices=["tiny", "default", "tiny_pt", "default_pt", "tiny_capture", "default_capture"])
    mb.add_argument("--out", required=True, help="output folder")
    mb.add_argument("--scenes", nargs="+", default=None,
                    help="scenes, or sets of them: 'heldout' (vase bowl lamp pattern, never used to tune a setting) "
                         "or 'tuning' (default: the four tuning scenes, stool cup blocks glossy)")
    mb.add_argument("--seed", type=int, default=0)
    mb.set_defaults(func=_cmd_make_benchmark)

    ph = sub.add_parser("make-photos", help="photos of a built-in scene with known cameras, to try process-images on")
    ph.add_argument("--out", required=True, help="folder to write the photos (and cameras.json) to")
    ph.add_argument("--resolution", type=int, default=320, help="pixels a side (default 320)")
    ph.add_argument("--spp", type=int, default=16, help="path-tracer samples per pixel (default 16)")
    ph.set_defaults(func=_cmd_make_photos)

    pi = sub.add_parser("process-images", help="photos to a COLMAP scene folder (structure from motion with pycolmap)")
    pi.add_argument("photos", help="a folder of .png/.jpg photos of one scene")
    pi.add_argument("--out", required=True, help="the scene folder to write (images/, sparse/0/, sfm.json)")
    pi.add_argument("--matcher", default="exhaustive", choices=["exhaustive", "sequential"],
                    help="exhaustive (every pair; default) or sequential (neighbours in name order: video frames)")
    pi.add_argument("--camera-model", default="SIMPLE_RADIAL",
                    help="COLMAP camera model (default SIMPLE_RADIAL; PINHOLE for undistorted images)")
    pi.add_argument("--camera-per-image", action="store_true",
                    help="intrinsics per image size and camera (default: one camera shared by every photo)")
    pi.add_argument("--max-image-size", type=int, default=3200, help="longest side features are found at")
    pi.add_argument("--threads", type=int, default=1,
                    help="COLMAP's threads (default 1: the same model every run; more is faster, not repeatable)")
    pi.add_argument("--overwrite", action="store_true", help="replace an existing --out folder once done")
    pi.add_argument("--verbose", action="store_true", help="COLMAP's own log on stderr")
    pi.set_defaults(func=_cmd_process_images)

    tr = sub.add_parser("train", help="train a model of a scene folder")
    tr.add_argument("scene", help="scene folder: NeRF Synthetic, nerfstudio (transforms.json), COLMAP (sparse/0 + "
                                  "images/), NSVF / Tanks and Temples, or LLFF (poses_bounds.npy); docs/captures.md")
    tr.add_argument("--out", required=True, help="run directory (resumed from its latest checkpoint if it has one)")
    tr.add_argument("--preset", default="tiny", choices=["tiny", "default", "paper"])
    tr.add_argument("--epochs", type=int, default=None, help="override the preset's epochs")
    tr.add_argument("--steps-per-epoch", type=int, default=None, help="override the preset's steps per epoch")
    tr.add_argument("--batch-size", type=int, default=None, help="override the preset's rays per batch")
    tr.add_argument("--downscale", type=int, default=1, metavar="N",
                    help="read the images downscaled by the integer N (every command on the run follows it)")
    tr.add_argument("--init", default="auto", choices=["auto", "carving", "sfm", "ply", "ground_truth"],
                    help="initial cloud: auto (default: the capture's SfM points where it has them, else carving "
                         "from the alpha masks), visual-hull carving, the SfM points, a PLY (--ply), or the "
                         "benchmark's ground-truth samples (labelled in the results)")
    tr.add_argument("--ply", default=None, help="the initial cloud for --init ply")
    tr.add_argument("--background", default="white", choices=["white", "black"])
    tr.add_argument("--seed", type=int, default=0)
    tr.add_argument("--effects", default="scene", metavar="SPEC",
                    help="effects the model computes: scene (what the scene folder's scene.json declares, else the "
                         "preset's for a NeRF Synthetic folder and auto for a capture; default), auto (decided "
                         "from the training views), all, or pairs such as "
                         "specular=off,background_model=sphere (specular=on|off, background_model=constant|sphere)")
    tr.add_argument("--set", action="append", default=[], metavar="FIELD.PATH=VALUE",
                    help="change one field of the preset's RunConfig (repeatable), e.g. "
                         "render.kdtree.density_falloff=1.0 (the density gate) or train.confidence_lr=10")
    tr.add_argument("--restart", action="store_true",
                    help="start afresh: remove the checkpoints and metrics of an earlier run in --out")
    tr.add_argument("--no-eval", action="store_true", help="skip evaluating the test views after training")
    tr.add_argument("--quiet", action="store_true", help="no progress bars")
    tr.set_defaults(func=_cmd_train)

    def run_parser(name, help_):
        p = sub.add_parser(name, help=help_)
        p.add_argument("run", help="a training run directory (from `ne-jax train`)")
        p.add_argument("--scene", default=None, help="scene folder (default: the one the run was trained on)")
        return p

    ev = run_parser("eval", "PSNR/SSIM/LPIPS of a trained run on a split")
    ev.add_argument("--split", default="test", choices=SCENE_SPLITS)
    ev.add_argument("--background", default=None, choices=["white", "black"], help="default: the run's")
    ev.add_argument("--out", default=None, help="output folder (default: RUN/eval_<split>)")
    ev.add_argument("--views", type=int, default=None, metavar="N",
                    help="score N views evenly spaced over the split (and project the whole split's time)")
    ev.set_defaults(func=_cmd_eval)

    rd = run_parser("render", "render a trained run's views or an orbit video")
    rd.add_argument("--split", default="test", choices=SCENE_SPLITS,
                    help="views to render (and the orbit's intrinsics)")
    rd.add_argument("--orbit", type=int, default=0, metavar="FRAMES", help="render a camera orbit of FRAMES frames")
    rd.add_argument("--elevation", type=float, default=25.0, help="orbit elevation in degrees")
    rd.add_argument("--fps", type=int, default=24)
    rd.add_argument("--background", default=None, choices=["white", "black"], help="default: the run's")
    rd.add_argument("--out", default=None, help="folder for views; .mp4/.gif file for an orbit (default: RUN/...)")
    rd.set_defaults(func=_cmd_render)

    ex = run_parser("export", "write a trained run's point cloud to PLY")
    ex.add_argument("--out", required=True, help="the .ply file to write")
    ex.set_defaults(func=_cmd_export)

    ed = run_parser("edit", "edit a trained run's point cloud into an edited model")
    ed.add_argument("--edit", required=True, metavar="NAME|FILE",
                    help="a benchmark edit of the run's scene by name (e.g. bend), or an edit file: .npy with one "
                         "row per alive point (NaN rows delete) or .ply with an index property (`ne-jax export`)")
    ed.add_argument("--out", required=True, help="the edited model's run directory")
    ed.add_argument("--no-ist", action="store_true", help="render without the IST (the 'without IST' variant)")
    ed.add_argument("--edited-scene", default=None,
                    help="ground truth of the edited scene (default: the benchmark's, for a named edit)")
    ed.add_argument("--no-eval", action="store_true", help="skip the zero-shot evaluation")
    ed.set_defaults(func=_cmd_edit)

    ft = run_parser("finetune", "fine-tune an edited model on the edited scene")
    ft.add_argument("--out", required=True, help="run directory of the fine-tuning")
    ft.add_argument("--epochs", type=int, default=1)
    ft.add_argument("--steps-per-epoch", type=int, default=None, help="default: the model's preset")
    ft.add_argument("--train-ist", action="store_true", help="make the ISTs trainable (kept orthogonal by a loss)")
    ft.add_argument("--rounds", action="store_true",
                    help="point-cloud rounds after epochs 1..min(5, epochs-1) (paper: warm-up, then rounds)")
    ft.add_argument("--restart", action="store_true",
                    help="start afresh: remove the checkpoints and metrics of an earlier run in --out")
    ft.add_argument("--no-eval", action="store_true", help="skip evaluating the test views")
    ft.add_argument("--quiet", action="store_true", help="no progress bars")
    ft.set_defaults(func=_cmd_finetune)

    mo = sub.add_parser("morph", help="morph one trained run into another (blended rendering along a path)")
    mo.add_argument("run_a", help="the run the morph starts from")
    mo.add_argument("run_b", help="the run the morph ends at")
    mo.add_argument("--out", required=True, help="output folder (frames/, morph.mp4, strip.png, morph.json)")
    mo.add_argument("--steps", type=int, default=24, help="frames, both ends included (default: 24)")
    mo.add_argument("--intermediate", nargs="+", default=None, metavar="CLOUD",
                    help="intermediate clouds from another generator (.ply/.npy, ordered from A to B, unindexed, "
                         "each with the matched number of points); default: straight lines along the matching")
    mo.add_argument("--scene", default=None, help="scene folder for the camera (default: run A's)")
    mo.add_argument("--split", default="test", choices=SCENE_SPLITS)
    mo.add_argument("--view", type=int, default=0, help="the split's view to render from (default: 0)")
    mo.add_argument("--scale", type=int, default=1, help="downscale the camera by this factor (default: 1)")
    mo.add_argument("--orbit", action="store_true", help="circle the camera once over the morph")
    mo.add_argument("--elevation", type=float, default=25.0, help="orbit elevation in degrees")
    mo.add_argument("--format", default="mp4", choices=["mp4", "gif"])
    mo.add_argument("--fps", type=float, default=12.0)
    mo.add_argument("--background", default=None, choices=["white", "black"], help="default: run A's")
    mo.add_argument("--seed", type=int, default=0, help="seed of the subsample when the clouds differ in size")
    mo.add_argument("--quiet", action="store_true", help="no progress bar")
    mo.set_defaults(func=_cmd_morph)

    vw = sub.add_parser("view", help="look at a trained run and edit it in the browser (needs the 'view' extra)")
    vw.add_argument("run", help="a run directory (from `ne-jax train` or `ne-jax edit`)")
    vw.add_argument("--port", type=int, default=8080, help="port to serve on (default: 8080; 0: any free port)")
    vw.add_argument("--host", default="127.0.0.1",
                    help="address to listen on (default: 127.0.0.1, this machine only; 0.0.0.0: every interface)")
    vw.add_argument("--max-side", type=int, default=128, help="longest side of a full-resolution frame (default: 128)")
    vw.set_defaults(func=_cmd_view)
    return parser


def main(argv=None) -> int:
    """Run ``ne-jax`` with ``argv`` (default: the command line); returns the exit status.

    It sets its process up first (:func:`ne_jax.setup`): one host device per usable core, or
    ``--host-devices N``; and, run as the program (``ne-jax ...``, ``python -m ne_jax.cli ...``:
    ``argv`` is ``None``), huge pages for XLA's scratch memory by starting itself again with
    ``GLIBC_TUNABLES=glibc.malloc.hugetlb=1`` where it lacks it. Called from Python with ``argv``,
    it never starts the process again."""
    args = build_parser().parse_args(argv)
    try:
        if args.host_devices is not None and args.host_devices < 1:
            raise ValueError(f"--host-devices: expected an integer >= 1 (1 opts out), found {args.host_devices}")
        from ne_jax import setup

        setup(args.host_devices, huge_pages=argv is None)  # before anything touches JAX's backends
        if args.coordinator is not None or args.num_processes != 1:
            from ne_jax.devices import initialize_distributed

            initialize_distributed(args.coordinator or "", args.num_processes, args.process_id)
        return args.func(args)
    except (KeyError, ValueError, FileNotFoundError) as e:  # user errors: one clear line, no traceback
        msg = e.args[0] if isinstance(e, KeyError) and e.args else e
        print(f"ne-jax {args.command}: error: {msg}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
