"""Speed and quality of the K-D-tree matching (:func:`ne_jax.morph.matching.kd_match`).

    python -m experiments.morph_matching_benchmark            # sizes 2^10 .. 2^20
    python -m experiments.morph_matching_benchmark --quick    # up to 2^16

Two clouds of different shapes (a unit cube's volume and a Gaussian blob) at each size ``N``:

* time of the vectorised matching, and of the obvious recursive NumPy reference (up to 2^14) — the
  ratio is the speed-up, and the two must give the same pairs;
* quality against the optimal assignment (``scipy.optimize.linear_sum_assignment`` on squared
  distances, up to 2^11): mean squared pair distance of the K-D matching over the optimum's (1 =
  optimal), and both times — what exactness would cost.

Writes ``experiments/results/morph_matching.{json,md}``.
"""

from __future__ import annotations

import argparse
import functools
import os
import platform
import time
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist

from ne_jax.atomic import atomic_write_json, atomic_write_text
from ne_jax.morph.matching import kd_match

from tests.morph.test_matching import reference_match  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def best_of(fn, repeats: int) -> tuple[float, object]:
    best, out = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    rng = np.random.default_rng(0)
    rows = []
    for e in range(10, 17 if args.quick else 21, 2):
        n = 2 ** e
        a, b = rng.random((n, 3)), 0.3 * rng.normal(size=(n, 3))
        t_kd, perm = best_of(functools.partial(kd_match, a, b), 3 if n <= 2 ** 16 else 1)
        row = {"n": n, "kd_seconds": round(t_kd, 4)}
        if n <= 2 ** 14:
            t_ref, ref = best_of(functools.partial(reference_match, a, b), 1)
            row.update(reference_seconds=round(t_ref, 4), speedup=round(t_ref / t_kd, 1),
                       same_pairs=bool(np.array_equal(ref, perm)))
        if n <= 2 ** 11:
            t_opt, (_, cols) = best_of(lambda a=a, b=b: linear_sum_assignment(cdist(a, b, "sqeuclidean")), 1)
            kd_cost = float(np.mean(np.sum((a - b[perm]) ** 2, axis=1)))
            opt_cost = float(np.mean(np.sum((a - b[cols]) ** 2, axis=1)))
            row.update(optimal_seconds=round(t_opt, 4), cost_over_optimal=round(kd_cost / opt_cost, 3))
        rows.append(row)
        print(row, flush=True)
    report = {"what": "K-D-tree matching of a unit cube's volume and a Gaussian blob (sigma 0.3), N points each",
              "rows": rows,
              "command": "python -m experiments.morph_matching_benchmark" + (" --quick" if args.quick else ""),
              "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()}}
    RESULTS.mkdir(exist_ok=True)
    atomic_write_json(RESULTS / "morph_matching.json", report)
    lines = [f"K-D matching, {report['what']}. Re-run: `{report['command']}`.", "",
             "| N | K-D matching (s) | recursive reference (s) | speed-up | same pairs | optimal assignment (s) | "
             "mean sq. distance / optimal |", "|---:|---:|---:|---:|---|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['n']} | {r['kd_seconds']} | {r.get('reference_seconds', '')} | {r.get('speedup', '')} | "
                     f"{r.get('same_pairs', '')} | {r.get('optimal_seconds', '')} | {r.get('cost_over_optimal', '')} |")
    atomic_write_text(RESULTS / "morph_matching.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    main()
