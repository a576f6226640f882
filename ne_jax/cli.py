"""The ``ne-jax`` command line: thin wrappers over library functions.

Sub-commands:
  demo            the main job on the built-in default scene set (tiny preset): generate the
                  procedural benchmark, write its images and a contact sheet
  make-benchmark  generate the procedural editing benchmark for a preset
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def _cmd_make_benchmark(args) -> int:
    from ne_jax.data.benchmark import generate_benchmark
    from ne_jax.viz import contact_sheet

    report = generate_benchmark(args.out, args.preset, args.scenes, args.seed)
    sheet = contact_sheet(args.out, Path(args.out) / "contact_sheet.png",
                          title=f"ne_jax procedural benchmark, preset {args.preset!r} (test view at 45 degrees)")
    print(f"benchmark[{args.preset}]: {len(report['scenes'])} scenes in {report['seconds']:.1f} s -> {args.out}")
    print(f"contact sheet: {sheet}")
    return 0


def _cmd_demo(args) -> int:
    from ne_jax.data.benchmark import generate_benchmark
    from ne_jax.viz import contact_sheet

    out = Path(args.out)
    t0 = time.perf_counter()
    print(f"[1/2] generating the procedural benchmark (preset {args.preset!r}) in {out / 'benchmark'}")
    report = generate_benchmark(out / "benchmark", args.preset, None, args.seed)
    print(f"      {len(report['scenes'])} scenes x (original + 4 edits) in {report['seconds']:.1f} s")
    print("[2/2] writing the contact sheet")
    sheet = contact_sheet(out / "benchmark", out / "contact_sheet.png",
                          title=f"ne_jax procedural benchmark, preset {args.preset!r} (test view at 45 degrees)")
    print(f"done in {time.perf_counter() - t0:.1f} s")
    print(f"  scenes (NeRF Synthetic layout): {out / 'benchmark'}")
    print(f"  contact sheet:                  {sheet}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ne-jax", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="run the main job on the built-in default scenes")
    demo.add_argument("--out", default="outputs/demo", help="output folder (default: outputs/demo)")
    demo.add_argument("--preset", default="tiny", choices=["tiny", "default"], help="benchmark preset (default: tiny)")
    demo.add_argument("--seed", type=int, default=0)
    demo.set_defaults(func=_cmd_demo)

    mb = sub.add_parser("make-benchmark", help="generate the procedural editing benchmark")
    mb.add_argument("--preset", default="tiny", choices=["tiny", "default"])
    mb.add_argument("--out", required=True, help="output folder")
    mb.add_argument("--scenes", nargs="+", default=None, help="subset of scenes (default: all)")
    mb.add_argument("--seed", type=int, default=0)
    mb.set_defaults(func=_cmd_make_benchmark)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (KeyError, ValueError, FileNotFoundError) as e:  # user errors: one clear line, no traceback
        msg = e.args[0] if isinstance(e, KeyError) and e.args else e
        print(f"ne-jax {args.command}: error: {msg}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
