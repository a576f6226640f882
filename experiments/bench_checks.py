"""What switching on the runtime checks (``RenderConfig.checks``) costs a ``default`` training step.

    python -m experiments.bench_checks [--rounds 2] [--steps 5] [--quick]

Each round runs three child processes, in turn: the training step without checks (``off``), with
checks as ``ne_jax.checks`` makes them (``on``: each ``checkify.check`` in a small program of its own,
taking its formatting arguments as arguments), and with each check made in the caller's trace
(``on_inline``: the reference, ``checkify.check`` called where the stage is checked). A child
builds the training step of ``experiments/profile_hot_path.py`` with ``checks`` set
(``whole_calls``: 100,000 points on the glossy surface, a 2,048-ray training batch; ``--quick``:
20,000 points), then times the step's first call, split into tracing, lowering and compiling (JAX's
monitoring events), and the best of ``--steps`` further calls.
The best of the rounds is tabled, with ratios against ``on_inline`` and ``off``; the loss must
agree to 1e-5 (relative) in every setting.

Writes ``experiments/results/bench_checks.{json,md}`` (``bench_checks_quick`` with ``--quick``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

from experiments.common import check_agree, command, commit, first_call_by_phase, write_results
from experiments.profile_hot_path import CONFIG, whole_calls

RESULTS = Path(__file__).resolve().parent / "results"
SETTINGS = ("off", "on", "on_inline")


def measure(setting: str, steps: int, quick: bool) -> dict:
    """The first call of the (un)checked training step, by phase, and the best of ``steps`` more."""
    import numpy as np
    from jax.experimental import checkify

    import ne_jax.checks
    from ne_jax.train.run import get_run_preset

    if setting == "on_inline":
        def inline(message, ok, i, value):
            checkify.check(ok, message, i=i, value=value)

        ne_jax.checks._check_finite = inline
    run = get_run_preset(CONFIG)
    run = run.replace(render=run.render.replace(checks=setting != "off"))
    _, step, state, _ = whole_calls(quick, run)
    phases, (_, metrics) = first_call_by_phase(lambda: step(state), steps)
    step_ms = phases.pop("best_ms")
    return {"setting": setting, **phases, "step_ms": step_ms,
            "loss": float(np.asarray(metrics["loss/total"])),
            "load_average_1_5_15_min": [round(x, 2) for x in os.getloadavg()]}


def _child(setting: str, steps: int, quick: bool) -> dict:
    cmd = [sys.executable, "-m", "experiments.bench_checks", "--child", setting, "--steps", str(steps)]
    res = subprocess.run(cmd + (["--quick"] if quick else []), capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"bench_checks child {setting!r} failed:\n{res.stderr[-4000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def to_markdown(res: dict) -> str:
    best, ref, off = res["best"], res["best"]["on_inline"], res["best"]["off"]
    lines = ["# Runtime checks: the cost of `checks=True` on a `default` training step", "",
             f"Commit {res['commit']}, {res['machine']['cpus']} CPUs, jax {res['jax']}; `{res['command']}`. "
             f"Best of {res['rounds']} rounds (each setting in a fresh process); first call = trace + lower + "
             f"compile + one run; loss {ref['loss']:.5f} in every setting.", "",
             "| setting | first call s | trace s | lower s | compile s | first call / inline | step ms | step / off |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for s in SETTINGS:
        r = best[s]
        lines.append(f"| {s} | {r['first_call_s']:.1f} | {r['trace_s']:.1f} | {r['lower_s']:.1f} "
                     f"| {r['compile_s']:.1f} | {r['first_call_s'] / ref['first_call_s']:.2f}x | {r['step_ms']:.0f} "
                     f"| {r['step_ms'] / off['step_ms']:.2f}x |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--steps", type=int, default=5, help="timed steps after the first call (best is kept)")
    ap.add_argument("--quick", action="store_true", help="20,000 points")
    ap.add_argument("--out-dir", type=Path, default=RESULTS)
    ap.add_argument("--child", choices=SETTINGS, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(measure(args.child, args.steps, args.quick)))
        return
    import jax

    rows = []
    for k in range(args.rounds):
        for s in SETTINGS:
            rows.append(_child(s, args.steps, args.quick))
            print(f"round {k + 1} {s}: first call {rows[-1]['first_call_s']:.1f} s, step {rows[-1]['step_ms']:.0f} ms",
                  flush=True)
    # the checks change fusion, so the float32 rounding may differ
    check_agree("bench_checks", "losses", [r["loss"] for r in rows])
    best = {s: min((r for r in rows if r["setting"] == s), key=lambda r: r["first_call_s"]) for s in SETTINGS}
    res = {"command": command("experiments.bench_checks", argv), "commit": commit(), "jax": jax.__version__,
           "machine": {"cpus": os.cpu_count()}, "rounds": args.rounds, "steps": args.steps, "quick": args.quick,
           "rows": rows, "best": best}
    write_results(args.out_dir, "bench_checks" + ("_quick" if args.quick else ""), res, to_markdown(res))


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    main()
