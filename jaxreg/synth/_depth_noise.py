"""A stereo depth sensor's noise model, `StereoSensor` (re-exported by `jaxreg.synth`)."""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxreg.camera.model import Intrinsics
from jaxreg.synth.render import Rendering

__all__ = ["StereoSensor"]


@dataclasses.dataclass(frozen=True)
class StereoSensor:
    """An active-stereo depth camera: Intel RealSense D435 / D415 (active IR stereo, D4
    vision processor), its optics and its noise.

    The model turns an exact z-depth render into the depth image such a camera reports, in the
    order the camera forms it (a left-imager-referenced disparity search):

    1. Lateral error: the depth at pixel `(u, v)` is that of the surface seen at
       `(u + du, v + dv)`, `du, dv ~ N(0, lateral_sigma_px^2)`, on the pixel's tangent plane, so a
       slanted surface gets depth noise `z * lateral_sigma_px * |(n_x / fx, n_y / fy)| / |n . r|`
       (n the normal, r the unit-depth ray) and a fronto-parallel one none.
    2. Flying pixels: a pixel next to a depth edge (a 4-neighbour more than `flying_min_jump_m`
       nearer or farther) sees both surfaces in its matching window; with probability
       `flying_probability` it reports `z + t (z_neighbour - z)`, `t ~ U(0, 1)`: a point floating
       between the two surfaces.
    3. Axial error in disparity: `d = fx B / z` plus `N(0, subpixel_rms_px^2)`, rounded to
       `disparity_step_px`; `z = fx B / d`, rounded to `depth_unit_m`. To first order the depth
       error is `sigma_z = z^2 subpixel_rms_px / (fx B)`: it grows with the square of the distance.
    4. Holes (NaN): no surface; a disparity above `max_disparity_px` (too near) or not positive;
       a point outside the right imager's view (the invalid band at the image's left edge,
       `fx B / z` pixels wide) or hidden from it by a nearer surface (the band left of every
       foreground object); and a weak infrared return, `s = albedo * cos(incidence)`, which is
       valid with probability rising linearly from 0 at `signal_range[0]` to 1 at
       `signal_range[1]` (dark and grazing surfaces).

    Sources of the coefficients:

    * Baselines (D435 50 mm, D415 55 mm), depth fields of view (87 and 65 degrees horizontal), the
      left-imager reference, the invalid depth band `fx B / z` and the RMS-error specification
      (at most 2% at 2 m): Intel RealSense D400 Series Product Family Datasheet.
    * `sigma_z = z^2 subpixel / (fx B)` with `subpixel ~ 0.08 px` RMS on a well-textured target,
      and the 126-disparity search that sets the minimum range `fx B / 126`: Grunnet-Jepsen,
      Sweetser & Woodfill, "Tuning depth cameras for best performance" (Intel white paper) and
      Keselman et al., "Intel RealSense Stereoscopic Depth Cameras" (CVPR workshops 2017,
      arXiv:1705.05548). For the D435 at 848x480 (`fx` = 447 px) this gives 1.3 mm at 0.6 m and
      14 mm (0.7%) at 2 m, inside the datasheet's 2% bound, which corresponds to `subpixel` ~0.22
      (`StereoSensor.d435(subpixel_rms_px=0.22)` models a camera at its specification limit). Ahn
      et al., "Analysis and noise modeling of the Intel RealSense D435 for mobile robots" (UR
      2019) model a real D435's noise against distance and incidence angle.
    * `disparity_step_px = 1/32`: the D4's subpixel resolution (Intel white paper "Subpixel
      linearity improvement for Intel RealSense depth cameras"); `depth_unit_m = 0.001`, the
      cameras' default depth units.
    * `lateral_sigma_px = 0.8`: a stand-in, the lateral sigma Nguyen, Izadi & Lovell
      (3DIMPVT 2012) measured for a Kinect below 60 degrees incidence, of the order of a stereo
      matcher's localisation error; replace it with your camera's.
    * `flying_probability`, `flying_min_jump_m`, `signal_range`: modelling choices, not published
      figures (white surfaces lose depth beyond ~80-85 degrees incidence, surfaces darker than
      ~10% albedo mostly); set them to match your own captures.

    Not modelled: spatial correlation of the noise over the matching window, the projector
    pattern, subpixel non-linearity ("pixel locking"), temporal filtering, multi-camera
    interference.

    Attributes:
        name: for reports.
        hfov_deg: horizontal field of view of the depth image, degrees.
        baseline_m: distance between the left and right imagers, metres; the right imager
            sits at `(+baseline_m, 0, 0)` in the (left-imager) camera frame.
        subpixel_rms_px: RMS disparity error, pixels.
        disparity_step_px: disparity quantum, pixels.
        max_disparity_px: largest disparity searched (nearer surfaces are holes), pixels.
        depth_unit_m: quantum of the reported depth, metres.
        lateral_sigma_px: standard deviation of the lateral error per image axis, pixels.
        flying_probability: chance that a pixel at a depth edge reports a mixed depth.
        flying_min_jump_m: depth difference to a 4-neighbour that makes an edge, metres.
        signal_range: `(lo, hi)` of `albedo * cos(incidence)` over which a return goes from
            always a hole to always valid.
    """

    name: str
    hfov_deg: float
    baseline_m: float
    subpixel_rms_px: float = 0.08
    disparity_step_px: float = 1.0 / 32.0
    max_disparity_px: float = 126.0
    depth_unit_m: float = 0.001
    lateral_sigma_px: float = 0.8
    flying_probability: float = 0.5
    flying_min_jump_m: float = 0.01
    signal_range: tuple[float, float] = (0.05, 0.15)

    @classmethod
    def d435(cls, **changes) -> StereoSensor:
        """Intel RealSense D435: 50 mm baseline, 87 degree depth HFOV; `changes` override."""
        return cls("Intel RealSense D435", hfov_deg=87.0, baseline_m=0.050, **changes)

    @classmethod
    def d415(cls, **changes) -> StereoSensor:
        """Intel RealSense D415: 55 mm baseline, 65 degree depth HFOV; `changes` override."""
        return cls("Intel RealSense D415", hfov_deg=65.0, baseline_m=0.055, **changes)

    def intrinsics(self, width: int = 848, height: int = 480) -> Intrinsics:
        """Ideal intrinsics of a `width` x `height` depth image: square pixels,
        `fx = fy = (width / 2) / tan(hfov / 2)`, centred principal point, no distortion."""
        focal = (width / 2) / np.tan(np.radians(self.hfov_deg) / 2)
        return Intrinsics(focal, focal, (width - 1) / 2, (height - 1) / 2, width, height)

    def axial_sigma(self, depth, fx: float) -> np.ndarray:
        """Standard deviation (metres) of the reported depth of a fronto-parallel surface at
        `depth` (metres, any shape), focal length `fx` (pixels): the disparity noise and both
        quantisations (each as a uniform error's variance, `step^2 / 12`)."""
        depth = np.asarray(depth, dtype=np.float64)
        disparity_var = self.subpixel_rms_px**2 + self.disparity_step_px**2 / 12
        slope = depth**2 / (fx * self.baseline_m)  # d depth / d disparity
        return np.sqrt(slope**2 * disparity_var + self.depth_unit_m**2 / 12)

    def depth_sigma(self, rendering: Rendering) -> np.ndarray:
        """`(H, W)` predicted standard deviation (metres) of every pixel's reported depth away
        from edges: `axial_sigma` and the lateral error on the pixel's tangent plane."""
        intrinsics = rendering.intrinsics
        fx, fy = float(intrinsics.fx), float(intrinsics.fy)
        n, z = rendering.normals, rendering.depth
        facing = np.abs(np.sum(n * rendering.rays, axis=-1))
        lateral = z * self.lateral_sigma_px * np.hypot(n[..., 0] / fx, n[..., 1] / fy) / facing
        return np.hypot(self.axial_sigma(z, fx), lateral)

    def depth_noise(self, intrinsics: Intrinsics, base_T_camera=None):
        """This sensor as a `jaxreg.uncertainty.DepthNoise` (for `icp_covariance`): axial
        `sigma_z = b z^2` with the disparity terms of `axial_sigma`, plus the lateral pixel
        noise; `base_T_camera` maps the camera into the cloud's frame (default identity)."""
        from jaxreg.uncertainty import DepthNoise

        fx = float(intrinsics.fx)
        disparity_sigma = np.hypot(self.subpixel_rms_px, self.disparity_step_px / np.sqrt(12))
        b = disparity_sigma / (fx * self.baseline_m)
        return DepthNoise(
            (0.0, 0.0, b),
            base_T_camera,
            pixel_sigma=self.lateral_sigma_px,
            focal_length=(fx, float(intrinsics.fy)),
        )

    @staticmethod
    def edge_jump(depth: np.ndarray) -> np.ndarray:
        """`(H, W)` signed difference `z_neighbour - z` to the 4-neighbour across the largest
        depth jump of an exact `(H, W)` depth image (metres); 0 where no neighbour has a depth.
        Pixels with `|edge_jump| > flying_min_jump_m` are the flying-pixel candidates."""
        padded = np.pad(depth, 1, constant_values=np.nan)
        jump = np.zeros_like(depth)
        for neighbour in (padded[:-2, 1:-1], padded[2:, 1:-1], padded[1:-1, :-2], padded[1:-1, 2:]):
            difference = neighbour - depth
            jump = np.where(np.abs(difference) > np.abs(jump), difference, jump)  # NaN: never
        return jump

    def measure(self, rendering: Rendering, rng: np.random.Generator) -> np.ndarray:
        """The `(H, W)` depth (metres, NaN holes) this sensor reports for an exact render."""
        intrinsics = rendering.intrinsics
        fx, fy, cx = float(intrinsics.fx), float(intrinsics.fy), float(intrinsics.cx)
        z0, n, rays = rendering.depth, rendering.normals, rendering.rays
        shape = z0.shape
        surface = np.isfinite(z0)

        # 1. lateral error on the tangent plane (kept where the shifted ray still meets it well)
        shift = rng.normal(0.0, self.lateral_sigma_px, (*shape, 2))
        facing = np.einsum("...i,...i->...", n, rays)
        shifted = facing + n[..., 0] * shift[..., 0] / fx + n[..., 1] * shift[..., 1] / fy
        stable = surface & (shifted * facing > 0.25 * facing**2)
        z = np.where(stable, z0 * facing / np.where(stable, shifted, 1.0), z0)

        # 2. flying pixels: mix with the 4-neighbour across the largest depth jump
        jump = self.edge_jump(z0)
        flying = (np.abs(jump) > self.flying_min_jump_m) & (
            rng.random(shape) < self.flying_probability
        )
        z = np.where(flying, z + rng.random(shape) * jump, z)

        # 3. disparity noise and quantisation, then depth units
        focal_baseline = fx * self.baseline_m
        disparity = focal_baseline / z + rng.normal(0.0, self.subpixel_rms_px, shape)
        disparity = np.round(disparity / self.disparity_step_px) * self.disparity_step_px
        matched = (disparity > 0) & (disparity <= self.max_disparity_px)
        z = focal_baseline / np.where(matched, disparity, 1.0)
        z = np.round(z / self.depth_unit_m) * self.depth_unit_m

        # 4. holes: weak return, right imager's view and occlusion
        cos_incidence = np.abs(facing) / np.linalg.norm(rays, axis=-1)
        lo, hi = self.signal_range
        p_valid = np.clip((rendering.albedo * cos_incidence - lo) / (hi - lo), 0.0, 1.0)
        returned = rng.random(shape) < p_valid
        u_right = fx * (rays[..., 0] - self.baseline_m / np.where(surface, z0, 1.0)) + cx
        in_right_view = u_right >= -0.5
        seen_right = rendering.visible_from(np.array([self.baseline_m, 0.0, 0.0]))
        valid = surface & matched & returned & in_right_view & seen_right
        return np.where(valid, z, np.nan)
