"""Huge pages for XLA:CPU's scratch memory (``ne_jax._host_memory``) against glibc's defaults, in one run.

    python -m experiments.bench_host_memory [--rounds 2] [--steps 10] [--quick] [--train SCENE_DIR]

Each round runs two child processes, one started with ``GLIBC_TUNABLES=glibc.malloc.hugetlb=1``
(``huge_pages``: what ``ne-jax`` and ``run.sh`` do) and one without (``system``), in alternating
order. Each child compiles a ``default`` training step (timed: the first call), then times
``--steps`` training steps (the state fed forward, as training does) and as many render chunks, on
the inputs of ``experiments/profile_hot_path.py`` (100,000 points on the glossy surface, 2,048
training rays, 4,096-ray render chunks; ``--quick``: 20,000 points), and reads the page faults and
the kernel and user CPU time of those calls from ``getrusage``. ``--train SCENE_DIR`` also trains
that scene end to end with ``ne-jax train --preset tiny`` in each setting (wall time, page faults
and CPU time of the whole process). The best of the rounds is tabled; the loss must be the same in
both settings.

Writes ``experiments/results/bench_host_memory.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from experiments.common import command, commit, write_results
from ne_jax._host_memory import TUNABLE

SETTINGS = ("huge_pages", "system")
TUNABLES = {"huge_pages": TUNABLE, "system": ""}


def measure(steps: int, quick: bool) -> dict:
    """Per training step and per render chunk: ms, page faults, kernel and user CPU seconds."""
    import jax

    from experiments.profile_hot_path import whole_calls

    render, step, state, _ = whole_calls(quick)

    def usage():
        r = resource.getrusage(resource.RUSAGE_SELF)
        return time.perf_counter(), r.ru_minflt, r.ru_stime, r.ru_utime

    def per_call(a, b):
        return {"ms": 1e3 * (b[0] - a[0]) / steps, "faults": (b[1] - a[1]) / steps,
                "sys_s": (b[2] - a[2]) / steps, "user_s": (b[3] - a[3]) / steps}

    c0 = usage()
    state, m = step(state)
    m["loss/total"].block_until_ready()
    c1 = usage()
    for _ in range(2):  # compile the render, warm up
        state, m = step(state)
        render(state).rgb.block_until_ready()
    first_loss = float(m["loss/total"])
    t0 = usage()
    for _ in range(steps):
        state, m = step(state)
    m["loss/total"].block_until_ready()
    t1 = usage()
    for _ in range(steps):
        out = render(state)
    out.rgb.block_until_ready()
    t2 = usage()
    return {"glibc_tunables": os.environ.get("GLIBC_TUNABLES", ""), "devices": jax.device_count(),
            "compile_step_s": c1[0] - c0[0], "compile_step_user_s": c1[3] - c0[3],
            "step": per_call(t0, t1), "render": per_call(t1, t2), "loss_after_warmup": first_loss,
            "loss_last": float(m["loss/total"])}


def train_once(scene_dir: str, setting: str) -> dict:
    """``ne-jax train --preset tiny`` on ``scene_dir`` in a fresh run directory: wall seconds and the
    child's page faults and CPU seconds."""
    with tempfile.TemporaryDirectory() as tmp:
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "ne_jax.cli", "train", scene_dir, "--preset", "tiny", "--out",
                        str(Path(tmp) / "run"), "--no-eval", "--quiet"],
                       env=_env(setting), check=True)
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        metrics = json.loads((Path(tmp) / "run" / "metrics.json").read_text())
    return {"wall_s": wall, "faults": after.ru_minflt - before.ru_minflt, "sys_s": after.ru_stime - before.ru_stime,
            "user_s": after.ru_utime - before.ru_utime, "final_train_psnr": _last_psnr(metrics)}


def _last_psnr(metrics: dict):
    return (metrics.get("epochs") or [{}])[-1].get("psnr")


def _env(setting: str) -> dict:
    """This process's environment with ``GLIBC_TUNABLES`` as ``setting`` wants it (``ne-jax`` would
    add the tunable itself: ``NE_JAX_HOST_MEMORY=system`` stops it in the ``system`` setting)."""
    env = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
    if TUNABLES[setting]:
        env["GLIBC_TUNABLES"] = TUNABLES[setting]
    else:
        env["NE_JAX_HOST_MEMORY"] = "system"
    return env


def _child(setting: str, steps: int, quick: bool) -> dict:
    cmd = [sys.executable, "-m", "experiments.bench_host_memory", "--child", "--steps", str(steps)]
    res = subprocess.run(cmd + (["--quick"] if quick else []), capture_output=True, text=True,
                         env=_env(setting))
    if res.returncode != 0:
        raise RuntimeError(res.stderr[-4000:])
    return json.loads(res.stdout.strip().splitlines()[-1])


def _best(rows: list[dict], kind: str) -> dict:
    return min((r[kind] for r in rows), key=lambda x: x["ms"])


def to_markdown(res: dict) -> str:
    lines = [f"Huge pages for XLA:CPU's scratch memory (`huge_pages`: `GLIBC_TUNABLES={TUNABLE}`, what `ne-jax` "
             f"and `run.sh` set) against glibc's defaults (`system`); commit {res['commit']}; `{res['command']}`; "
             f"{res['devices']} host devices, "
             f"{res['cpus']} CPUs; best of {res['rounds']} alternating rounds, {res['steps']} calls each; "
             f"load average {res['load_average'][0]:.1f} at the end.", "",
             "| call | setting | ms per call | page faults per call | kernel CPU s per call | user CPU s per call |",
             "|---|---|---:|---:|---:|---:|"]
    for kind, name in (("step", "`default` training step (2,048 rays)"), ("render", "render chunk (4,096 rays)")):
        for s in SETTINGS:
            b = res["best"][s][kind]
            lines.append(f"| {name} | {s} | {b['ms']:.1f} | {b['faults']:.0f} | {b['sys_s']:.3f} | {b['user_s']:.3f} |")
    r = res["ratio"]
    comp = {s: min(x["compile_step_s"] for x in res["rounds_raw"][s]) for s in SETTINGS}
    lines += ["", f"`system` / `huge_pages` time per call: training step {r['step']:.2f}x, render chunk "
              f"{r['render']:.2f}x. Compiling the training step: {comp['huge_pages']:.1f} s (huge_pages), "
              f"{comp['system']:.1f} s (system). Loss after the timed steps: {res['loss_last']['huge_pages']:.6f} "
              f"(huge_pages), {res['loss_last']['system']:.6f} (system)."]
    if res.get("train"):
        lines += ["", "| `ne-jax train --preset tiny` | wall s | page faults | kernel CPU s | user CPU s |",
                  "|---|---:|---:|---:|---:|"]
        for s in SETTINGS:
            t = min(res["train"][s], key=lambda x: x["wall_s"])
            lines.append(f"| {s} | {t['wall_s']:.1f} | {t['faults']:,} | {t['sys_s']:.1f} | {t['user_s']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--quick", action="store_true", help="20,000 points instead of 100,000")
    ap.add_argument("--train", default=None, metavar="SCENE_DIR", help="also train this scene at tiny in each setting")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--out-dir", type=Path, default=Path(__file__).resolve().parent / "results")
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(measure(args.steps, args.quick)))
        return
    code = commit()  # before the runs: HEAD may move while they run
    rows = {s: [] for s in SETTINGS}
    train = {s: [] for s in SETTINGS} if args.train else None
    for i in range(args.rounds):
        for s in SETTINGS if i % 2 == 0 else SETTINGS[::-1]:
            rows[s].append(_child(s, args.steps, args.quick))
            print(s, json.dumps(rows[s][-1]), flush=True)
            if train is not None:
                train[s].append(train_once(args.train, s))
                print(s, "train", json.dumps(train[s][-1]), flush=True)
    best = {s: {k: _best(rows[s], k) for k in ("step", "render")} for s in SETTINGS}
    res = {"what": "page faults and time per call with and without huge pages for XLA:CPU's scratch memory",
           "commit": code, "command": command("experiments.bench_host_memory", argv),
           "rounds": args.rounds, "steps": args.steps, "quick": args.quick, "cpus": os.cpu_count(),
           "devices": rows["huge_pages"][0]["devices"], "load_average": list(os.getloadavg()),
           "best": best, "rounds_raw": rows, "train": train,
           "loss_last": {s: rows[s][0]["loss_last"] for s in SETTINGS},
           "ratio": {k: best["system"][k]["ms"] / best["huge_pages"][k]["ms"] for k in ("step", "render")}}
    write_results(args.out_dir, "bench_host_memory" + ("_quick" if args.quick else ""), res, to_markdown(res))


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    main()
