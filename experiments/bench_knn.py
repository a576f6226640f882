"""How the renderer's KNN integration chooses each sample's ``K`` nearest candidates: by ranking
(every candidate counts the candidates closer to the sample) or by ``lax.top_k``.

    python -m experiments.bench_knn [--segments 16384] [--repeats 5]

For the candidate widths of the presets (``tiny``/``default``: 16 of 32, 6 samples per segment;
``paper``: 32 of 96, 22 samples), on segments of a 100,000-point cloud on the benchmark's glossy
surface, in one process:

* the selection alone: ``lax.top_k`` against ranking, and whether they choose the same set;
* the whole ``knn_integrate`` (distances, selection, weights, the per-candidate sums and the
  gather of 32 feature floats): the ``top_k`` path (the reference) against the path
  :data:`~ne_jax.geometry.knn.RANK_MAX_CANDIDATES` picks, and the largest difference of the results.

Writes ``experiments/results/bench_knn.{json,md}`` and prints the table.
"""

from __future__ import annotations

import argparse
import os
import platform
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"

SETTINGS = (("tiny / default", 32, 16, 6), ("paper", 96, 32, 22))  # (presets, candidates, K, samples)


def _inputs(kc: int, k: int, samples: int, segments: int):
    import jax
    import jax.numpy as jnp
    import numpy as np

    from ne_jax.benchmark import scenes as S
    from ne_jax.geometry.kdtree import KDTreeConfig, build_tree
    from ne_jax.geometry.points import PointState

    smp = S.surface_samples(S.get_scene("glossy", 1.0), 100_000, seed=0)
    pts = PointState.from_numpy(smp["xyz"].astype(np.float32), feature_dim=32)
    pts = pts.replace(feature=jax.random.normal(jax.random.key(0), pts.feature.shape))
    cfg = KDTreeConfig(candidate_min=kc, knn_k=k, num_render_levels=2 if kc <= 32 else 4)
    tree = build_tree(np.asarray(pts.xyz), np.asarray(pts.alive), cfg)
    rng = np.random.default_rng(0)
    r0 = 2 ** (tree.depth - cfg.num_render_levels) - 1  # segments in voxels of the rendering levels
    node = rng.integers(r0, 2**tree.depth - 1, segments)
    node = node[np.asarray(tree.valid)[node]]
    lo, hi = np.asarray(tree.lo)[node], np.asarray(tree.hi)[node]
    x = lo[:, None] + rng.random((node.size, samples, 3)) * (hi - lo)[:, None]
    w = rng.random((node.size, samples)).astype(np.float32)
    return pts, tree, cfg, jnp.asarray(x, jnp.float32), jnp.asarray(node, jnp.int32), jnp.asarray(w)


def measure(kc: int, k: int, samples: int, segments: int, repeats: int) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax import lax

    from experiments.common import best_time
    from ne_jax.geometry import knn as K
    from ne_jax.numerics import stable_ranks

    pts, tree, cfg, x, node, w = _inputs(kc, k, samples, segments)
    _, ok, d2 = jax.jit(K._candidate_distances)(pts, tree, x, node)
    key = jnp.where(ok[:, None, :], d2, jnp.inf)

    def by_top_k(key):
        _, j = lax.top_k(-key, k)
        return jnp.zeros(key.shape, bool).at[jnp.arange(key.shape[0])[:, None, None],
                                             jnp.arange(key.shape[1])[None, :, None], j].set(True)

    def by_rank(key):
        return stable_ranks(key) < k

    sel_t, sel_r = jax.jit(by_top_k), jax.jit(by_rank)
    t_top, t_rank = best_time(lambda: sel_t(key), repeats)[1], best_time(lambda: sel_r(key), repeats)[1]
    same = bool(np.array_equal(np.asarray(sel_t(key)), np.asarray(sel_r(key))))
    eps = (cfg.knn_eps_factor * tree.spacing).astype(jnp.float32)
    values = {"feature": pts.feature}

    def integrate_top_k(p, x, node, w):  # the top_k path: chosen slots, then a scatter per candidate
        pc, ci = K._per_candidate_weights_top_k(p, tree, x, node, w, k, eps)
        return jnp.einsum("bc,bcd->bd", pc, p.feature[ci])

    ref = jax.jit(integrate_top_k)
    new = jax.jit(lambda p, x, node, w: K.knn_integrate(p, tree, x, node, w, values, cfg)["feature"])
    t_ref = best_time(lambda: ref(pts, x, node, w), repeats)[1]
    t_new = best_time(lambda: new(pts, x, node, w), repeats)[1]
    diff = float(jnp.max(jnp.abs(ref(pts, x, node, w) - new(pts, x, node, w))))
    return {"candidates": kc, "k": k, "samples": samples, "segments": int(node.shape[0]),
            "select_top_k_ms": 1e3 * t_top, "select_rank_ms": 1e3 * t_rank, "same_choice": same,
            "integrate_top_k_ms": 1e3 * t_ref, "integrate_ms": 1e3 * t_new,
            "integrate_path": "rank" if kc <= K.RANK_MAX_CANDIDATES else "top_k", "max_abs_diff": diff}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--segments", type=int, default=16384)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)

    import jax

    from ne_jax import provenance
    from ne_jax.atomic import atomic_write_json, atomic_write_text

    rows = []
    for presets, kc, k, s in SETTINGS:
        row = {"presets": presets, **measure(kc, k, s, args.segments, args.repeats)}
        print(row, flush=True)
        rows.append(row)
    command = f"python -m experiments.bench_knn --segments {args.segments} --repeats {args.repeats}"
    report = {"what": "KNN selection by ranking against lax.top_k, alone and in knn_integrate",
              "commit": provenance.commit(), "worktree_modified": provenance.modified(), "command": command,
              "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(),
                          "device": jax.devices()[0].platform, "jax": jax.__version__,
                          "load_before": round(os.getloadavg()[0], 2)},
              "rows": rows}
    RESULTS.mkdir(exist_ok=True)
    atomic_write_json(RESULTS / "bench_knn.json", report)
    lines = [f"KNN selection, {jax.devices()[0].platform} ({os.cpu_count()} cores, JAX {jax.__version__}), "
             f"commit {report['commit'][:12]}{' (work tree modified)' if report['worktree_modified'] else ''}; "
             f"re-run: `{command}`.", "",
             "| presets | K of candidates | samples | segments | select: top_k ms | select: rank ms | rank / top_k "
             "| same set | integrate: top_k path ms | integrate ms (path) | speed-up | max abs diff |",
             "|---|---|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(
            f"| {r['presets']} | {r['k']} of {r['candidates']} | {r['samples']} | {r['segments']} | "
            f"{r['select_top_k_ms']:.1f} | {r['select_rank_ms']:.1f} | "
            f"{r['select_rank_ms'] / r['select_top_k_ms']:.2f}x | "
            f"{'yes' if r['same_choice'] else 'no'} | {r['integrate_top_k_ms']:.1f} | "
            f"{r['integrate_ms']:.1f} ({r['integrate_path']}) | {r['integrate_top_k_ms'] / r['integrate_ms']:.2f}x | "
            f"{r['max_abs_diff']:.1e} |")
    atomic_write_text(RESULTS / "bench_knn.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    main()
