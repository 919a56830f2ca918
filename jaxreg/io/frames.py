"""RGB-D frames from files: organized PCD captures, and 16-bit depth PNGs with an intrinsics JSON.

Public through `jaxreg.io.read_frame` / `jaxreg.io.write_frame`. Host-side: files are read with
numpy and Pillow, and malformed or inconsistent input raises `ValueError` naming the file, the
problem and what to try.

Depth PNG + JSON (the RealSense / Azure Kinect export convention)
-----------------------------------------------------------------
* `<name>.png`: one channel of 16-bit unsigned counts; metres = counts * `depth_scale`; 0 is a
  hole. With the usual `depth_scale = 0.001` a count is a millimetre.
* `<name>.json` (beside it unless given): an object with the required keys `fx`, `fy`, `cx`,
  `cy` (pixels, OpenCV conventions: pixel centres at integers), `width`, `height` (pixels,
  must match the PNG) and `depth_scale` (metres per count), and the optional keys
  `dist_coeffs` (4 or 5 Brown-Conrady coefficients, OpenCV order), `base_T_camera` (4x4
  nested list, the hand-eye transform camera -> robot base) and `rgb` (file name of an 8-bit
  colour PNG registered to the depth, relative to the JSON's folder).
* `read_frame(..., rgb=PATH)` reads a colour image named by the caller instead (any format
  Pillow reads, converted to 8-bit RGB); it must have the depth's size.

Organized PCD (PCL's Kinect and stereo captures)
------------------------------------------------
The points of an organized cloud are `z * ((u - cx) / fx, (v - cy) / fy, 1)` in the camera
frame, so `u` is an exact affine function of `x / z` (and `v` of `y / z`): a least-squares line
through all valid pixels recovers `fx, cx` (and `fy, cy`), and the largest residual, which must
stay below `_PINHOLE_TOLERANCE_PX`, proves the cloud is a pinhole image. The file's VIEWPOINT is
not a hand-eye transform (PCL's OpenNI grabber writes a 180 degree rotation about x there, a
viewer convention), so the frame's `base_T_camera` is the identity unless given.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image

from jaxreg.camera.model import Intrinsics, RGBDFrame
from jaxreg.geometry.lie import se3_to_matrix
from jaxreg.io.clouds import read_pcd
from jaxreg.io.images import read_depth_counts, read_rgb

__all__ = ["read_frame", "write_frame"]

# Largest |pixel - (f * x / z + c)| of a recovered organized cloud: PCL's Kinect captures fit to
# ~2e-4 px and the stereo mug capture to 0.02 px (float32 coordinates); a cloud that is not one
# pinhole image (registered, rectified from another camera, resampled) misses by pixels.
_PINHOLE_TOLERANCE_PX = 0.05
_REQUIRED_KEYS = ("fx", "fy", "cx", "cy", "width", "height", "depth_scale")
_UINT16_MAX = np.iinfo(np.uint16).max


def _pinhole_axis(path: Path, axis: str, coords: np.ndarray, pixels: np.ndarray):
    """`(f, c)` of `pixels = f * coords + c` by least squares, checked to fit every pixel."""
    if np.ptp(pixels) == 0:
        raise ValueError(
            f"{path}: every valid point lies in one image {axis}: the intrinsics cannot be "
            "recovered; pass a depth PNG with an intrinsics JSON instead"
        )
    design = np.stack([coords, np.ones_like(coords)], axis=1)
    (focal, centre), *_ = np.linalg.lstsq(design, pixels, rcond=None)
    worst = np.abs(design @ (focal, centre) - pixels).max()
    if not focal > 0 or worst > _PINHOLE_TOLERANCE_PX:
        raise ValueError(
            f"{path}: the organized points are not one pinhole image (best fit f{axis}="
            f"{focal:.3f} misses a pixel by {worst:.3g} px > {_PINHOLE_TOLERANCE_PX}); is the "
            "cloud transformed out of the camera frame? Read it with read_pcd instead"
        )
    return focal, centre


def _frame_from_pcd(path: Path, base_T_camera) -> RGBDFrame:
    cloud = read_pcd(path)
    if not cloud.is_organized:
        raise ValueError(
            f"{path}: not an organized cloud (HEIGHT 1): a frame needs the image layout; "
            "use read_pcd / load_points for unorganized clouds"
        )
    points = cloud.points.astype(np.float64)
    height, width = points.shape[:2]
    valid = np.isfinite(points).all(axis=-1) & (points[..., 2] > 0)
    if valid.sum() < 2:
        raise ValueError(f"{path}: fewer than 2 valid points: the intrinsics cannot be recovered")
    rows, cols = np.nonzero(valid)
    xyz = points[valid]
    fx, cx = _pinhole_axis(path, "x", xyz[:, 0] / xyz[:, 2], cols.astype(np.float64))
    fy, cy = _pinhole_axis(path, "y", xyz[:, 1] / xyz[:, 2], rows.astype(np.float64))
    depth = np.where(valid, points[..., 2], np.nan).astype(cloud.points.dtype)
    intrinsics = Intrinsics(fx, fy, cx, cy, width, height)
    return RGBDFrame(depth, intrinsics, rgb=cloud.colors, base_T_camera=base_T_camera)


def _load_json(path: Path) -> dict:
    try:
        meta = json.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(
            f"intrinsics JSON {path} not found: pass intrinsics=<path to the JSON> or an Intrinsics"
        ) from None
    except json.JSONDecodeError as error:
        raise ValueError(f"{path}: not valid JSON ({error})") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: expected a JSON object with keys {', '.join(_REQUIRED_KEYS)}")
    missing = [key for key in _REQUIRED_KEYS if key not in meta]
    if missing:
        raise ValueError(
            f"{path}: missing {', '.join(missing)} (a depth-PNG intrinsics JSON needs "
            f"{', '.join(_REQUIRED_KEYS)})"
        )
    if not float(meta["depth_scale"]) > 0:
        raise ValueError(f"{path}: depth_scale must be positive metres per count")
    return meta


def _checked_rgb(path: Path, rgb, shape: tuple[int, int]) -> np.ndarray:
    """The colour image `rgb` (a file or an `(H, W, 3)` array) as uint8, checked to have the
    depth image's `(H, W)` `shape`; `path` is the depth's file, named in the error."""
    if isinstance(rgb, str | Path):
        source, image = Path(rgb), read_rgb(Path(rgb))
    else:
        source, image = "the rgb array", np.asarray(rgb)
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(
                f"rgb must be an (H, W, 3) uint8 colour image, got {image.dtype} {image.shape}"
            )
    if image.shape[:2] != tuple(shape):
        raise ValueError(
            f"{source}: the colour image is {image.shape[1]}x{image.shape[0]} (width x height) "
            f"but the depth {path} is {shape[1]}x{shape[0]}: give the colour image registered "
            "to this depth image"
        )
    return image


def _frame_from_png(
    path: Path, intrinsics, depth_scale: float, base_T_camera, rgb_file
) -> RGBDFrame:
    rgb = None
    if isinstance(intrinsics, Intrinsics):
        scale = depth_scale
    else:
        json_path = path.with_suffix(".json") if intrinsics is None else Path(intrinsics)
        meta = _load_json(json_path)
        intrinsics = Intrinsics(
            meta["fx"],
            meta["fy"],
            meta["cx"],
            meta["cy"],
            meta["width"],
            meta["height"],
            meta.get("dist_coeffs"),
        )
        scale = float(meta["depth_scale"])
        if base_T_camera is None and "base_T_camera" in meta:
            base_T_camera = np.asarray(meta["base_T_camera"], dtype=np.float64)
        if "rgb" in meta and rgb_file is None:
            rgb = read_rgb(json_path.parent / meta["rgb"])
    counts = read_depth_counts(path, "depth PNG")
    if counts.shape != intrinsics.shape:
        raise ValueError(
            f"{path}: the depth image is {counts.shape[1]}x{counts.shape[0]} (width x height) "
            f"but the intrinsics are for {intrinsics.width}x{intrinsics.height}"
        )
    if rgb_file is not None:
        rgb = _checked_rgb(path, rgb_file, counts.shape)
    elif rgb is not None and rgb.shape[:2] != counts.shape:
        raise ValueError(f"{path}: the colour image is {rgb.shape[:2]}, the depth {counts.shape}")
    depth = np.where(counts > 0, counts * scale, np.nan).astype(np.float32)
    return RGBDFrame(depth, intrinsics, rgb=rgb, base_T_camera=base_T_camera)


def read_frame(
    path: str | Path,
    intrinsics: str | Path | Intrinsics | None = None,
    *,
    depth_scale: float = 0.001,
    base_T_camera=None,
    rgb: str | Path | np.ndarray | None = None,
) -> RGBDFrame:
    """Read an `RGBDFrame` from an organized `.pcd` or a 16-bit depth `.png`.

    Args:
        path: an organized PCD (intrinsics recovered exactly from its points, colour from its
            `rgb`/`rgba` field) or a depth PNG (see the module docstring for the format).
        intrinsics: PNG only: the intrinsics JSON (default: `path` with suffix `.json`), or
            an `Intrinsics` (then `depth_scale` says what a count is, and no JSON is read).
            Must be `None` for a PCD.
        depth_scale: metres per PNG count when `intrinsics` is an `Intrinsics`.
        base_T_camera: `SE3` or `(4, 4)` hand-eye transform camera -> base; default: the JSON's
            `base_T_camera` if any, else the identity.
        rgb: the colour image registered to the depth pixels: a file (PNG, JPEG, ...; read as
            8-bit RGB) or an `(H, W, 3)` uint8 array. It replaces the JSON's `rgb` (PNG) or
            the cloud's colours (PCD). Default: those, if any.

    Returns:
        The frame: `(H, W)` depth in metres with NaN holes (PNG count 0, PCD NaN points),
        `rgb` `(H, W, 3)` uint8 or None.

    Raises:
        ValueError: unknown suffix, unreadable file, an unorganized or non-pinhole cloud,
            missing JSON keys, or an image size (depth or colour) that does not match the
            intrinsics.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".pcd":
        if intrinsics is not None:
            raise ValueError(
                f"{path}: an organized PCD's intrinsics are recovered from its points; "
                "pass intrinsics only with a depth PNG"
            )
        frame = _frame_from_pcd(path, base_T_camera)
        if rgb is None:
            return frame
        colour = _checked_rgb(path, rgb, frame.intrinsics.shape)
        return RGBDFrame(frame.depth, frame.intrinsics, colour, frame.base_T_camera)
    if suffix == ".png":
        return _frame_from_png(path, intrinsics, depth_scale, base_T_camera, rgb)
    raise ValueError(f"{path}: read_frame reads .pcd (organized) or .png (16-bit depth) files")


def write_frame(path: str | Path, frame: RGBDFrame, *, depth_scale: float = 0.001) -> None:
    """Write `frame` as a 16-bit depth PNG `path`, its JSON beside it and, with colour, an RGB PNG.

    Files: `path` (`.png`, counts = round(depth / depth_scale), 0 for holes),
    `path.with_suffix(".json")` (intrinsics, `depth_scale`, `base_T_camera`, distortion if
    any, and `rgb`), and `<stem>_rgb.png` when `frame.rgb` is set. `read_frame(path)` returns
    the frame with depth rounded to `depth_scale`.

    Raises:
        ValueError: `path` is not a `.png`, `depth_scale` is not positive, or a depth exceeds
            65535 counts (choose a larger `depth_scale`).
    """
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"{path}: write_frame writes a .png depth image (and a .json beside it)")
    if not depth_scale > 0:
        raise ValueError(f"depth_scale must be positive metres per count, got {depth_scale}")
    depth = np.asarray(frame.depth, dtype=np.float64)
    counts = np.rint(np.nan_to_num(depth, nan=0.0) / depth_scale)
    if counts.max() > _UINT16_MAX:
        raise ValueError(
            f"{path}: depth {np.nanmax(depth):.3f} m is {counts.max():.0f} counts > 65535 at "
            f"depth_scale {depth_scale}: choose a larger depth_scale"
        )
    Image.fromarray(counts.astype(np.uint16)).save(path)
    intrinsics = frame.intrinsics
    meta = {key: float(getattr(intrinsics, key)) for key in ("fx", "fy", "cx", "cy")}
    meta |= {"width": intrinsics.width, "height": intrinsics.height, "depth_scale": depth_scale}
    if intrinsics.dist_coeffs is not None:
        meta["dist_coeffs"] = np.asarray(intrinsics.dist_coeffs, dtype=np.float64).tolist()
    meta["base_T_camera"] = np.asarray(se3_to_matrix(frame.base_T_camera), np.float64).tolist()
    if frame.rgb is not None:
        rgb_path = path.with_name(f"{path.stem}_rgb.png")
        Image.fromarray(np.asarray(frame.rgb, dtype=np.uint8)).save(rgb_path)
        meta["rgb"] = rgb_path.name
    path.with_suffix(".json").write_text(json.dumps(meta, indent=2))
