"""Interoperability with other pose tools.

- 2D import as the pose2d stage output: DeepFly3D result pickles, DeepLabCut / Lightning Pose CSV
  and HDF5, SLEAP analysis HDF5 (:func:`import_points2d`).
- Calibrations: Anipose TOML read/write, DeepFly3D calibration pickles, the ``calibrations.csv``
  session index (:func:`load_calibration`).
- Exports: Anipose's pose-3d CSV and per-view DeepLabCut CSVs (:func:`export_result`); NWB with
  ndx-pose in :mod:`flylib.interop.nwb` (imported on demand: it loads pynwb)."""

import lazy_loader as _lazy

# The names and their modules are listed once, in ``__init__.pyi``: pandas loads with the CSV
# readers and writers, not with the calibration files every stage job reads.
__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
