"""Looking at a model and editing it in the browser (``ne-jax view RUN``; see docs/viewer.md).

* :mod:`ne_jax.view.edits`: the edit logic as pure functions (selection by region or screen rectangle,
  gizmo transforms, deletion, the indexed PLY and the edited run directory);
* :mod:`ne_jax.view.frames`: browser cameras, renders and render modes as images;
* :class:`Viewer` (:mod:`ne_jax.view.viewer`, needs the ``view`` extra: viser): the web viewer.
"""

from __future__ import annotations

from ne_jax.view.edits import Region, SelectionError, Transform, ViewEdit, save_view_edit, write_edit_ply


def __getattr__(name):
    if name in ("Viewer", "ViewerError"):  # viser is imported only when the viewer is asked for
        from ne_jax.view import viewer

        return getattr(viewer, name)
    raise AttributeError(f"module 'ne_jax.view' has no attribute {name!r}")


__all__ = ["Region", "SelectionError", "Transform", "ViewEdit", "Viewer", "ViewerError", "save_view_edit",
           "write_edit_ply"]
