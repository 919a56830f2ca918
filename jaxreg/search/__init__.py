"""Nearest-neighbour search with static shapes: the host-built grid/octree and its exact
queries (1-NN, kNN, radius), voxel downsampling, normal estimation and FPFH features with
their matching.

Capacities are chosen on the host and overflow is reported, never silently dropped. May import
:mod:`jaxreg.core` and :mod:`jaxreg.geometry`.
"""

from jaxreg.core._lazy import exports

# The public names, each module imported on first use; jaxreg.search.<module> resolves too.
__getattr__, __dir__ = exports(
    __name__,
    {
        "jaxreg.search.features": ("FPFH", "FeatureMatches", "fpfh", "match_features"),
        "jaxreg.search.neighbors": (
            "NeighborGrid", "build_grid", "knn", "pad_grid", "query_nearest", "radius_search",
            "validate_grid", "voxel_downsample",
        ),
        "jaxreg.search.normals": (
            "NormalEstimate", "NormalStatus", "estimate_normals", "estimate_normals_with_curvature",
        ),
    },
)  # fmt: skip
