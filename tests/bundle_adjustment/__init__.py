"""Tests of ``flylib.bundle_adjustment``."""
