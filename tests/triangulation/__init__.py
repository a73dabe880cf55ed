"""Tests of ``flylib.triangulation``."""
