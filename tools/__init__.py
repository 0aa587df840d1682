"""Project tools that are not part of the library: ``python -m tools.<name>`` from the project root."""
