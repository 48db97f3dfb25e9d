"""jsve: scene-visibility-based switching for visual-inertial SLAM, in JAX.

    logs -> LogBatch -> SVE features -> rule + ORB-SLAM3 state machine -> replay -> trajectory error

The public API and the map of layers are in `jsve/__init__.pyi`; names are imported when first used
(lazy_loader), so the `jsve` command starts without loading JAX.
"""

import lazy_loader as _lazy

__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
