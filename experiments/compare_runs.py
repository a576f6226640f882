"""Two training runs side by side: are their final models the same array for array, and what did
each take?

    python -m experiments.compare_runs RUN_A RUN_B

Loads each run's latest checkpoint (as ``ne-jax eval`` does) and prints per array of the parameters and
the cloud the largest absolute difference (``shape`` where the shapes differ), then both runs'
per-epoch training PSNR and seconds and the ratio of their sums. Exit code 0 when every array is equal.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from experiments.common import entry


def array_differences(a, b) -> dict[str, float | str]:
    """``{path: max |a - b|}`` over the leaves of two pytrees of arrays (``"shape"`` if they differ)."""
    import jax

    la, lb = jax.tree_util.tree_leaves_with_path(a), jax.tree_util.tree_leaves_with_path(b)
    if [p for p, _ in la] != [p for p, _ in lb]:
        raise ValueError("the two runs' models have different structures")
    out = {}
    for (path, x), (_, y) in zip(la, lb):
        x, y = np.asarray(x), np.asarray(y)
        name = jax.tree_util.keystr(path)
        if x.shape != y.shape:
            out[name] = "shape"
        elif x.dtype == bool or np.issubdtype(x.dtype, np.integer):
            out[name] = float(np.sum(x != y))
        else:
            out[name] = float(np.max(np.abs(x.astype(np.float64) - y.astype(np.float64)), initial=0.0))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", type=Path, nargs=2, metavar="RUN")
    args = ap.parse_args(argv)
    from ne_jax.train.model import load_trained

    models = [load_trained(r) for r in args.runs]
    points = [m.state.point_state(m.scene.points) for m in models]
    diffs = {**{f"params{k}": v for k, v in array_differences(models[0].state.params, models[1].state.params).items()},
             **{f"points{k}": v for k, v in array_differences(points[0], points[1]).items()}}
    for name, d in diffs.items():
        print(f"{name}: {d if isinstance(d, str) else f'{d:.3g}'}")
    same = all(d == 0.0 for d in diffs.values())
    print(f"every array equal bit for bit: {same}")
    epochs = [json.loads((r / "metrics.json").read_text())["epochs"] for r in args.runs]
    print("epoch | train PSNR A | train PSNR B | s A | s B")
    for ea, eb in zip(*epochs):
        print(f"{ea['epoch']} | {ea['psnr']:.4f} | {eb['psnr']:.4f} | {ea['train_seconds']:.0f} | "
              f"{eb['train_seconds']:.0f}")
    sa, sb = (sum(e["train_seconds"] for e in ep) for ep in epochs)
    print(f"training seconds: A {sa:.0f}, B {sb:.0f}, B / A = {sb / sa:.3f}")
    return 0 if same else 1


if __name__ == "__main__":
    entry(main)
