"""Measurements built on training and evaluation: Table I's report, the learned legs'
quality, the recovery claim, and the per-run records a long comparison keeps."""
