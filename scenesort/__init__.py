"""scenesort: the one import name of the project.

Its packages live in the repository's top-level folders (setuptools `package-dir`):
`scenesort.kernels` is kernels/, the engine (Warp device code); `scenesort.backend` is
backend/, the service and the command line. The Blender add-on (addon/) is not part of it:
it talks to the service over HTTP.
"""

__version__ = "0.1.0"
