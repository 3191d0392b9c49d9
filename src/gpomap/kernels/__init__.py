"""Covariance functions: point kernels and the multi-support (area) kernels built on them."""

from gpomap.kernels.area import AREA_METHODS, NORMALISATIONS, AreaKernel
from gpomap.kernels.point import Matern32, PointKernel, SquaredExponential, make_point_kernel

__all__ = [
    "AREA_METHODS",
    "NORMALISATIONS",
    "AreaKernel",
    "Matern32",
    "PointKernel",
    "SquaredExponential",
    "make_point_kernel",
]
