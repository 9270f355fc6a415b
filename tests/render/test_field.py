"""The saved field (conftest.tiny_expanded's field.pt) reloads and renders the masks it wrote,
also from a file saved before the outer background existed."""

from __future__ import annotations

import cv2
import pytest
import torch

from labelsynth.capture import load_capture
from labelsynth.render.field import SemanticField

# All tests using the shared tiny run go to one xdist worker, so it is fitted once.
pytestmark = pytest.mark.xdist_group("tiny_expanded")


def test_the_saved_field_re_renders_without_refitting(tiny_expanded):
    run = tiny_expanded
    cap = load_capture(run.capture_dir)
    sem = SemanticField.load(run.out / "field.pt", torch.device("cpu"))
    again = sem.render(cap.unit_cameras()[0]).mask
    saved = cv2.imread(str(run.out / "masks" / f"{cap.frames[0].name}.png"), cv2.IMREAD_UNCHANGED)
    assert (again == saved).mean() > 0.999


def test_a_field_saved_before_the_outer_background_still_loads(tiny_expanded, tmp_path):
    run = tiny_expanded
    state = torch.load(run.out / "field.pt", weights_only=False)
    state["sdf"] = {k: v for k, v in state["sdf"].items() if not k.startswith("outer.")}
    del state["recipe"]["geometry"]["sdf"]["background"], state["recipe"]["geometry"]["sdf"]["outer"]
    torch.save(state, tmp_path / "old.pt")
    sem = SemanticField.load(tmp_path / "old.pt", torch.device("cpu"))
    assert sem.sdf.outer is None and sem.recipe.geometry.sdf.background == "env"
    cam = load_capture(run.capture_dir).unit_cameras()[0]
    assert sem.render(cam).mask.shape == (cam.height, cam.width)
