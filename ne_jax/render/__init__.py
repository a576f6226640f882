"""Rendering pieces that need no K-D tree: quadrature, the IDE, the colour model, compositing."""
