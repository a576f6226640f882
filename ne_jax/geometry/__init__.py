"""Geometry core: the point state, the flattened K-D tree, ray traversal and KNN interpolation."""

from ne_jax.geometry.capacity import Capacities, Lost, LostCounts, fit_packing, grow
from ne_jax.geometry.intersect import Segments, intersect, intersect_checked, slab_intersect
from ne_jax.geometry.kdtree import KDTree, KDTreeConfig, build_tree, tree_depth
from ne_jax.geometry.knn import Neighbors, interpolate, knn_interpolate, knn_neighbors, knn_weights
from ne_jax.geometry.points import PointState

__all__ = [
    "Capacities",
    "Lost",
    "LostCounts",
    "KDTree",
    "KDTreeConfig",
    "Neighbors",
    "PointState",
    "Segments",
    "build_tree",
    "fit_packing",
    "grow",
    "interpolate",
    "intersect",
    "intersect_checked",
    "knn_interpolate",
    "knn_neighbors",
    "knn_weights",
    "slab_intersect",
    "tree_depth",
]
