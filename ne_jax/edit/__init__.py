"""Editing: indexed point-cloud edits ``P -> Q(P)`` and the infinitesimal surface transformation."""
