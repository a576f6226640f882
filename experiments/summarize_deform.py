"""The deformation benchmark's zero-shot (and fine-tuned) PSNR by kind of edit: the mean over the
scenes of each kind (smooth deformation, rigid part, cut, deletion, the two whole-scene turns) per
variant, with the mean SSIM and LPIPS over every edit.

    python -m experiments.summarize_deform experiments/results/deform_benchmark_tiny.json

Writes ``<stem>_by_kind.md`` next to the input.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ne_jax.atomic import atomic_write_text

KINDS = {
    "smooth deformation": ("twist", "bend"),
    "rigid part": ("tilt_seat", "turn_handle", "roll_ball", "tilt_ring"),
    "cut": ("cut",),
    "deletion": ("delete_leg", "delete_handle", "delete_ball", "delete_cube"),
    "turn, co-moving": ("turn_with_light",),
    "turn, fixed": ("turn_scene",),
}
"""Each benchmark edit by kind (``ne_jax.benchmark.scenes``: one edit of each kind per scene)."""


def kind_of(edit: str) -> str:
    for kind, names in KINDS.items():
        if edit in names:
            return kind
    raise KeyError(f"summarize_deform: edit {edit!r} has no kind; expected one of {sorted(sum(KINDS.values(), ()))}")


def by_kind(records: list[dict], stage: str = "zero_shot") -> str:
    """A Markdown table: one row per variant, the mean PSNR of each kind of edit over the scenes,
    the mean over every edit, and the mean SSIM and LPIPS."""
    variants = list(dict.fromkeys(r["variant"] for r in records))
    kinds = [k for k in KINDS if any(kind_of(r["edit"]) == k for r in records)]
    lines = ["| variant | " + " | ".join(kinds) + " | mean | SSIM | LPIPS |",
             "|---|" + "---:|" * (len(kinds) + 3)]
    for v in variants:
        rows = [r[stage] for r in records if r["variant"] == v and stage in r]
        if not rows:
            continue
        cells = []
        for k in kinds:
            vals = [r[stage]["psnr"] for r in records if r["variant"] == v and kind_of(r["edit"]) == k and stage in r]
            cells.append(f"{np.mean(vals):.2f}" if vals else "")
        lp = [x["lpips"] for x in rows if x.get("lpips") is not None]
        cells += [f"{np.mean([x['psnr'] for x in rows]):.2f}", f"{np.mean([x['ssim'] for x in rows]):.3f}",
                  f"{np.mean(lp):.3f}" if lp else ""]
        lines.append(f"| {v} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", type=Path, help="a deform_benchmark_<preset>.json")
    args = parser.parse_args(argv)
    data = json.loads(args.results.read_text(encoding="utf-8"))
    unedited = data.get("unedited", {})
    parts = [f"Deformation benchmark by kind of edit, preset `{data['preset']}`, commit {data['commit']} "
             f"(from `{args.results.name}`; re-run: `python -m experiments.summarize_deform {args.results.name}`). "
             "PSNR in dB, the mean over the scenes of each kind.", "", "**Zero-shot**", "",
             by_kind(data["records"])]
    if any("finetune" in r for r in data["records"]):
        parts += ["", "**Fine-tuned**", "", by_kind(data["records"], "finetune")]
    if unedited:
        mean = np.mean([u["psnr"] for u in unedited.values()])
        parts += ["", f"The unedited models score {mean:.2f} dB on their own test views (mean of "
                      f"{len(unedited)} scenes)."]
    out = args.results.with_name(args.results.stem + "_by_kind.md")
    atomic_write_text(out, "\n".join(parts) + "\n")
    print(out.read_text(encoding="utf-8"))


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    main()
