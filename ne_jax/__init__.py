"""ne_jax: a functional JAX reimplementation of NeuralEditor (CVPR 2023).

A scene is a point cloud with per-point features and confidences; rendering walks each ray through
K-D-tree voxels and integrates KNN-interpolated features; editing moves indexed points.
Sub-packages follow the data flow: ``data`` (cameras, rays, scenes) -> ``geometry`` (points, K-D
tree, traversal, KNN) -> ``render`` -> ``train`` -> ``edit``.

Importing ``ne_jax`` gives JAX one host device per usable CPU core (on the CPU platform only, and
only where no device count was given to JAX itself), so the ray mesh of :mod:`ne_jax.devices` uses
every core; ``NE_JAX_HOST_DEVICES=1`` opts out (:mod:`ne_jax._platform`).
"""

from ne_jax._host_memory import reexec_entry_point as _reexec_entry_point

_reexec_entry_point()  # `ne-jax`, `python -m ne_jax.<name>` / `experiments.<name>`: start again with huge pages

from ne_jax._platform import configure_host_devices as _configure_host_devices  # noqa: E402

_configure_host_devices()

__version__ = "0.1.0"
