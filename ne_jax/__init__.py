"""ne_jax: a functional JAX reimplementation of NeuralEditor (CVPR 2023).

A scene is a point cloud with per-point features and confidences; rendering walks each ray through
K-D-tree voxels and integrates KNN-interpolated features; editing moves indexed points.
Sub-packages follow the data flow: ``data`` (cameras, rays, scenes) -> ``geometry`` (points, K-D
tree, traversal, KNN) -> ``render`` -> ``train`` -> ``edit``.

Importing ``ne_jax`` changes nothing in the process: JAX keeps its defaults (one CPU device). A
script or notebook that wants what the ``ne-jax`` command line gets (one host device per usable
CPU core, so the ray mesh of :mod:`ne_jax.devices` uses every core) calls :func:`setup` before any
JAX code runs::

    import ne_jax

    ne_jax.setup()  # or ne_jax.setup(host_devices=4); ne_jax.setup(huge_pages=True) in a script
"""

from ne_jax._platform import setup

__version__ = "0.1.0"

__all__ = ["setup"]
