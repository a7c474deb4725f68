"""Map Container: map-based cooperative perception between connected vehicles (the core library).

The core never does network I/O and never imports zenoh or ``services``; given a seed it is
deterministic.
"""

__version__ = "0.1.0"
