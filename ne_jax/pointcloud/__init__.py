"""Point clouds on the host: initial clouds (carving, PLY, benchmark ground truth), normals, accuracy.

See :mod:`ne_jax.pointcloud.init`, :mod:`ne_jax.pointcloud.normals`, :mod:`ne_jax.pointcloud.metrics`,
:mod:`ne_jax.pointcloud.neighbors` (PCA normals and statistical outliers, by Open3D or scipy).
"""
