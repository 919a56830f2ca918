"""Files in and out: PCD (every variant PCL writes, LZF-compressed included), meshes and point
files through trimesh, RGB-D frames (organized PCD, or a depth PNG with intrinsics JSON), object
masks, depth and colour images, BOP datasets in and BOP result CSVs out, and YCB-Video frames
with their annotated objects (and written as a BOP split).

Readers return metres and raise ``ValueError`` naming the file and what is wrong with it. May
import :mod:`jaxreg.core`, :mod:`jaxreg.geometry` and :mod:`jaxreg.camera`.
"""

from jaxreg.core._lazy import exports
from jaxreg.io._ycbv_bop import ycbv_to_bop as ycbv_to_bop
from jaxreg.io.bop import (
    BopModel as BopModel,
    BopResult as BopResult,
    BopSplit as BopSplit,
    BopTarget as BopTarget,
    read_bop as read_bop,
    read_bop_results as read_bop_results,
    write_bop_results as write_bop_results,
)
from jaxreg.io.clouds import (
    PointCloud as PointCloud,
    load_points as load_points,
    read_pcd as read_pcd,
    write_pcd as write_pcd,
    write_ply as write_ply,
)
from jaxreg.io.frames import read_frame as read_frame, write_frame as write_frame
from jaxreg.io.images import (
    read_depth_counts as read_depth_counts,
    read_image_size as read_image_size,
    read_mask as read_mask,
    read_rgb as read_rgb,
)
from jaxreg.io.ycbv import (
    YcbvFrame as YcbvFrame,
    YcbvInstance as YcbvInstance,
    read_ycbv as read_ycbv,
    read_ycbv_models as read_ycbv_models,
)

# jaxreg.io.<module> without importing it first; dir() lists the public names
__getattr__, __dir__ = exports(__name__, {})
