"""What the density gate (``KDTreeConfig.density_falloff``) does to a preset, on both benchmarks.

For each benchmark root (``--root NAME=DIR``: the ray-cast and the path-traced variant of a preset)
the preset is trained with :mod:`experiments.train_benchmark` as it is (``baseline``) and in each
config ``--config NAME=FIELD.PATH=VALUE[,FIELD.PATH=VALUE...]`` (by default ``gate``: the gate
alone, ``render.kdtree.density_falloff=1.0``), on the same scenes, and the configs are compared
scene by scene: test PSNR / SSIM, training seconds, the points the rounds grew and pruned,
the seen-surface Chamfer ratio, and where the final confidences sit (share below the pruning
threshold 0.1, share above 0.9, median). Without a gate the confidences cannot move the density
(the KNN weights are normalised), so they stay at their initial 0.5 and pruning never fires; the
table shows whether the gate changes that and what it costs.

    python -m experiments.density_gate_study --preset tiny --root tiny=BENCH/tiny --root tiny_pt=BENCH/tiny_pt \\
        --runs RUNS --config gate=render.kdtree.density_falloff=1.0 \\
        --config gate_lr10=render.kdtree.density_falloff=1.0,train.confidence_lr=10

Runs go to ``RUNS/<name>/<config>/`` (``runs/`` and ``results/``); a stopped study continues where it
stopped (finished configs are read back, a stopped one is resumed). Writes
``experiments/results/density_gate_<preset>.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import platform
from pathlib import Path

import numpy as np

from experiments import train_benchmark
from experiments.common import benchmark_suffix, command, commit, write_results
from ne_jax.benchmark.scenes import SCENES

RESULTS = Path(__file__).resolve().parent / "results"
DEFAULT_CONFIG = "gate=render.kdtree.density_falloff=1.0"


def parse_configs(items: list[str]) -> dict[str, list[str]]:
    """``{"baseline": [], name: [FIELD.PATH=VALUE, ...]}`` from ``NAME=CHANGE[,CHANGE...]`` items."""
    out = {"baseline": []}
    for item in items:
        name, sep, changes = item.partition("=")
        if not sep or not name.isidentifier() or "=" not in changes or name in out:
            raise ValueError(f"--config {item!r}: expected a new NAME=FIELD.PATH=VALUE[,FIELD.PATH=VALUE...]")
        out[name] = changes.split(",")
    return out


def same_as_preset(preset: str, configs: dict[str, list[str]]) -> None:
    """Raise ``ValueError`` naming a config whose changes leave the preset as it is (it would train
    the ``baseline``'s models again under another name)."""
    from ne_jax.config_json import config_key, config_set
    from ne_jax.train.run import get_run_preset

    base = get_run_preset(preset)
    for name, changes in configs.items():
        if changes and config_key(config_set(base, *changes)) == config_key(base):
            raise ValueError(f"--config {name}: {', '.join(changes)} is the {preset} preset as it is "
                             f"(config key {config_key(base)}); expected a change")


def _train(preset: str, root: Path, scenes: list[str], out: Path, extra: list[str]) -> dict:
    """The ``train_benchmark`` results of one config (trained now, or read back when complete)."""
    name = preset + benchmark_suffix(root, scenes)
    results = out / "results" / f"train_benchmark_{name}.json"
    if results.is_file():
        done = json.loads(results.read_text())
        if set(scenes) <= set(done["scenes"]):
            return done
    argv = ["--preset", preset, "--root", str(root), "--runs", str(out / "runs"), "--results", str(out / "results"),
            "--scenes", *scenes, *extra]
    if (out / "runs").is_dir():
        argv.append("--resume")
    train_benchmark.main(argv)
    return json.loads(results.read_text())


def confidence_summary(run_dir: Path) -> dict:
    """Where the final alive points' confidences sit."""
    from ne_jax.train.model import load_trained

    points = load_trained(run_dir).scene.points
    conf = np.asarray(points.confidence)[np.asarray(points.alive)]
    return {"below_0.1": round(float(np.mean(conf < 0.1)), 4), "above_0.9": round(float(np.mean(conf > 0.9)), 4),
            "median": round(float(np.median(conf)), 4)}


def _row(name: str, cfg: str, scene: str, res: dict, conf: dict) -> str:
    s = res["scenes"][scene]
    return (f"| {name} | {scene} | {cfg} | {s['test_psnr']:.2f} | {s['test_ssim']:.3f} | {s['train_seconds']:.0f} | "
            f"{s['final_points']} | {s['grown']} | {s['pruned']} | {s['chamfer_seen_ratio']:.2f} | "
            f"{conf['below_0.1']:.1%} | {conf['above_0.9']:.1%} | {conf['median']:.2f} |")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="tiny", choices=["tiny", "default"])
    parser.add_argument("--root", action="append", required=True, metavar="NAME=DIR",
                        help="a benchmark folder of the preset (repeat: ray-cast and path-traced)")
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    parser.add_argument("--runs", type=Path, required=True, help="folder of the runs (kept; a study resumes)")
    parser.add_argument("--config", action="append", default=None, metavar="NAME=FIELD.PATH=VALUE[,...]",
                        help=f"a config to compare with the preset (repeatable; default {DEFAULT_CONFIG})")
    parser.add_argument("--results", type=Path, default=RESULTS)
    parser.add_argument("--epochs", type=int, default=None, help="override the preset's epochs (smoke tests)")
    parser.add_argument("--steps-per-epoch", type=int, default=None)
    args = parser.parse_args(argv)
    schedule = [] if args.epochs is None else ["--epochs", str(args.epochs)]
    schedule += [] if args.steps_per_epoch is None else ["--steps-per-epoch", str(args.steps_per_epoch)]
    try:
        configs = parse_configs(args.config or [DEFAULT_CONFIG])
        same_as_preset(args.preset, configs)
    except ValueError as e:
        parser.error(str(e))
    roots = {}
    for item in args.root:
        name, sep, path = item.partition("=")
        if not sep or not (Path(path) / args.scenes[0] / "scene.json").is_file():
            parser.error(f"--root {item!r}: expected NAME=DIR with DIR/{args.scenes[0]}/scene.json")
        roots[name] = Path(path)

    started = commit()
    table, out = [], {}
    for name, root in roots.items():
        for cfg, changes in configs.items():
            folder = args.runs / name / cfg
            res = _train(args.preset, root, args.scenes, folder, schedule + [a for c in changes for a in ("--set", c)])
            confs = {s: confidence_summary(folder / "runs" / s) for s in args.scenes}
            out.setdefault(name, {})[cfg] = {"config_key": res["config_key"], "commit": res["commit"],
                                             "scenes": {s: {**res["scenes"][s], "confidence": confs[s]}
                                                        for s in args.scenes}}
            table += [_row(name, cfg, s, res, confs[s]) for s in args.scenes]
    means = []
    for name in roots:
        base = np.mean([out[name]["baseline"]["scenes"][s]["test_psnr"] for s in args.scenes])
        for cfg in configs:
            psnr = [out[name][cfg]["scenes"][s]["test_psnr"] for s in args.scenes]
            secs = [out[name][cfg]["scenes"][s]["train_seconds"] for s in args.scenes]
            means.append(f"| {name} | {cfg} | {np.mean(psnr):.2f} | {np.mean(psnr) - base:+.2f} | {min(psnr):.2f} | "
                         f"{np.mean(secs):.0f} |")
    res = {"what": "density gate study", "preset": args.preset, "configs": configs, "commit": started,
           "command": command("experiments.density_gate_study", argv), "machine": {"platform": platform.platform()},
           "benchmarks": out}
    md = "\n".join([
        "Configs against the `" + args.preset + "` preset as it is (`baseline`): "
        + "; ".join(f"`{n}`: " + ", ".join(f"`{c}`" for c in ch) for n, ch in configs.items() if ch)
        + f"; on {', '.join(roots)}; trained at commit "
        f"{', '.join(sorted({c['commit'] for b in out.values() for c in b.values()}))} (the training code of every "
        f"run), tabled at {started}; `{res['command']}`. Training seconds are wall time on the 2-core machine, "
        "the runs one after another; short jobs overlapped some of them, so compare the seconds only roughly.",
        "",
        "| benchmark | config | mean test PSNR | against baseline | worst scene | mean train s |",
        "|---|---|---:|---:|---:|---:|",
        *means,
        "",
        "| benchmark | scene | config | test PSNR | SSIM | train s | final points | grown | pruned | "
        "seen Chamfer ratio | conf < 0.1 | conf > 0.9 | median conf |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        *table,
    ])
    write_results(args.results, f"density_gate_{args.preset}", res, md)


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    main()
