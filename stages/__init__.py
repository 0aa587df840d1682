"""The DVC pipeline's stages, thin scripts over the ``endoflow`` library.

``dvc.yaml`` runs each as a module from the project's root (``python -m stages.train``), which puts that root
first on ``sys.path``: a DVC experiment queued with a change to the library runs in its own copy of the project
and imports that copy's ``endoflow``, not the workspace's editable install; Ray's workers import the same files
(Ray puts the driver's working directory on their path).
"""
