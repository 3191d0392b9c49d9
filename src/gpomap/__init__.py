"""gpomap: continuous occupancy maps with multi-support Gaussian processes."""

from gpomap.errors import GpomapError
from gpomap.scans import Scan

__all__ = ["GpomapError", "Scan"]
__version__ = "0.1.0"
