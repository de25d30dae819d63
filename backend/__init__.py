"""The scenesort service and command line, a package per concept: wire/ (what crosses the
wire), work/ (long work off the event loop), render/ (the only one that calls the engine),
api/ (the HTTP layer), commands/ (the `scenesort` command), tools/ (a packager's: not in the
wheel Blender installs). tests/backend/test_layout.py checks which imports which."""

__version__ = "0.1.0"
