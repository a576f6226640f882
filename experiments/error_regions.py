"""Where the error of trained models lives: each model's test views labelled by region
(:mod:`ne_jax.eval.regions`: silhouette, hole, see-through, highlight, texture, flat, background), the share of
the squared error and of the pixels per region, and one error-map row per model.

    python -m experiments.error_regions --run LABEL RUN_DIR SCENE_DIR [--run ...] --out error_regions_tiny

Writes ``experiments/results/<out>.{json,md,png}``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from experiments.common import commit as _commit
from ne_jax.atomic import atomic_write_json, atomic_write_text
from ne_jax.config_json import config_key
from ne_jax.data.nerf_synthetic import composite, load_split
from ne_jax.data.png import write_image
from ne_jax.eval import evaluate_model
from ne_jax.eval.regions import REGIONS, error_map_picture, split_regions
from ne_jax.train.model import load_trained

RESULTS = Path(__file__).resolve().parent / "results"


def measure(label: str, run_dir: Path, scene_dir: Path, view: int) -> tuple[dict, np.ndarray]:
    """Score one model's test views by region; ``(record, error-map row of test view`` ``view``)."""
    model = load_trained(run_dir)
    split = load_split(scene_dir, "test")
    report, images, depths = evaluate_model(model, split, progress=False, with_depth=True)
    regions, labels = split_regions(split, images, model.background, depths=depths)
    truth = composite(split.images, report["background"])
    record = {"label": label, "run": str(run_dir), "scene_dir": str(scene_dir), "config_key": config_key(model.run),
              "psnr": round(report["psnr"], 2), "ssim": round(report["ssim"], 4), "regions": regions}
    return record, error_map_picture(truth[view], images[view], labels[view])


def table(records: list[dict]) -> str:
    head = "| model | PSNR | " + " | ".join(REGIONS) + " |\n|---|---:|" + "---:|" * len(REGIONS) + "\n"
    rows = []
    for r in records:
        cells = []
        for name in REGIONS:
            g = r["regions"][name]
            cells.append(f"{100 * g['error']:.0f}% ({100 * g['pixels']:.0f}%)" if g["pixels"] else "-")
        rows.append(f"| {r['label']} | {r['psnr']:.2f} | " + " | ".join(cells) + " |")
    return head + "\n".join(rows) + "\n"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", nargs=3, action="append", required=True, metavar=("LABEL", "RUN_DIR", "SCENE_DIR"),
                        help="a model, its run directory and the scene folder of its test views (repeatable)")
    parser.add_argument("--view", type=int, default=0, help="the test view shown in the picture")
    parser.add_argument("--out", default="error_regions", help="results file stem")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    records, rows = [], []
    for label, run_dir, scene_dir in args.run:
        record, row = measure(label, Path(run_dir), Path(scene_dir), args.view)
        records.append(record)
        rows.append(np.repeat(np.repeat(row, 2, axis=0), 2, axis=1))
        print(f"{label}: PSNR {record['psnr']:.2f} dB; error by region " + ", ".join(
            f"{k} {100 * v['error']:.0f}%" for k, v in record["regions"].items()), flush=True)
    command = "python -m experiments.error_regions " + " ".join(
        f"--run {label} {run} {scene}" for label, run, scene in args.run) + f" --view {args.view} --out {args.out}"
    report = {"what": "squared error of the test views by region (ne_jax.eval.regions)", "commit": _commit(),
              "command": command, "seconds": round(time.perf_counter() - t0, 1), "models": records}
    RESULTS.mkdir(exist_ok=True)
    atomic_write_json(RESULTS / f"{args.out}.json", report)
    text = (f"Share of the squared error (share of the pixels) by region, test views; commit {report['commit']}; "
            f"`{command}`. Picture: test view {args.view} of each model as ground truth | render | error x4 | "
            f"regions (`{args.out}.png`).\n\n" + table(records))
    atomic_write_text(RESULTS / f"{args.out}.md", text)
    write_image(RESULTS / f"{args.out}.png", np.concatenate(rows, axis=0))
    print(text)


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    main()
