"""Synthetic tabletop RGB-D scenes: meshes of the test objects, an exact ray-cast rendering, a
stereo depth sensor model, scenes with their ground truth (pose, mask, symmetry), sequences of a
moving target for tracking, and those scenes written as a BOP dataset split.

Needs the ray caster (trimesh + Embree), so ``import jaxreg`` loads it on first use. May import
core, geometry, uncertainty and camera.
"""

from jaxreg.core._lazy import exports
from jaxreg.synth._depth_noise import StereoSensor as StereoSensor
from jaxreg.synth._meshes import (
    MODEL_SAMPLES as MODEL_SAMPLES,
    OBJECTS as OBJECTS,
    distractor_mesh as distractor_mesh,
    object_mesh as object_mesh,
    surface_points as surface_points,
    surface_samples as surface_samples,
)
from jaxreg.synth.bop import (
    image_scene as image_scene,
    obj_id as obj_id,
    write_bop_split as write_bop_split,
)
from jaxreg.synth.scenes import (
    Rendering as Rendering,
    TabletopScene as TabletopScene,
    look_at as look_at,
    render as render,
    tabletop_scene as tabletop_scene,
)
from jaxreg.synth.sequences import (
    TrackingSequence as TrackingSequence,
    tracking_sequence as tracking_sequence,
)

# jaxreg.synth.<module> without importing it first; dir() lists the public names
__getattr__, __dir__ = exports(__name__, {})
