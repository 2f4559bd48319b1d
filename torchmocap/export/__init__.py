"""Exports for other tools: an animated glTF 2.0 binary (``.glb``) of a skinned body following a
track, which opens in Blender and in web viewers.

A package of its own (rather than part of :mod:`torchmocap.body` or :mod:`torchmocap.io`)
because it combines both: a body mesh bound to a skeleton, and a file format. It depends only
on ``body``, ``skeleton`` and ``geometry``.
"""

from torchmocap.export.gltf import Z_UP_TO_Y_UP, gltf_document, read_accessor, read_glb, write_glb
from torchmocap.export.skins import MeshSkin, skin_from_body, stick_figure_skin

__all__ = [
    "Z_UP_TO_Y_UP",
    "MeshSkin",
    "gltf_document",
    "read_accessor",
    "read_glb",
    "skin_from_body",
    "stick_figure_skin",
    "write_glb",
]
