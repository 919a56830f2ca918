"""Nearest-neighbour search with static shapes: the host-built grid/octree and its exact
queries (1-NN, kNN, radius), voxel downsampling, normal estimation and FPFH features with
their matching.

Capacities are chosen on the host and overflow is reported, never silently dropped. May import
:mod:`jaxreg.core` and :mod:`jaxreg.geometry`.
"""

from jaxreg.core._lazy import submodules

__getattr__ = submodules(__name__)  # jaxreg.search.<module> without importing it first
