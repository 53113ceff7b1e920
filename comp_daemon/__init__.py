"""comp-daemon: accuracy compensation for a robotic drilling and riveting cell."""

__version__ = "0.1.0"
