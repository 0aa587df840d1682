"""The DVC pipeline's stages, thin scripts over the ``endoflow`` library.

``dvc.yaml`` runs each as a module from the project's root (``python -m stages.train``), which puts that root
first on ``sys.path``: a queued DVC experiment, run in its own copy of the project, then imports the copy's
``endoflow`` rather than the environment's editable install (the workspace's files), so an experiment queued
with a change to the library runs that change. Ray's workers import the same files: Ray puts the driver's
working directory on their path.
"""
