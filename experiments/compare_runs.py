"""Two training runs side by side: are their final models and a test render the same array for array,
and what did each take?

    python -m experiments.compare_runs RUN_A RUN_B [--checkout-a OLD_CHECKOUT] [--view I]

Each run's latest checkpoint (as ``ne-jax eval`` reads it) and a render of its scene's test view
``--view``, read with this checkout's ``ne_jax`` or, for a run another version made, with that
checkout's (``--checkout-a``/``-b``; in a fresh process, ``common.json_from``). Prints per array the
largest absolute difference (``shape`` where the shapes differ), both runs' per-epoch training PSNR
and seconds and the ratio of their sums. Exit code 0 when every array is equal.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np

from experiments.common import entry, json_from


def model_arrays(run: Path, view: int, checkout: Path | None = None) -> dict[str, np.ndarray]:
    """``{name: array}``: the parameters (``params[...]``), the cloud (``points[...]``) and the test
    view ``view``'s ``render.rgb|opacity|depth`` (where the run records its scene folder) of ``run``,
    with the ``ne_jax`` on the path or, given ``checkout``, with its in a fresh process."""
    if checkout is not None:
        with tempfile.TemporaryDirectory() as tmp:
            file = Path(tmp) / "arrays.npz"
            json_from("compare_runs", ["--dump", str(file), str(run.resolve()), "--view", str(view)], checkout)
            with np.load(file) as data:
                return dict(data)
    import jax

    from ne_jax.train.model import load_trained

    model = load_trained(run)
    trees = {"params": model.state.params, "points": model.state.point_state(model.scene.points)}
    out = {name + jax.tree_util.keystr(path): np.asarray(x)
           for name, tree in trees.items() for path, x in jax.tree_util.tree_leaves_with_path(tree)}
    if model.scene_dir is not None:
        try:
            from ne_jax.data.scene import load_split
        except ImportError:  # a version that reads NeRF Synthetic folders only, at full size
            from ne_jax.data.nerf_synthetic import load_split
        downscale = getattr(model.run, "downscale", 1)
        split = load_split(model.scene_dir, "test", *((downscale,) if downscale != 1 else ()))
        image = model.render_image(split.camera(view))
        out.update({f"render.{k}": np.asarray(getattr(image, k)) for k in ("rgb", "opacity", "depth")})
    return out


def array_differences(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, float | str]:
    """``{name: max |a - b|}`` (``"shape"`` where the shapes differ; the count of differing entries of
    integer and boolean arrays)."""
    if list(a) != list(b):
        raise ValueError(f"the two runs' models have different arrays: {sorted(set(a) ^ set(b))}")
    out = {}
    for name, x in a.items():
        y = b[name]
        if x.shape != y.shape:
            out[name] = "shape"
        elif x.dtype == bool or np.issubdtype(x.dtype, np.integer):
            out[name] = float(np.sum(x != y))
        else:
            out[name] = float(np.max(np.abs(x.astype(np.float64) - y.astype(np.float64)), initial=0.0))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", type=Path, nargs="+", metavar="RUN")
    ap.add_argument("--view", type=int, default=0, help="the test view rendered and compared (default 0)")
    ap.add_argument("--checkout-a", type=Path, default=None, help="read RUN_A with this checkout's ne_jax")
    ap.add_argument("--checkout-b", type=Path, default=None, help="read RUN_B with this checkout's ne_jax")
    ap.add_argument("--dump", type=Path, default=None, help=argparse.SUPPRESS)  # model_arrays' child
    args = ap.parse_args(argv)
    if args.dump is not None:
        np.savez(args.dump, **model_arrays(args.runs[0], args.view))
        print(json.dumps({"file": str(args.dump)}))
        return 0
    if len(args.runs) != 2:
        ap.error(f"expected two run directories, found {len(args.runs)}")
    diffs = array_differences(*(model_arrays(r, args.view, c) for r, c in zip(args.runs, (args.checkout_a,
                                                                                        args.checkout_b))))
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
