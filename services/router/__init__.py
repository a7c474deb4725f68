"""The router role: a Zenoh router process for multi-host fleets (no zenohd binary comes from PyPI)."""
