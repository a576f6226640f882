"""Shared fixtures of the training tests: ``world``, the tiny generated scene of ``test_step.py``
(points, tree, ray pool and the compiled step), built once per requesting module."""

from .test_step import world  # noqa: F401
