"""ne_jax: a functional JAX reimplementation of NeuralEditor (CVPR 2023).

A scene is a point cloud with per-point features and confidences; rendering walks each ray through
K-D-tree voxels and integrates KNN-interpolated features; editing moves indexed points.
Sub-packages follow the data flow: ``data`` (cameras, rays, scenes) -> ``geometry`` (points, K-D
tree, traversal, KNN) -> ``render`` -> ``train`` -> ``edit``.
"""

__version__ = "0.1.0"
