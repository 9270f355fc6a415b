"""Synthetic wound captures with exact truth for every frame.

A procedural wound on a curved body surface (a tapered limb or a gently curved torso patch)
is ray-cast from a hand-held-like camera path (layout "one-sided"), or a wound wrapped around a
limb is filmed in one turn around it (layout "all-around"). Class labels, albedo and relief are
functions of the surface parameters (u, v), so every view agrees on the class of a surface
point, and colour and truth of a pixel come from the same ray hit. Writes::

    OUT/capture/   images/, transforms.json, annotations/ (a few frames), predictions/ (all)
    OUT/truth/     <stem>.png (class ids), depth/<stem>.npy (ray distance), scene.json

Predictions imitate a good but imperfect 2D segmenter whose errors differ from view to view,
so that a multi-view method has something to fix.

The parts: ``config`` (``SynthConfig``, ``SynthResult``, the class ids), ``textures``
(procedural noise, texture sampling, skin marks), ``scene`` (the one-sided scene and its
rendering), ``around`` (the all-around scene), ``shading`` (background, vignette,
Blinn-Phong), ``paths`` (camera paths, with the distance and zoom changes), ``camera`` (what a
phone does to the image: exposure and white-balance drift, blur, noise), ``layouts`` (scene + path + lights of a layout, the
random streams, ``SynthScene``), ``predictions`` (the imitation segmenter's errors) and
``writer`` (``synthesize``: the per-frame stages and the files).
"""

from .around import AroundScene
from .config import LAYOUTS, PHONE, SynthConfig, SynthResult
from .layouts import SynthScene, build_layout
from .predictions import predict_errors
from .scene import OneSidedScene
from .shading import background_image
from .writer import SynthFrame, annotated_indices, render_frame, synthesize

__all__ = [
    "LAYOUTS",
    "PHONE",
    "AroundScene",
    "OneSidedScene",
    "SynthConfig",
    "SynthFrame",
    "SynthResult",
    "SynthScene",
    "annotated_indices",
    "background_image",
    "build_layout",
    "predict_errors",
    "render_frame",
    "synthesize",
]
