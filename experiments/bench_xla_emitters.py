"""What XLA:CPU's code emitters cost a ``default`` render and training step: compile time and run time.

    python -m experiments.bench_xla_emitters [--rounds 2] [--steps 5] [--quick]

XLA:CPU turns each fusion of the optimised program into machine code with one of two emitters:
the MLIR-based fusion emitters (JAX 0.10's default) or the older LLVM-IR loop emitters
(``XLA_FLAGS=--xla_cpu_use_fusion_emitters=false``). This study prices the choice on the programs
ne_jax runs, at XLA's default optimisation level (3, what users' programs get) and at level 0 (what
``tests/conftest.py`` compiles the test suite at). Each setting runs in a child process with its
``XLA_FLAGS`` and one host device: it builds the render and the training step of
``experiments/profile_hot_path.py`` (``whole_calls``: 100,000 points on the glossy surface, a
2,048-ray training batch and a render batch; ``--quick``: 20,000 points), then times each one's
first call, split into tracing, lowering and compiling (JAX's monitoring events), and the best of
``--steps`` further calls. Results must agree across settings: the loss to 1e-5 and the rendered
colours to 1e-5 (relative, in their sum).

Writes ``experiments/results/bench_xla_emitters.{json,md}`` (``bench_xla_emitters_quick`` with
``--quick``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

from experiments.common import check_agree, command, commit, first_call_by_phase, write_results

RESULTS = Path(__file__).resolve().parent / "results"
SETTINGS = {
    "level 3, fusion emitters": "",
    "level 3, loop emitters": "--xla_cpu_use_fusion_emitters=false",
    "level 0, fusion emitters": "--xla_backend_optimization_level=0",
    "level 0, loop emitters": "--xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false",
}


def measure(steps: int, quick: bool) -> dict:
    """The render's and the training step's first call, by phase, and their best of ``steps``."""
    import numpy as np

    from experiments.profile_hot_path import whole_calls

    render, step, state, _ = whole_calls(quick)
    r, out = first_call_by_phase(lambda: render(state), steps)
    s, (_, metrics) = first_call_by_phase(lambda: step(state), steps)
    return {"render": r, "step": s, "rgb_sum": float(np.asarray(out.rgb, np.float64).sum()),
            "loss": float(np.asarray(metrics["loss/total"])),
            "load_average_1_5_15_min": [round(x, 2) for x in os.getloadavg()]}


def _child(setting: str, steps: int, quick: bool) -> dict:
    env = {**os.environ, "XLA_FLAGS": SETTINGS[setting], "NE_JAX_HOST_DEVICES": "1"}
    cmd = [sys.executable, "-m", "experiments.bench_xla_emitters", "--child", "--steps", str(steps)]
    res = subprocess.run(cmd + (["--quick"] if quick else []), capture_output=True, text=True, env=env)
    if res.returncode != 0:
        raise RuntimeError(f"bench_xla_emitters child {setting!r} failed:\n{res.stderr[-4000:]}")
    return {"setting": setting, "xla_flags": SETTINGS[setting], **json.loads(res.stdout.strip().splitlines()[-1])}


def to_markdown(res: dict) -> str:
    best, ref = res["best"], res["best"]["level 3, fusion emitters"]
    lines = ["# XLA:CPU's emitters: compile and run time of a `default` render and training step", "",
             f"Commit {res['commit']}, {res['machine']['cpus']} CPUs, jax {res['jax']}, one host device; "
             f"`{res['command']}`. Best of {res['rounds']} rounds (each setting in a fresh process); first "
             f"call = trace + lower + compile + one run; ratios against level 3 with the fusion emitters "
             f"(JAX's default). Loss {ref['loss']:.5f} and rendered colour sum {ref['rgb_sum']:.3f} agree to "
             f"1e-5 in every setting.", ""]
    for call in ("step", "render"):
        lines += [f"**{'training step' if call == 'step' else 'render'}**", "",
                  "| setting | first call s | trace s | lower s | compile s | compile / default | ms per call | "
                  "run / default |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
        for s in SETTINGS:
            r, d = best[s][call], ref[call]
            lines.append(f"| {s} | {r['first_call_s']:.1f} | {r['trace_s']:.1f} | {r['lower_s']:.1f} "
                         f"| {r['compile_s']:.1f} | {r['compile_s'] / d['compile_s']:.2f}x | {r['best_ms']:.0f} "
                         f"| {r['best_ms'] / d['best_ms']:.2f}x |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--steps", type=int, default=5, help="timed calls after the first (best is kept)")
    ap.add_argument("--quick", action="store_true", help="20,000 points")
    ap.add_argument("--out-dir", type=Path, default=RESULTS)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(measure(args.steps, args.quick)))
        return
    import jax

    rows = []
    for k in range(args.rounds):
        for s in SETTINGS:
            rows.append(_child(s, args.steps, args.quick))
            st, rd = rows[-1]["step"], rows[-1]["render"]
            print(f"round {k + 1} {s}: step first call {st['first_call_s']:.1f} s, {st['best_ms']:.0f} ms; "
                  f"render first call {rd['first_call_s']:.1f} s, {rd['best_ms']:.0f} ms", flush=True)
    check_agree("bench_xla_emitters", "loss", [r["loss"] for r in rows])
    check_agree("bench_xla_emitters", "rendered colour sums", [r["rgb_sum"] for r in rows])
    best = {}
    for s in SETTINGS:  # per call: the round with the fastest first call, and the fastest run of any round
        mine = [r for r in rows if r["setting"] == s]
        best[s] = {**mine[0]}
        for call in ("step", "render"):
            best[s][call] = {**min((r[call] for r in mine), key=lambda c: c["first_call_s"]),
                             "best_ms": min(r[call]["best_ms"] for r in mine)}
    res = {"command": command("experiments.bench_xla_emitters", argv), "commit": commit(), "jax": jax.__version__,
           "machine": {"cpus": os.cpu_count()}, "rounds": args.rounds, "steps": args.steps, "quick": args.quick,
           "rows": rows, "best": best}
    write_results(args.out_dir, "bench_xla_emitters" + ("_quick" if args.quick else ""), res, to_markdown(res))


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    main()
