"""Tests of ``flylib.neuromechfly``."""
