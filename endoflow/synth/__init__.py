"""Procedural endoscopy data with exact ground truth, written in the real datasets' native layouts.

One module per part (tube geometry, camera path, texture, shading, indoor rooms, scene presets); the entry
point is :func:`endoflow.synth.writers.synthesize_layout`. See docs/synthetic_data.md.
"""
