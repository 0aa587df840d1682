"""Procedural colon renderer: the built-in data, with exact depth and poses, in native layouts."""
