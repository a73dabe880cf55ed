"""Tests of ``flylib.camera``."""
