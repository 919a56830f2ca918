"""The model's colours as the segment stage's cue: a look-alike of another paint is no rival."""

import re

import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from jaxreg.camera import RGBDFrame
from jaxreg.pipeline import estimate_pose
from jaxreg.pipeline._colour import colour_match, model_palette
from jaxreg.synth import object_mesh, render, tabletop_scene
from jaxreg.synth.render import display_color

RED, BLUE = np.array([0.7, 0.12, 0.1]), np.array([0.1, 0.2, 0.7])  # linear RGB paints
TABLE = np.array([0.55, 0.42, 0.30])


def _painted_pair(gap: float, paints):
    """Two identical boxes side by side, ``gap`` metres apart along their x axis (the twins
    scene of test_pipeline at 0.08 m), painted ``paints`` (two linear RGB colours): the frame,
    the centres of the boxes and the box's symmetry."""
    box, symmetry = object_mesh("box")
    shift = (0.08 + gap, 0.0, 0.0)  # the box is 80 mm long in x
    pair = trimesh.util.concatenate([box, box.copy().apply_translation(shift)])
    scene = tabletop_scene(6, mesh=pair, distractors=0, symmetry=symmetry)
    truth = np.asarray(scene.truth.as_matrix(), np.float64)
    table = trimesh.creation.box((1.2, 0.8, 0.04)).apply_translation((0.0, 0.0, -0.02))
    meshes = [table, box.copy().apply_transform(truth),
              box.copy().apply_translation(shift).apply_transform(truth)]  # fmt: skip
    camera = np.asarray(scene.frame.base_T_camera.as_matrix(), np.float64)
    rgb = render(meshes, scene.frame.intrinsics, camera, np.stack([TABLE, *paints])).shade()
    frame = RGBDFrame(scene.frame.depth, scene.frame.intrinsics, rgb=rgb,
                      base_T_camera=scene.frame.base_T_camera)  # fmt: skip
    return frame, [truth[:3, 3], np.asarray(scene.truth @ jnp.asarray(shift))], symmetry


@pytest.fixture(scope="module")
def painted_twins():
    """The twins of test_pipeline (16 cm apart): the frame with the first painted red and the
    second blue, the frame with both red, their centres, the model (box surface samples)."""
    (frame, centres, symmetry), (same, _, _) = (
        _painted_pair(0.08, paints) for paints in ([RED, BLUE], [RED, RED])
    )
    box, _ = object_mesh("box")
    model = trimesh.sample.sample_surface(box, 6000, seed=1)[0].astype(np.float32)
    return (frame, same), model, symmetry, centres


@pytest.mark.parametrize(("paint", "which"), [(RED, 0), (BLUE, 1)])
def test_a_twin_of_another_paint_is_no_rival(painted_twins, paint, which):
    """Depth alone refuses the twins (test_pipeline); with the model's paint the box of that
    colour is posed, and the other is set aside as another colour. Per-point colours (a
    textured model's) do the same as one colour."""
    (frame, _), model, symmetry, centres = painted_twins
    for colors in (display_color(paint), np.tile(display_color(paint), (len(model), 1))):
        est = estimate_pose(frame, model, symmetry=symmetry, model_colors=colors)
        assert est.success, est.reason
        found = np.asarray(est.pose.translation())
        assert np.linalg.norm(found[:2] - centres[which][:2]) < 0.01
        assert len(est.stages["segment"].other_color) == 1


def test_twins_of_one_paint_stay_refused(painted_twins):
    """Both boxes red: colour cannot tell them apart, so the twins are refused as without it."""
    (_, one_paint), model, symmetry, _ = painted_twins
    est = estimate_pose(one_paint, model, symmetry=symmetry, model_colors=display_color(RED))
    assert not est.success and "two separate segments fit the model equally well" in est.reason
    assert est.stages["segment"].other_color == []


def test_no_cluster_of_the_model_paint_is_refused(painted_twins):
    """A green model: every cluster of its size shows another colour, so the object is not in
    view, and the reason says what to check."""
    (frame, _), model, symmetry, _ = painted_twins
    est = estimate_pose(frame, model, symmetry=symmetry, model_colors=(0.1, 0.8, 0.1))
    assert est.failed_stage == "segment"
    assert "shows other colours than the model's" in est.reason and "pixel=" in est.reason


def test_colour_match_ignores_shading_and_judges_only_clear_pixels():
    """One paint lit and in shade shares its chromaticity; dark and clipped pixels are not
    judged; another paint is not within the tolerance."""
    palette = model_palette(display_color(RED), 1)
    red = np.rint(255 * display_color(RED) * np.array([[1.0], [0.6], [0.3]]) ** (1 / 2.2))
    judged, match = colour_match(red.astype(np.uint8), palette, 0.03)
    assert judged.tolist() == match.tolist() == [True] * 3
    dark_and_clipped = np.array([[3, 1, 1], [255, 40, 30]], np.uint8)
    assert not colour_match(dark_and_clipped, palette, 0.03)[0].any()
    blue = np.rint(255 * display_color(BLUE))[None].astype(np.uint8)
    judged, match = colour_match(blue, palette, 0.03)
    assert judged.tolist() == [True] and match.tolist() == [False]


@pytest.mark.parametrize(
    ("colors", "message"),
    [
        (np.zeros((10, 4)), "must be (M, 3)"),
        (np.full((7, 3), 0.5), "7 colours for 10 model points"),
        (np.array([1.0, 2.0, 0.5]), "sRGB floats in [0, 1]"),
        (np.array([0.5, np.nan, 0.5]), "sRGB floats in [0, 1]"),
        (np.array([1, 2, 3]), "floats in [0, 1] or uint8"),
        (np.zeros(3), "all black"),
    ],
)
def test_bad_model_colors_are_refused(colors, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        model_palette(colors, 10)
    assert model_palette(np.array([[255, 0, 0], [0, 0, 255]], np.uint8), 2).shape == (2, 2)


def test_a_touching_neighbour_of_another_paint_is_split_off(painted_twins):
    """The red box with a blue one 5 mm beside it: one cluster, too wide for the model, and
    from depth alone refused. With the model's paint its red pixels are the candidate
    (``stripped_by_color``) and the lift keeps only them: the red box is posed."""
    _, model, symmetry, _ = painted_twins
    frame, centres, _ = _painted_pair(0.005, [RED, BLUE])
    plain = estimate_pose(frame, model, symmetry=symmetry)
    assert not plain.success
    est = estimate_pose(frame, model, symmetry=symmetry, model_colors=display_color(RED))
    assert est.success, est.reason
    assert est.stages["segment"].stripped_by_color == [0]
    found = np.asarray(est.pose.translation())
    assert np.linalg.norm(found[:2] - centres[0][:2]) < 0.01
