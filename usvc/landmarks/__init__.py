"""Landmarks: the SfM points with one SIFT descriptor each, for feature-based pose refinement."""
