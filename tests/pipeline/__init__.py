"""Tests of ``flylib.pipeline``."""
