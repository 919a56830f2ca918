"""A mask is evidence, not truth: the mask route keeps the object's surface inside the mask
(pixels the depth image connects to it), so a mask grown over the background, shrunk, or bled
sideways by a few pixels still gives the object's pose, and the segment's extent, units and
coverage are judged on that surface."""

import numpy as np
import pytest
from scipy import ndimage

import jaxreg as jr
from jaxreg.geometry.metrics import add_s
from jaxreg.pipeline._surface import depth_step, mask_surface


def _wall_and_box(shape=(120, 160)):
    """A depth image: a wall 1.0 m away, a box face 0.8 m away in its middle, and a slanted
    strip (depth rising 2 mm per pixel) attached to the face."""
    depth = np.full(shape, 1.0)
    depth[40:80, 50:110] = 0.8
    depth[80:90, 50:110] = 0.8 + 0.002 * np.arange(1, 11)[:, None]
    truth = np.zeros(shape, bool)
    truth[40:90, 50:110] = True
    return depth, truth


def test_the_surface_drops_the_background_behind_and_keeps_slanted_faces():
    depth, truth = _wall_and_box()
    sigma = np.array([0.0, 0.0, 2.5e-3])
    grown = ndimage.binary_dilation(truth, iterations=4)  # 4 pixels of wall in the mask
    surface = mask_surface(depth, grown, sigma, 500.0)
    assert np.array_equal(surface, truth)
    holes = depth.copy()
    holes[60, :] = np.nan  # a row without depth cuts the face in two pieces: both kept
    cut = mask_surface(holes, grown, sigma, 500.0)
    assert np.array_equal(cut, truth & np.isfinite(holes))
    assert not mask_surface(depth, np.zeros_like(truth), sigma, 500.0).any()


def test_the_depth_step_follows_the_noise_and_the_pixel_size():
    near, far = depth_step(np.array([0.5, 1.0]), np.array([0.001, 0.003]), 600.0)
    assert 0 < near < far
    # a 45 degree face's step across one pixel is one pixel's width: one surface
    assert depth_step(1.0, 0.0, 600.0) > 1.0 / 600.0


@pytest.fixture(scope="module")
def mug():
    return jr.synth.tabletop_scene(2, object="mug")


@pytest.mark.parametrize("change", ["grown", "shrunk", "bled"])
def test_a_mask_off_by_a_few_pixels_still_poses_the_object(mug, change):
    mask = mug.mask
    if change == "grown":
        mask = ndimage.binary_dilation(mask, iterations=4)
    elif change == "shrunk":
        mask = ndimage.binary_erosion(mask, iterations=3)
    else:
        mask = np.roll(mask, 4, axis=1)
    est = jr.estimate_pose(mug.frame, mug.model_points, mask=mask, symmetry=mug.symmetry)
    assert est.success, est.reason
    assert float(add_s(mug.model_points, est.pose, mug.truth)) < 0.005
    # what was lifted lies on the object: its points are near the model at the truth
    moved = np.asarray(mug.truth.inverse() @ est.points)
    gap = np.min(np.linalg.norm(moved[:, None] - mug.model_points[None, ::4], axis=-1), 1)
    assert np.mean(gap < 0.01) > 0.97
