"""Pictures a person would rather look at than read: contact sheets of scenes and edits."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ne_jax.data.nerf_synthetic import composite, load_split, parse_background


def contact_sheet(root, out_png, view: int | None = None, split: str = "test", background="white", title=None) -> Path:
    """One row per benchmark scene under ``root``, one column per variant (original, then edits),
    each cell view ``view`` of ``split`` (default: the one an eighth of the way round the test orbit,
    45 degrees off the x axis) composited on ``background``. Writes ``out_png``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ne_jax.benchmark.generate import list_variants

    variants = list_variants(root)
    if not variants:
        raise FileNotFoundError(f"contact_sheet: no benchmark scenes (folders with scene.json) under {root}")
    scenes = list(dict.fromkeys(s for s, _, _ in variants))
    rows = {s: [(e, d) for s2, e, d in variants if s2 == s] for s in scenes}
    cols = max(len(r) for r in rows.values())
    bg = parse_background(background)
    fig, axes = plt.subplots(len(scenes), cols, figsize=(1.9 * cols, 2.0 * len(scenes)), squeeze=False)
    for i, scene in enumerate(scenes):
        for j in range(cols):
            ax = axes[i, j]
            ax.axis("off")
            if j >= len(rows[scene]):
                continue
            edit, directory = rows[scene][j]
            images = load_split(directory, split).images
            rgba = images[len(images) // 8 if view is None else view]
            ax.imshow(np.clip(composite(rgba, bg), 0, 1), interpolation="nearest")
            ax.set_title(edit or "original", fontsize=9)
            if j == 0:
                ax.text(-0.08, 0.5, scene, transform=ax.transAxes, rotation=90, va="center", ha="right", fontsize=10)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_png.with_name(out_png.name + ".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(out_png)
    return out_png
