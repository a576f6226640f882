"""The procedural editing benchmark: scenes made the way the paper's were (build a mesh, render it
from many views, edit the mesh, render again as ground truth), and the method's variants scored on it.

============  ====================================================================================
meshes        triangle meshes: lathes, boxes, tubes, built pre-cut where a scene's edit cuts
scenes        the four scenes (materials, textures, parts) and their edits by name
raycaster     the ground-truth renderer (Blinn-Phong ray caster with shadows and a sky reflection)
generate      writing a preset of scenes and their edited ground truth to disk (NeRF Synthetic layout)
capture       the capture variant: environment visible, a ground, COLMAP and nerfstudio layouts, SfM points
edits         a scene's edits by name, looked up from the folder a model was trained on
variants      the method's variants and ablations (the rows of the deformation benchmark)
============  ====================================================================================

It sits above the library (it imports ``data``, ``edit``, ``render`` and ``train``; nothing below
imports it): the cameras it renders from live in :mod:`ne_jax.data.cameras`.
"""
