"""Tests of ``flylib.kinematics``."""
