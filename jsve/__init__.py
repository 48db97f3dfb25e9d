"""jsve: scene-visibility-based switching for visual-inertial SLAM, in JAX.

This file re-exports the public API; a user learns the whole surface from it.
"""

from . import schema as schema
from .schema import RunLog as RunLog

__version__ = "0.1.0"
