"""jaxreg.io.images: one reader each for masks, depth counts and colour, and the mask rule for
images of several channels or 16 bits."""

import numpy as np
import pytest
from PIL import Image

from jaxreg.io import read_depth_counts, read_image_size, read_mask, read_rgb

SHAPE = (6, 9)
MODES = {
    "1-bit": ("1",), "8-bit": ("L",), "16-bit": ("I;16", "I;16B", "I;16L", "I"),
    "RGB grey": ("RGB",), "RGBA opaque": ("RGBA",), "LA opaque": ("LA",), "palette": ("P",),
}  # fmt: skip


def _object() -> np.ndarray:
    mask = np.zeros(SHAPE, bool)
    mask[1:4, 2:7] = True
    mask[5, 0] = True
    return mask


@pytest.mark.parametrize("layout", MODES)
def test_read_mask_reads_grey_masks_of_every_layout(tmp_path, layout):
    mask = _object()
    level = np.where(mask, 200, 0).astype(np.uint8)
    if layout == "1-bit":
        image = Image.fromarray(mask)
    elif layout == "8-bit":
        image = Image.fromarray(level)
    elif layout == "16-bit":
        image = Image.fromarray(np.where(mask, 40000, 0).astype(np.uint16))
    elif layout == "RGB grey":
        image = Image.fromarray(np.repeat(level[..., None], 3, -1))
    elif layout == "RGBA opaque":
        rgba = np.concatenate([np.repeat(level[..., None], 3, -1), np.full((*SHAPE, 1), 255)], -1)
        image = Image.fromarray(rgba.astype(np.uint8))
    elif layout == "LA opaque":
        image = Image.fromarray(np.stack([level, np.full(SHAPE, 255, np.uint8)], -1), mode="LA")
    else:
        image = Image.fromarray(level).convert("P")
    path = tmp_path / "mask.png"
    image.save(path)
    with Image.open(path) as written:  # the file holds the layout the case names
        assert written.mode in MODES[layout], written.mode
    got = read_mask(path)
    assert got.shape == SHAPE and got.dtype == bool
    np.testing.assert_array_equal(got, mask)


def test_read_mask_refuses_colour_and_transparency(tmp_path):
    labels = np.zeros((*SHAPE, 3), np.uint8)
    labels[1:3, 1:3] = (255, 0, 0)  # two objects told apart by colour
    labels[4:6, 5:8] = (0, 255, 0)
    Image.fromarray(labels).save(tmp_path / "labels.png")
    with pytest.raises(ValueError, match="labels.png: the mask has colours"):
        read_mask(tmp_path / "labels.png")
    rgba = np.zeros((*SHAPE, 4), np.uint8)
    rgba[..., 3] = np.where(_object(), 255, 0)  # the object drawn in the alpha channel
    Image.fromarray(rgba).save(tmp_path / "alpha.png")
    with pytest.raises(ValueError, match="alpha.png: the mask has transparent pixels"):
        read_mask(tmp_path / "alpha.png")
    Image.fromarray(np.ones(SHAPE, np.float32)).save(tmp_path / "float.tiff")
    with pytest.raises(ValueError, match="a mask must be a grey image.*'F'"):
        read_mask(tmp_path / "float.tiff")
    (tmp_path / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with pytest.raises(ValueError, match="the mask image is not a readable image"):
        read_mask(tmp_path / "broken.png")
    with pytest.raises(ValueError, match="no such file"):
        read_mask(tmp_path / "absent.png")


def test_depth_counts_colour_and_size(tmp_path):
    counts = (np.arange(54).reshape(SHAPE) * 1000).astype(np.uint16)
    Image.fromarray(counts).save(tmp_path / "depth.png")
    np.testing.assert_array_equal(read_depth_counts(tmp_path / "depth.png"), counts)
    assert read_image_size(tmp_path / "depth.png") == SHAPE
    colour = np.random.default_rng(0).integers(0, 256, (*SHAPE, 3)).astype(np.uint8)
    Image.fromarray(colour).save(tmp_path / "colour.png")
    np.testing.assert_array_equal(read_rgb(tmp_path / "colour.png"), colour)
    with pytest.raises(ValueError, match="a depth PNG must be one 16-bit channel.*'RGB'"):
        read_depth_counts(tmp_path / "colour.png")
