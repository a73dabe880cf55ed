"""Tests of ``flylib.refinement``."""
