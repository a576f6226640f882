"""Generate the procedural editing benchmark and measure how long each preset takes.

    python -m experiments.make_benchmark                      # tiny and default presets
    python -m experiments.make_benchmark --presets tiny       # just tiny
    python -m experiments.make_benchmark --preset tiny_pt --out DIR   # the path-traced tiny set (Mitsuba 3)
    python -m experiments.make_benchmark --preset tiny_capture --out DIR   # the same as captures (COLMAP, nerfstudio)
    python -m experiments.make_benchmark --preset default_pt --out DIR --scenes glossy cup --originals-only --resume
                                                              # two unedited scenes, continuing a stopped run

Writes the scenes to ``--out/<preset>/`` (a scene asked for replaces its folder once complete; the
others there are kept), each preset's contact sheet (``benchmark_contact_sheet_<preset>.png``) and the
timings (``make_benchmark.json``) to ``experiments/results``, and prints a table (docs/benchmark.md).
``--resume`` keeps the finished scenes asked for too and continues a stopped one from its last image.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from experiments.common import RESULTS, entry, machine
from ne_jax.benchmark.generate import PRESETS, generate_benchmark, get_preset, list_variants
from ne_jax.provenance import commit
from ne_jax.viz import contact_sheet


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--presets", "--preset", nargs="+", default=["tiny", "default"],
                        help=f"presets to generate, of {sorted(PRESETS)} (default: tiny default)")
    parser.add_argument("--out", default="outputs/benchmark", help="each preset goes to OUT/<preset>/")
    parser.add_argument("--scenes", nargs="+", default=None, help="only these scenes (default: all)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--originals-only", action="store_true",
                        help="only the unedited scenes, none of their edits (training needs no more)")
    parser.add_argument("--resume", action="store_true",
                        help="keep OUT/<preset>/: skip its finished scenes, continue a stopped one from its last image")
    args = parser.parse_args(argv)

    for name in args.presets:
        if name not in PRESETS:
            parser.error(f"--presets: unknown preset {name!r}; expected one of {sorted(PRESETS)}")
    rows = {}
    started_at = commit()  # the code that generates (HEAD may move during a long generation)
    for name in args.presets:
        preset = get_preset(name)
        root = Path(args.out) / name
        report = generate_benchmark(root, preset, args.scenes, seed=args.seed,
                                    edits=() if args.originals_only else None, resume=args.resume)
        n_scenes = len(report["scenes"])
        n_edits = sum(edit is not None and scene in report["scenes"]  # over the scenes asked for
                      for scene, edit, _ in list_variants(root))
        edit_train = preset.train_views if preset.edit_train_views is None else preset.edit_train_views
        images = (n_scenes * (preset.train_views + preset.val_views + preset.test_views)
                  + n_edits * (edit_train + preset.test_views))
        sheet = contact_sheet(root, RESULTS / f"benchmark_contact_sheet_{name}.png",
                              title=f"ne_jax procedural benchmark, preset {name!r} (test view at 45 degrees)")
        size = sum(p.stat().st_size for scene in report["scenes"] for p in (root / scene).rglob("*") if p.is_file())
        rows[name] = {
            "resolution": preset.resolution, "supersample": preset.supersample, "renderer": preset.renderer,
            "spp": preset.spp if preset.renderer == "pathtrace" else None, "scenes": n_scenes,
            "variants_per_scene": 1 + n_edits // n_scenes, "images": images, "seconds": round(report["seconds"], 2),
            "ms_per_image": round(1000 * report["seconds"] / images, 1), "megabytes": round(size / 2**20, 1),
            "per_scene_seconds": {k: round(v["total"], 2) for k, v in report["scenes"].items()},
            "contact_sheet": str(sheet.relative_to(RESULTS.parent.parent)), "seed": args.seed, "commit": started_at,
            "command": "python -m experiments.make_benchmark --presets " + name
                       + (f" --scenes {' '.join(args.scenes)}" if args.scenes else "")
                       + (f" --seed {args.seed}" if args.seed else "")
                       + (" --originals-only" if args.originals_only else "") + (" --resume" if args.resume else ""),
        }
        print(f"benchmark[{name}]: {images} images in {report['seconds']:.1f} s "
              f"({1000 * report['seconds'] / images:.0f} ms per image) -> {root}", flush=True)
    out, host = RESULTS / "make_benchmark.json", machine(python=True, loadavg=[round(x, 2) for x in os.getloadavg()])
    previous = json.loads(out.read_text()) if out.exists() else {}
    previous.setdefault("presets", {}).update(rows)
    out.write_text(json.dumps({**previous, "machine": host}, indent=2) + "\n")

    print("\n| preset | resolution | samples / pixel | scenes x variants | images | time | per image | size |")
    print("|---|---|---|---|---|---|---|---|")
    for name, r in rows.items():
        samples = f"{r['spp']} spp" if r["renderer"] == "pathtrace" else f"{r['supersample']}x{r['supersample']}"
        print(f"| {name} | {r['resolution']}x{r['resolution']} | {samples} | "
              f"{r['scenes']} x {r['variants_per_scene']} | {r['images']} | {r['seconds']:.1f} s | "
              f"{r['ms_per_image']:.0f} ms | {r['megabytes']:.0f} MB |")
    print(f"\nmachine: {host}; results in {out}")


if __name__ == "__main__":
    entry(main)
