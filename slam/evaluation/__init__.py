"""Measuring results: trajectory metrics (ATE, RPE) and the map's error against ground-truth depth."""
