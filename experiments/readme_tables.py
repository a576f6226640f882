"""The README's results tables, one per preset, written from the results files so they cannot drift.

    python -m experiments.readme_tables           # rewrite the tables between their markers in README.md
    python -m experiments.readme_tables --check   # exit 1 (and say which) when README.md's differ

Each table sits between ``<!-- table:NAME -->`` and ``<!-- /table:NAME -->`` in README.md;
:data:`TABLES` names the function that writes it from ``experiments/results/``. The results files
keep the provenance (commit, config key, command); the README keeps none.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

from experiments.common import RESULTS, ROOT, entry

README = ROOT / "README.md"


def _load(stem: str, results: Path) -> dict:
    return json.loads((results / f"{stem}.json").read_text())


def _mean(xs: list[float]) -> str:
    return f"**{sum(xs) / len(xs):.2f}**" if xs else ""


def _rows(rc: dict, pt: dict, label: str) -> list[str]:
    """A table's rows of one scene set: each scene's ray-cast and path-traced PSNR, SSIM and training
    time, then the set's mean (``label``)."""
    lines = []
    for name in {**rc, **pt}:
        cells = []
        for r in (rc.get(name), pt.get(name)):
            cells += ([f"{r['test_psnr']:.2f}", f"{r['test_ssim']:.3f}", f"{r['train_seconds']:.0f}"] if r
                      else ["", "", ""])
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines.append(f"| {label} | {_mean([r['test_psnr'] for r in rc.values()])} | | | "
                 f"{_mean([p['test_psnr'] for p in pt.values()])} | | |")
    return lines


def tiny(results: Path = RESULTS) -> str:
    """``train_benchmark_tiny`` and ``_tiny_pt``: test PSNR, SSIM and training time per scene; below
    them the held-out scenes (``train_benchmark_tiny_heldout``, ``_tiny_pt_heldout``), where measured."""
    rc, pt = (_load(s, results)["scenes"] for s in ("train_benchmark_tiny", "train_benchmark_tiny_pt"))
    lines = ["| scene | ray-cast PSNR (dB) | SSIM | train time (s) | path-traced PSNR (dB) | SSIM | train time (s) |",
             "|---|---:|---:|---:|---:|---:|---:|", *_rows(rc, pt, "mean")]
    held = [_load(s, results)["scenes"] if (results / f"{s}.json").is_file() else {}
            for s in ("train_benchmark_tiny_heldout", "train_benchmark_tiny_pt_heldout")]
    if any(held):
        lines += ["| *held out* | | | | | | |", *_rows(*held, "held-out mean")]
    return "\n".join(lines)


def _grid_psnr(stem: str, results: Path) -> dict[str, float]:
    """Per scene, the test PSNR at 2 x 2 rays per pixel (the ``default`` preset's images)."""
    return {run["name"].split("_")[-1]: next(r["psnr"] for r in run["rows"] if r["pixel_samples"] == 2)
            for run in _load(stem, results)["runs"]}


def default(results: Path = RESULTS) -> str:
    """``train_benchmark_default`` and ``_default_pt`` (one ray per pixel: PSNR, SSIM, training time) and
    the same models' test views at 2 x 2 rays per pixel (``pixel_grid_default_{rc,pt}_all``); below
    them the held-out scenes (``train_benchmark_default_heldout``: test images at 2 x 2), where measured."""
    rc, pt = (_load(s, results)["scenes"] for s in ("train_benchmark_default", "train_benchmark_default_pt"))
    grid = {kind: _grid_psnr(f"pixel_grid_default_{kind}_all", results) for kind in ("rc", "pt")}
    lines = ["| scene | ray-cast PSNR (dB) | one ray | SSIM (one ray) | train time (s) "
             "| path-traced PSNR (dB) | one ray | SSIM (one ray) | train time (s) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name in rc:
        cells = []
        for kind, runs in (("rc", rc), ("pt", pt)):
            r = runs.get(name)
            cells += [f"{grid[kind][name]:.2f}", f"{r['test_psnr']:.2f}", f"{r['test_ssim']:.3f}",
                      f"{r['train_seconds']:.0f}"] if r else ["", "", "", ""]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    means = []
    for kind, runs in (("rc", rc), ("pt", pt)):
        means += [f"{_mean([grid[kind][n] for n in runs])} ({len(runs)} scenes)",
                  f"{sum(r['test_psnr'] for r in runs.values()) / len(runs):.2f}", "", ""]
    lines.append("| mean | " + " | ".join(means) + " |")
    if (results / "train_benchmark_default_heldout.json").is_file():  # the preset as it is: 2 x 2 test images
        held = _load("train_benchmark_default_heldout", results)["scenes"]
        lines += ["| *held out* | | | | | | | | |",
                  *(f"| {n} | {r['test_psnr']:.2f} | | | {r['train_seconds']:.0f} | | | | |" for n, r in held.items()),
                  f"| held-out mean | {_mean([r['test_psnr'] for r in held.values()])} ({len(held)} scenes) "
                  "| | | | | | | |"]
    return "\n".join(lines)


TABLES = {"tiny": tiny, "default": default}
"""Table name -> the function that writes it (from a results folder)."""


def render(text: str, results: Path = RESULTS) -> str:
    """``text`` (a README) with every marked table written again from ``results``."""
    for name, make in TABLES.items():
        pattern = re.compile(rf"(<!-- table:{name} -->\n)(?:.*?\n)?(<!-- /table:{name} -->)", re.S)
        if not pattern.search(text):
            raise ValueError(f"README: expected the markers <!-- table:{name} --> ... <!-- /table:{name} -->, "
                             "found none")
        table = make(results)
        text = pattern.sub(lambda m, table=table: m.group(1) + table + "\n" + m.group(2), text)
    return text


def main(argv=None) -> int:
    args = sys.argv[1:] if argv is None else argv
    text = README.read_text()
    new = render(text)
    if "--check" in args:
        if new != text:
            print("README.md: the results tables differ from the results files; run "
                  "python -m experiments.readme_tables", file=sys.stderr)
            return 1
        return 0
    README.write_text(new)
    return 0


if __name__ == "__main__":
    entry(main, huge_pages=False)  # this one starts no JAX
