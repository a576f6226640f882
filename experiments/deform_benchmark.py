"""The deformation benchmark (paper Table 1 layout): every scene x every edit x every variant,
zero-shot and after fine-tuning, PSNR and SSIM on the edited scene's test views.

    python -m experiments.deform_benchmark --preset tiny --runs runs/deform          # main variants
    python -m experiments.deform_benchmark --preset tiny --runs runs/deform --variants all
    python -m experiments.deform_benchmark --scenes glossy --edits bend --no-finetune  # a quick look
    python -m experiments.deform_benchmark --preset tiny --root BENCH/tiny_pt --runs runs/deform_pt  # path-traced
    python -m experiments.deform_benchmark --preset tiny --runs runs/deform1 --set render.pixel_samples=1  # a field
    python -m experiments.deform_benchmark --by-kind experiments/results/deform_benchmark_tiny.json  # by kind

The models are cached in ``--runs`` (docs/editing.md), every record in ``<runs>/<scene>/records/<config
key>/<edit>/`` (a re-run measures only what is missing); ``experiments/results/deform_benchmark_<preset>[_pt]``
is written after every (scene, edit). ``--by-kind`` writes ``<stem>_by_kind.md`` beside a results file.
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import shlex
import time
import zlib
from pathlib import Path

import numpy as np

from experiments import common
from experiments.common import RESULTS, benchmark_suffix, cached_run, entry, machine
from ne_jax.atomic import atomic_write_bytes, atomic_write_json, atomic_write_text
from ne_jax.benchmark.edits import benchmark_edit
from ne_jax.benchmark.generate import generate_benchmark, get_preset
from ne_jax.benchmark.scenes import SCENES, get_scene
from ne_jax.benchmark.variants import MAIN_VARIANTS, VARIANTS, get_variant, variant_run
from ne_jax.config_json import config_key, config_set
from ne_jax.data.nerf_synthetic import composite, load_split
from ne_jax.data.png import write_image
from ne_jax.edit.apply import EditConfig
from ne_jax.edit.model import edit_model, finetune
from ne_jax.eval import evaluate_model
from ne_jax.provenance import commit
from ne_jax.train.model import TrainedModel
from ne_jax.train.run import get_run_preset


def score(model: TrainedModel, variant, scene_dir: Path) -> tuple[dict, np.ndarray]:
    split = load_split(scene_dir, "test")
    report, images = evaluate_model(model, split, progress=False, image_fn=variant.image_fn())
    lp = report.get("lpips")
    return {"psnr": round(report["psnr"], 2), "ssim": round(report["ssim"], 4),
            "lpips": None if lp is None else round(lp, 4), "lost_segments": report["lost_segments"]}, images[0]


def trained_model(run, scene_dir: Path, run_dir: Path, log) -> TrainedModel:
    t0 = time.perf_counter()
    model = cached_run(run, scene_dir, run_dir)
    log(f"  model {run.name}: {time.perf_counter() - t0:.0f} s (cached runs return at once)")
    return model


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="tiny", choices=["tiny", "default"])
    parser.add_argument("--root", default=None,
                        help="an existing benchmark folder of the preset (default: generate in --runs)")
    parser.add_argument("--runs", help="folder for models, edited models and fine-tuning runs (reused; required)")
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    parser.add_argument("--edits", nargs="+", default=None, help="subset of edit names (default: every edit)")
    parser.add_argument("--variants", nargs="+", default=list(MAIN_VARIANTS),
                        help=f"variant names or 'all' (default: {' '.join(MAIN_VARIANTS)}); one of {sorted(VARIANTS)}")
    parser.add_argument("--finetune-epochs", type=int, default=1)
    parser.add_argument("--finetune-steps", type=int, default=None,
                        help="steps per fine-tuning epoch (default: the preset's)")
    parser.add_argument("--no-finetune", action="store_true")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD.PATH=VALUE",
                        help="change a field of the preset's RunConfig (repeatable), e.g. render.pixel_samples=1")
    parser.add_argument("--by-kind", type=Path, metavar="RESULTS.json",
                        help="write the table by kind of edit of a results file next to it, and stop")
    args = parser.parse_args(argv)
    if args.by_kind:
        print(write_by_kind(args.by_kind).read_text(encoding="utf-8"))
        return
    if args.runs is None:
        parser.error("the following arguments are required: --runs")
    try:
        full = config_set(get_run_preset(args.preset), *args.set)
    except ValueError as e:
        parser.error(f"--set: {e}")
    names = list(VARIANTS) if args.variants == ["all"] else args.variants
    variants = [get_variant(n) for n in names]

    runs = Path(args.runs)
    root = Path(args.root) if args.root else runs / "benchmark"
    if not (root / args.scenes[0] / "scene.json").is_file():
        generate_benchmark(root, get_preset(args.preset), args.scenes)
    key = config_key(full)
    complete = set(MAIN_VARIANTS) <= set(names) and set(args.scenes) == set(SCENES) and args.edits is None
    tag = ("_all" if len(names) > len(MAIN_VARIANTS) else "") if complete else "_partial"
    benchmark = args.preset + benchmark_suffix(root, args.scenes)  # <preset>_pt on the path-traced variant
    out_name = f"deform_benchmark_{benchmark}{tag}"
    records, figure, unedited_models = [], {}, {}
    t_start = time.perf_counter()
    ft_tag = "zero" if args.no_finetune else f"ft{args.finetune_epochs}x{args.finetune_steps or full.steps_per_epoch}"
    for scene in args.scenes:
        print(f"== {scene}", flush=True)
        scene_dir = root / scene
        models = {}

        def model_of(v, models=models, scene_dir=scene_dir, scene=scene):  # trained (or read back) only when needed
            run = variant_run(full, v)
            if run.name not in models:
                models[run.name] = trained_model(run, scene_dir, runs / scene / "models" / run.name, print)
            return models[run.name]

        records_dir = runs / scene / "records" / key
        own = records_dir / f"unedited-{full.name}.json"
        if own.is_file():
            unedited = json.loads(own.read_text(encoding="utf-8"))
        else:  # the full model on its own test views: what a faithful zero-shot edit can reach
            unedited = {"scene": scene, **score(model_of(get_variant("full")), get_variant("full"), scene_dir)[0]}
            own.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_json(own, unedited)
        unedited_models[scene] = unedited
        edits = [e for e in get_scene(scene).edits if args.edits is None or e in args.edits]
        for edit in edits:
            truth = scene_dir / "edits" / edit
            split = load_split(truth, "test")
            figure[(scene, edit, "ground truth")] = composite(split.images[:1], full.background)[0]
            finetuned = {}
            for v in variants:
                cache = records_dir / edit / f"{v.name}-{ft_tag}"
                if cache.with_suffix(".json").is_file():  # measured by an earlier run with the same settings
                    rec = json.loads(cache.with_suffix(".json").read_text(encoding="utf-8"))
                    image = np.load(cache.with_suffix(".npy"))
                else:
                    zero = records_dir / edit / f"{v.name}-zero"  # zero-shot, measured on its own
                    rec, image = measure(args, runs, scene, edit, truth, v, model_of(v), finetuned, zero)
                    cache.parent.mkdir(parents=True, exist_ok=True)
                    atomic_write_bytes(cache.with_suffix(".npy"), _npy_bytes(image))
                    atomic_write_json(cache.with_suffix(".json"), rec)
                figure[(scene, edit, v.label)] = image
                records.append(rec)
                ft = rec.get("finetune", {}).get("psnr", float("nan"))
                print(f"  {edit:>12} {v.name:>22}: zero-shot {rec['zero_shot']['psnr']:.2f} dB, "
                      f"fine-tuned {ft:.2f} dB", flush=True)
            write_results(out_name, args, full, records, variants, time.perf_counter() - t_start, unedited_models,
                          benchmark)
            write_figure(out_name, figure, variants)
    print((RESULTS / f"{out_name}.md").read_text())


def _npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


def measure(args, runs: Path, scene: str, edit: str, truth: Path, v, model: TrainedModel, finetuned: dict,
            zero_cache: Path) -> tuple[dict, np.ndarray]:
    """One record: edit ``model`` for variant ``v``, score zero-shot (or read the score back from
    ``zero_cache``, a ``--no-finetune`` record of the same edit and variant), fine-tune (shared by
    variants with the same model and IST setting through ``finetuned``) and score again. The edit is
    made only when something reads it."""
    t0 = time.perf_counter()
    key = (model.run.name, v.ist, v.edit)  # Naive Plotting plots the fine-tuned model without IST
    scored = zero_cache.with_suffix(".json").is_file()
    if not scored or (not args.no_finetune and key not in finetuned):  # else nothing reads the edit
        edited, rep = edit_model(model, benchmark_edit(model.scene_dir, edit)[0], ist=v.ist, cfg=v.edit,
                                 scene_dir=truth, label=edit)
    if scored:
        rec = json.loads(zero_cache.with_suffix(".json").read_text(encoding="utf-8"))
        image = np.load(zero_cache.with_suffix(".npy"))
    else:
        zero, image = score(edited, v, truth)
        rec = {"scene": scene, "edit": edit, "variant": v.name, "zero_shot": zero,
               "edit_report": {k: rep[k] for k in ("moved", "deleted", "good", "filled", "identity")},
               "zero_shot_seconds": round(time.perf_counter() - t0, 1)}
    if not args.no_finetune:
        t0 = time.perf_counter()
        if key not in finetuned:
            changed = "".join(  # the edit settings that differ from the default, one folder each
                f"-{f.name}={val if isinstance(val, (bool, int, float, str)) else zlib.crc32(repr(val).encode())}"
                for f in dataclasses.fields(v.edit)
                if (val := getattr(v.edit, f.name)) != getattr(EditConfig(), f.name))
            steps = args.finetune_steps or model.run.steps_per_epoch  # a folder per fine-tuning length
            ft_dir = (runs / scene / "finetune" / edit / f"{model.run.name}-{config_key(model.run)}"
                      f"-{'ist' if v.ist else 'noist'}{changed}-ft{args.finetune_epochs}x{steps}")
            finetuned[key] = finetune(edited, ft_dir, args.finetune_epochs, steps_per_epoch=args.finetune_steps,
                                      progress=False, log=lambda s: None)
        rec["finetune"] = score(finetuned[key], v, truth)[0]
        rec["finetune_seconds"] = round(time.perf_counter() - t0, 1)
    return rec, image


def write_results(out_name: str, args, full, records: list, variants, seconds: float, unedited: dict,
                  benchmark: str | None = None) -> None:
    benchmark = benchmark or args.preset
    report = {
        "what": "edit each scene's trained models by every benchmark edit; PSNR/SSIM of the edited test views "
                "zero-shot and after fine-tuning on the edited scene's training views",
        "preset": args.preset, "benchmark": benchmark,
        "finetune_epochs": 0 if args.no_finetune else args.finetune_epochs,
        "finetune_steps_per_epoch": args.finetune_steps or full.steps_per_epoch,
        "training": {"epochs": full.epochs, "steps_per_epoch": full.steps_per_epoch,
                     "batch_size": full.sampler.batch_size},
        "background": full.background, "seconds": round(seconds, 1), "records": records,
        "unedited": unedited, "commit": commit(short=True), "config_key": config_key(full), "set": list(args.set),
        "machine": machine(python=True),
        "command": "python -m experiments.deform_benchmark " + " ".join(
            f"--{k.replace('_', '-')}" + ("" if v is True else f" {' '.join(v) if isinstance(v, list) else v}")
            for k, v in vars(args).items()
            if v not in (None, False, []) and k not in ("runs", "root", "set")
            and not (k == "finetune_epochs" and args.no_finetune))
        + "".join(f" --set {shlex.quote(a)}" for a in args.set)
        + ("" if benchmark == args.preset else f" --root BENCH/{benchmark}") + " --runs DIR"}
    columns = list(dict.fromkeys((r["scene"], r["edit"]) for r in records))
    on = "" if benchmark == args.preset else f" on the `{benchmark}` benchmark"
    lines = [f"Deformation benchmark, preset `{args.preset}`{on} ({full.epochs} x {full.steps_per_epoch} training "
             f"steps; fine-tuning {report['finetune_epochs']} epoch(s) x {report['finetune_steps_per_epoch']} steps), "
             f"commit {report['commit']}, config key {report['config_key']}. PSNR (dB) on the edited scenes' test "
             f"views per edit, and the means of PSNR, SSIM and LPIPS (AlexNet; lower is better); background "
             f"{full.background}. The last row is the unedited model on its own test views (the reference a "
             f"faithful edit can reach). Re-run: `{report['command']}`.", ""]
    for phase, title in (("zero_shot", "Zero-shot"), ("finetune", "Fine-tuned")):
        if not any(phase in r for r in records):
            continue
        lines += [f"**{title}**", "", "| variant | " + " | ".join(f"{s}/{e}" for s, e in columns)
                  + " | PSNR | SSIM | LPIPS |", "|---|" + "---:|" * (len(columns) + 3)]
        for v in variants:
            got = {(r["scene"], r["edit"]): r[phase] for r in records if r["variant"] == v.name and phase in r}
            if not got:
                continue
            cells = ["" if c not in got else f"{got[c]['psnr']:.2f}" for c in columns]
            lines.append(f"| {v.label} | " + " | ".join(cells) + f" | {_means(got.values())} |")
        own = [unedited[s] for s, _ in columns if s in unedited]
        if own:
            cells = [f"{unedited[s]['psnr']:.2f}" if s in unedited else "" for s, _ in columns]
            lines.append("| unedited model, own test views | " + " | ".join(cells) + f" | {_means(own)} |")
        lines.append("")
    common.write_results(RESULTS, out_name, report, "\n".join(lines), echo=False)


def _means(rows) -> str:
    """The mean PSNR, SSIM and LPIPS cells of a table row, each over the ``rows`` that have it."""
    vals = {k: [r[k] for r in rows if r.get(k) is not None] for k in ("psnr", "ssim", "lpips")}
    return " | ".join(f"{np.mean(v):.{2 if k == 'psnr' else 3}f}" if v else "" for k, v in vals.items())


def write_figure(out_name: str, figure: dict, variants) -> None:
    rows = list(dict.fromkeys((s, e) for s, e, _ in figure))
    cols = ["ground truth"] + [v.label for v in variants]
    h, w = next(iter(figure.values())).shape[:2]
    pad = 2
    grid = np.ones((len(rows) * (h + pad), len(cols) * (w + pad), 3), np.float32)
    for i, (s, e) in enumerate(rows):
        for j, c in enumerate(cols):
            img = figure.get((s, e, c))
            if img is not None:
                grid[i * (h + pad):i * (h + pad) + h, j * (w + pad):j * (w + pad) + w] = np.clip(img, 0, 1)
    write_image(RESULTS / f"{out_name}.png", grid)
    atomic_write_text(RESULTS / f"{out_name}_figure.txt", "columns: " + ", ".join(cols) + "\nrows: "
                      + ", ".join(f"{s}/{e}" for s, e in rows) + "\n")


KINDS = {
    "smooth deformation": ("twist", "bend"),
    "rigid part": ("tilt_seat", "turn_handle", "roll_ball", "tilt_ring"),
    "cut": ("cut",),
    "deletion": ("delete_leg", "delete_handle", "delete_ball", "delete_cube"),
    "turn, co-moving": ("turn_with_light",),
    "turn, fixed": ("turn_scene",),
}
"""Each benchmark edit by kind (``ne_jax.benchmark.scenes``: one edit of each kind per scene)."""


def kind_of(edit: str) -> str:
    for kind, names in KINDS.items():
        if edit in names:
            return kind
    raise KeyError(f"deform_benchmark: edit {edit!r} has no kind; expected one of {sorted(sum(KINDS.values(), ()))}")


def by_kind(records: list[dict], stage: str = "zero_shot") -> str:
    """A Markdown table: one row per variant, the mean PSNR of each kind of edit over the scenes,
    the mean over every edit, and the mean SSIM and LPIPS."""
    variants = list(dict.fromkeys(r["variant"] for r in records))
    kinds = [k for k in KINDS if any(kind_of(r["edit"]) == k for r in records)]
    lines = ["| variant | " + " | ".join(kinds) + " | mean | SSIM | LPIPS |", "|---|" + "---:|" * (len(kinds) + 3)]
    for v in variants:
        rows = [r[stage] for r in records if r["variant"] == v and stage in r]
        if not rows:
            continue
        cells = []
        for k in kinds:
            vals = [r[stage]["psnr"] for r in records if r["variant"] == v and kind_of(r["edit"]) == k and stage in r]
            cells.append(f"{np.mean(vals):.2f}" if vals else "")
        lines.append(f"| {v} | " + " | ".join(cells) + f" | {_means(rows)} |")
    return "\n".join(lines)


def write_by_kind(results: Path) -> Path:
    """``<stem>_by_kind.md`` next to the results file ``results`` (``--by-kind``); returns its path."""
    data = json.loads(results.read_text(encoding="utf-8"))
    unedited = data.get("unedited", {})
    parts = [f"Deformation benchmark by kind of edit, preset `{data['preset']}`, commit {data['commit']} "
             f"(from `{results.name}`; re-run: `python -m experiments.deform_benchmark --by-kind {results.name}`). "
             "PSNR in dB, the mean over the scenes of each kind.", "", "**Zero-shot**", "", by_kind(data["records"])]
    if any("finetune" in r for r in data["records"]):
        parts += ["", "**Fine-tuned**", "", by_kind(data["records"], "finetune")]
    if unedited:
        mean = np.mean([u["psnr"] for u in unedited.values()])
        parts += ["", f"The unedited models score {mean:.2f} dB on their own test views (mean of "
                      f"{len(unedited)} scenes)."]
    out = results.with_name(results.stem + "_by_kind.md")
    atomic_write_text(out, "\n".join(parts) + "\n")
    return out


if __name__ == "__main__":
    entry(main)
