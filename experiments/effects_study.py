"""What declaring a scene's effects buys: each benchmark scene trained with the effects its
``scene.json`` declares and with every effect on (docs/studies/effects.md).

    python -m experiments.effects_study --root BENCH/tiny --preset tiny --runs RUNS --out effects_study_tiny

Pin it to one core (``taskset -c 0``) for one core's CPU times. Writes ``<out>.{json,md}`` to
``experiments/results``; runs are cached in ``--runs`` (a finished run keeps its recorded times).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import jax
import numpy as np

from experiments import common
from ne_jax.config_json import config_key
from ne_jax.data.nerf_synthetic import load_split
from ne_jax.eval import evaluate_model
from ne_jax.train.effects import ALL_ON, declare_effects, effects_of, scene_effects, with_declared
from ne_jax.train.loop import train
from ne_jax.train.run import get_run_preset

SCENES = ("glossy", "cup", "stool", "blocks")
TIMING_NOTE = ("train_seconds: wall time of one training as the run recorded it (compiles included; a cached run keeps "
               "its own); train_cpu_seconds: this process's CPU time over that training (for a resumed or "
               "cached run, the CPU time the training loop recorded per epoch, round and initial cloud; null where it "
               "recorded none); seconds_per_image, cpu_seconds_per_image: one pass over the test views after a pass "
               "that compiles; rows ran one after another, next to whatever else the machine ran (load averages "
               "recorded): wall times move with that load, CPU times much less")


def _machine() -> dict:
    """CPU count, device, JAX version and the load average (other jobs inflate the timings)."""
    return common.machine(usable_cpus=len(os.sched_getaffinity(0)), device=jax.devices()[0].device_kind,
                          jax_devices=jax.device_count(), jax=jax.__version__,
                          load_average_1_5_15_min=[round(x, 2) for x in os.getloadavg()], note=TIMING_NOTE)


def specs_for(preset: str, scene_dir: Path, each_effect: bool) -> list[str]:
    """``scene``, then (with ``each_effect``, where the declaration leaves out more than one
    effect) the declaration with each left-out effect switched on alone, as ``name=value`` specs,
    then ``all``."""
    declared = effects_of(with_declared(get_run_preset(preset).render, scene_effects(scene_dir) or {}))
    left_out = [name for name, value in ALL_ON.items() if declared[name] != value]
    singles = [",".join(f"{n}={v}" for n, v in {**declared, name: ALL_ON[name]}.items()) for name in left_out]
    return ["scene", *(singles if each_effect and len(left_out) > 1 else []), "all"]


def measure(preset: str, scene_dir: Path, spec: str, run_dir: Path) -> dict:
    base = get_run_preset(preset)
    render, record = declare_effects(base.render, spec, scene_dir)
    run = base.replace(render=render)
    fresh = not (Path(run_dir) / "metrics.json").exists()  # else resumed or cached: its CPU time as recorded
    c0 = time.process_time()  # this process's CPU time, all its threads: what a job costs, whatever else runs
    model = train(run, scene_dir, run_dir, progress=False, log=lambda s: None, notes={"effects": record})
    train_cpu = time.process_time() - c0 if fresh else model.recorded_cpu_seconds
    split = load_split(scene_dir, "test")
    evaluate_model(model, split, progress=False, lpips_net=None)  # compiles
    t0, c0 = time.perf_counter(), time.process_time()
    report, _ = evaluate_model(model, split, progress=False, lpips_net=None)
    per_image = (time.perf_counter() - t0) / split.num_views
    cpu_per_image = (time.process_time() - c0) / split.num_views
    params = sum(int(np.size(x)) for x in jax.tree_util.tree_leaves(model.state.params))
    return {"spec": spec, "effects": record["effects"], "source": record["source"], "config_key": config_key(run),
            "load_average_1_5_15_min": [round(x, 2) for x in os.getloadavg()],
            "train_seconds": round(model.recorded_seconds, 1),
            "train_cpu_seconds": None if train_cpu is None else round(train_cpu, 1),
            "seconds_per_image": round(per_image, 3), "cpu_seconds_per_image": round(cpu_per_image, 3),
            "parameters": params, "psnr": round(report["psnr"], 2), "ssim": round(report["ssim"], 4)}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", type=Path, required=True, help="a generated benchmark preset folder")
    parser.add_argument("--preset", default="tiny", choices=["tiny", "default"])
    parser.add_argument("--scenes", nargs="+", default=list(SCENES))
    parser.add_argument("--runs", type=Path, required=True)
    parser.add_argument("--out", default=None)
    parser.add_argument("--each-effect", action="store_true",
                        help="also train each effect a scene leaves out, switched on alone")
    parser.add_argument("--specs", nargs="+", default=None, metavar="SPEC",
                        help="only these of each scene's runs (`scene`, `all`, or a `name=value,...` spec of "
                             "--each-effect), e.g. to spread one study over several processes")
    args = parser.parse_args(argv)
    out = args.out or f"effects_study_{args.preset}"
    rows = []
    machine_at_start, commit_at_start = _machine(), common.commit()  # the code imported is the code at the start
    for scene in args.scenes:
        specs = specs_for(args.preset, args.root / scene, args.each_effect)
        unknown = sorted(set(args.specs or ()) - set(specs))
        if unknown:
            parser.error(f"--specs {' '.join(unknown)}: {scene} trains only {', '.join(specs)}")
        for spec in [s for s in specs if args.specs is None or s in args.specs]:
            folder = spec.replace("=", "-").replace(",", "_")
            rec = measure(args.preset, args.root / scene, spec, args.runs / scene / folder)
            rec["scene"] = scene
            rows.append(rec)
            print(f"{scene} {spec}: {rec}", flush=True)
    command = (f"python -m experiments.effects_study --root {args.root} --preset {args.preset} --scenes "
               f"{' '.join(args.scenes)} --runs RUNS --out {out}" + (" --each-effect" if args.each_effect else "")
               + (f" --specs {' '.join(args.specs)}" if args.specs else ""))
    report = {"what": "declared effects against every effect on, per scene", "commit": commit_at_start,
              "command": command, "machine": machine_at_start,
              "load_average_at_end": _machine()["load_average_1_5_15_min"], "rows": rows}
    lines = [f"Declared effects (`scene.json`) against every effect on (`all`), preset `{args.preset}`, commit "
             f"{report['commit']}: `{command}`.", "",
             "| scene | effects | specular | background model | train s | train CPU s | s / image | CPU s / image | "
             "parameters | test PSNR | test SSIM |",
             "|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        e = r["effects"]
        cpu = "-" if r["train_cpu_seconds"] is None else f"{r['train_cpu_seconds']:.0f}"
        lines.append(f"| {r['scene']} | {r['spec']} | {e['specular']} | {e['background_model']} | "
                     f"{r['train_seconds']:.0f} | {cpu} | {r['seconds_per_image']:.2f} | "
                     f"{r['cpu_seconds_per_image']:.2f} | {r['parameters']:,} | {r['psnr']:.2f} | {r['ssim']:.3f} |")
    common.write_results(common.RESULTS, out, report, "\n".join(lines) + "\n")


if __name__ == "__main__":
    common.entry(main)
