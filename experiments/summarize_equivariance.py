"""One table from several ``experiments/equivariance.py`` results files: every model's PSNR per
motion, with the tree carried and rebuilt, and the worst rigid motion per model.

    python -m experiments.summarize_equivariance experiments/results/equivariance_*.json --out equivariance

Writes ``experiments/results/<out>.md`` (the sources' commits and commands are listed under it).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ne_jax.atomic import atomic_write_text

RESULTS = Path(__file__).resolve().parent / "results"


def summary(sources: list[Path]) -> str:
    models, notes = [], []
    for path in sources:
        data = json.loads(path.read_text(encoding="utf-8"))
        models += data["models"]
        notes.append(f"- `{path.name}`: commit {data['commit']}, `{data['command']}`")
    names = [f"{Path(m['scene_dir']).name} ({m['preset']})" for m in models]
    lines = ["PSNR (dB) between the edited model seen from moved test cameras and the unedited model "
             "(120 = identical renders); each cell: tree carried / tree rebuilt (paper).", "",
             "| motion | " + " | ".join(names) + " |", "|---|" + "---:|" * len(models)]
    for i, row in enumerate(models[0]["motions"]):
        cells = [f"{m['motions'][i]['carry']:.1f} / {m['motions'][i]['rebuild']:.1f}" for m in models]
        lines.append(f"| {row['motion']} | " + " | ".join(cells) + " |")
    worst = []
    for m in models:
        rigid = [r for r in m["motions"] if r["kind"] == "rigid"]
        worst.append(f"{min(r['carry'] for r in rigid):.1f} / {min(r['rebuild'] for r in rigid):.1f}")
    lines += ["| **worst rigid motion** | " + " | ".join(worst) + " |", "",
              "Models: " + "; ".join(f"{Path(m['scene_dir']).name}: {m['points']} points, {m['views']} test views"
                                     for m in models)
              + ".", "", "Sources:", *notes, ""]
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sources", nargs="+", type=Path, help="equivariance results (.json)")
    parser.add_argument("--out", default="equivariance", help="results file stem")
    args = parser.parse_args(argv)
    text = summary(args.sources)
    atomic_write_text(RESULTS / f"{args.out}.md", text)
    print(text)


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    main()
