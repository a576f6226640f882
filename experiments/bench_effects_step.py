"""The colour model's share of a ``default`` training step and render chunk, per declared effects.

For each set of effects (``blocks``'s declaration: specular off and a constant background; specular
alone; the background sphere alone; every effect), the hot-path profile of
:mod:`experiments.profile_hot_path` on the same inputs (the benchmark's glossy surface, 100,000
points, a 2,048-ray training batch and a 4,096-ray render chunk): the whole training step, the
colour MLPs (``shade``) jitted alone on the training and the render batch, the whole render chunk,
and the colour model's parameters. Shares are of the whole step or render, ratios against every
effect on, all measured in one process one after the other (best of ``--repeats`` each).

    python -m experiments.bench_effects_step [--repeats 5] [--quick]

Writes ``experiments/results/bench_effects_step.{json,md}``.
"""

from __future__ import annotations

import argparse
import os
import platform
from pathlib import Path

from experiments.common import write_results
from experiments.profile_hot_path import CONFIG, RESULTS, profile_stages

SPECS = {  # label -> --effects spec
    "declared by blocks (specular off, constant background)": "specular=off,background_model=constant",
    "specular alone (the preset)": "specular=on,background_model=constant",
    "background sphere alone": "specular=off,background_model=sphere",
    "every effect (specular, sphere)": "all",  # ne_jax.train.effects.ALL_ON
}


def _row(label: str, spec: str, repeats: int, quick: bool) -> dict:
    import jax

    from ne_jax.render.shading import init_color_model
    from ne_jax.train.effects import declare_effects
    from ne_jax.train.run import get_run_preset

    base = get_run_preset(CONFIG)
    render, record = declare_effects(base.render, spec, scene_dir=None)
    run = base.replace(render=render)
    prof = profile_stages(repeats, quick, run)
    ms = {(r["batch"], r["stage"]): r["ms"] for r in prof["rows"]}
    params = init_color_model(render.shading, jax.random.key(1))
    n_params = sum(int(x.size) for x in jax.tree_util.tree_leaves(params))
    step, shade_t = ms[("train", "whole training step")], ms[("train", "MLPs (shade)")]
    render, shade_r = ms[("render", "whole render")], ms[("render", "MLPs (shade)")]
    return {"label": label, "spec": spec, "effects": record["effects"], "colour_parameters": n_params,
            "step_ms": step, "shade_train_ms": shade_t, "shade_share_of_step": shade_t / step,
            "render_ms": render, "shade_render_ms": shade_r, "shade_share_of_render": shade_r / render,
            "load_average_1_5_15_min": [round(x, 2) for x in os.getloadavg()], "profile": prof}


def to_markdown(report: dict) -> str:
    ref = report["rows"][-1]
    lines = [f"# The colour model's share of a `{CONFIG}` step, per declared effects", "",
             f"Commit {report['commit']}, {report['device']}, jax {report['jax']}, {report['machine']['cpus']} CPUs. "
             f"Command: `{report['command']}`. Rows measured one after the other in one process, best of "
             f"{report['repeats']}; load averages in the JSON.", "",
             "| effects | colour parameters | training step ms | shade ms (share of step) | step / every effect | "
             "render chunk ms | shade ms (share of render) | render / every effect |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in report["rows"]:
        lines.append(f"| {r['label']} | {r['colour_parameters']:,} | {r['step_ms']:.1f} | {r['shade_train_ms']:.1f} "
                     f"({100 * r['shade_share_of_step']:.0f}%) | {r['step_ms'] / ref['step_ms']:.2f}x | "
                     f"{r['render_ms']:.1f} | {r['shade_render_ms']:.1f} ({100 * r['shade_share_of_render']:.0f}%) | "
                     f"{r['render_ms'] / ref['render_ms']:.2f}x |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="20,000 points (a smoke test)")
    ap.add_argument("--out-dir", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    import jax

    from ne_jax.provenance import commit

    rows = []
    for label, spec in SPECS.items():
        rows.append(_row(label, spec, args.repeats, args.quick))
        print(f"{label}: step {rows[-1]['step_ms']:.1f} ms, shade {rows[-1]['shade_train_ms']:.1f} ms", flush=True)
    report = {"command": "python -m experiments.bench_effects_step" + (" --quick" if args.quick else "")
              + (f" --repeats {args.repeats}" if args.repeats != 5 else ""),
              "commit": commit(), "config": CONFIG, "repeats": args.repeats, "device": str(jax.devices()[0]),
              "jax": jax.__version__, "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
              "rows": rows}
    write_results(args.out_dir, "bench_effects_step" + ("_quick" if args.quick else ""), report, to_markdown(report))


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    main()
