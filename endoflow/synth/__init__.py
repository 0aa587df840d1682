"""Procedural endoscopy data with exact ground truth, written in the real datasets' native layouts.

- :mod:`endoflow.synth.tube`: the colon geometry (a tube of conical slabs) and exact ray intersection.
- :mod:`endoflow.synth.camera_path`: a colonoscope-like camera trajectory along the tube.
- :mod:`endoflow.synth.texture`: the mucosa texture atlas fixed to the tube surface.
- :mod:`endoflow.synth.render`: shading (light at the camera) and depth of one frame.
- :mod:`endoflow.synth.rooms`: indoor box scenes for the SceneNet layout.
- :mod:`endoflow.synth.writers`: :func:`~endoflow.synth.writers.synthesize_layout`, the entry point.
"""
