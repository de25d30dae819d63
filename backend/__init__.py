"""scenesort service, command line and the host-side helpers they share."""

__version__ = "0.1.0"
