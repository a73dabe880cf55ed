"""Tests of ``flylib.visualization``."""
