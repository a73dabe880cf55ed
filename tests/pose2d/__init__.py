"""Tests of ``flylib.pose2d``."""
