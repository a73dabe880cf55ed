"""The default fly rig's constants, declared once for the tests.

The 7-camera DeepFly3D orbit rig of ``../shared/spec/fly38-rig.yaml`` (and of
``config/config.yaml``): cameras on a circle about the fly, looking at the origin.
"""

from __future__ import annotations

#: Views in config order.
VIEWS: tuple[str, ...] = ("rh", "rm", "rf", "f", "lf", "lm", "lh")
#: Each view's orbit azimuth in degrees (about +z; 0 = the front camera on +x).
AZIMUTHS: dict[str, float] = dict(zip(VIEWS, (-120.0, -90.0, -45.0, 0.0, 45.0, 90.0, 120.0)))
#: Focal length in pixels (both axes).
FOCAL = 22388.125
#: Camera distance from the look-at point (world units, about millimetres).
DISTANCE = 107.463
#: Raw frame ``(height, width)``.
IMAGE_SIZE: tuple[int, int] = (480, 960)
